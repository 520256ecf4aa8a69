"""`trajflow ingest round`: rounD (levelX) gap-acceptance scenarios as a unified Parquet dataset, with maps: target
and ego of every accepted or rejected gap, 15 past / 25 (up to 35) future steps at 0.2 s, 5 folds of whole
situations. The specification (scenario definition, horizons, folds, maps): docs/datasets/round.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from rich.text import Text

from ..errors import DataError, UsageError
from ..schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter
from ..util.progress import make_progress, styled
from .base import Ingest, collect_warnings, warn
from .folds import ceiled_share, fold_arrays
from .levelx import (FILE_KINDS, ROUND, Recording, RecordingMeta, discover_recordings, read_raw_tracks,
                     read_recording_meta, read_tracks_meta)
from .levelx_pipeline import (ALL_AGENTS, DEFAULT_CLASSES, MOTOR_CLASSES, STRIDE, Horizons, background_map,
                              check_problems, ingest_levelx, input_keys, parse_classes, resample)
from .levelx_pipeline import wrote_line as all_agents_line
from .round_geometry import (GeometryConfig, GeometryError, RoundaboutGeometry, geometry_for, geometry_option,
                             infer_geometry)

DATASET = "round"
#: the --problems value of the scenario below (the default); "all-agents" is the other
GAP_ACCEPTANCE = "gap-acceptance"
DT = 0.2
N_PAST, N_FUTURE, N_FUTURE_MAX = 15, 25, 35
#: the decision horizon counts at most this many steps, plus HORIZON_MARGIN (Schumann et al.: 2 * n_past)
DECISION_HORIZON_CAP = 2 * N_PAST
HORIZON_MARGIN = 5
#: braking deceleration (m/s^2) the ego is assumed to manage when the target cuts in: past the last frame at
#: which it could still stop before the conflict zone (t_crit) a prediction is useless (Schumann et al.: a_brake)
CRITICAL_DECELERATION = 4.0
#: the levelX tools display rounD backgrounds downscaled by this factor: metres per pixel = orthoPxToMeter * 10
BACKGROUND_SCALE_DOWN = ROUND.scale_down
FOLDS = 5
VAL_FRACTION = 0.1
SPLIT_SEED = 0
SHARD_ROWS = 500_000

SAMPLE_SCHEMA = {"sample_id": pl.Int64, "scene_id": pl.String, "agent_id": pl.Int64, "t0_frame": pl.Int64,
                 "n_past": pl.Int64, "n_future": pl.Int64, "group_id": pl.Int64, "split": pl.String,
                 "fold": pl.String, "joint_id": pl.Int64, "n_future_max": pl.Int64, "role": pl.String,
                 "partner_id": pl.Int64, "gap": pl.String, "decision_frame": pl.Int64, "conflict_frame": pl.Int64,
                 "critical_frame": pl.Int64, "entry_arm": pl.Int64, "situation_id": pl.Int64}
#: scenes columns describing the roundabout geometry used -> RoundaboutGeometry field
GEOMETRY_COLUMNS = {"centre_x": "centre_x", "centre_y": "centre_y", "inner_radius": "inner_radius",
                    "outer_radius": "outer_radius", "circulation": "direction", "geometry_source": "source"}

SCENE_SCHEMA = {"fold": pl.String, "map_world_to_px": pl.List(pl.Float64), "centre_x": pl.Float64,
                "centre_y": pl.Float64, "inner_radius": pl.Float64, "outer_radius": pl.Float64,
                "circulation": pl.Int64, "geometry_source": pl.String, "recording_id": pl.Int64,
                "location_id": pl.Int64, "frame_rate": pl.Float64}


@dataclass
class RecordingResult:
    """One recording's contribution: its tracks, scene row, samples and a summary for the lineage."""

    tracks: pl.DataFrame
    scene: dict[str, Any]
    samples: pl.DataFrame
    summary: dict[str, Any] = field(default_factory=dict)


# -------------------------------------------------------------------------------------------------- scenarios


def _wrap(angle: pl.Expr) -> pl.Expr:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _polar(frame: pl.DataFrame, geometry: RoundaboutGeometry) -> pl.DataFrame:
    dx, dy = pl.col("x") - geometry.centre_x, pl.col("y") - geometry.centre_y
    return frame.with_columns(r=(dx ** 2 + dy ** 2).sqrt(), theta=pl.arctan2(dy, dx))


def motor_tracks(tracks: pl.DataFrame) -> pl.DataFrame:
    """Rows of the vehicles that can be target or ego, sorted by (agent_id, frame)."""
    return tracks.filter(pl.col("agent_class").is_in(MOTOR_CLASSES)).select("agent_id", "frame", "x", "y", "vx", "vy",
                                                                             "length")


def _targets(motor: pl.DataFrame, geometry: RoundaboutGeometry) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Per motor vehicle its span; and the vehicles that qualify as targets, with t_A and arm direction phi."""
    outer, margin = geometry.outer_radius, geometry.approach_margin
    inside, near = pl.col("r") < outer, pl.col("r") < outer + margin
    stats = motor.group_by("agent_id", maintain_order=True).agg(
        first_frame=pl.col("frame").first(), last_frame=pl.col("frame").last(),
        r_first=pl.col("r").first(), r_min=pl.col("r").min(),
        frame_a=pl.col("frame").filter(inside).first(), theta_a=pl.col("theta").filter(inside).first(),
        x0=pl.col("x").first(), y0=pl.col("y").first(),
        xe=pl.col("x").filter(near).first(), ye=pl.col("y").filter(near).first())
    arm = pl.arctan2(pl.col("y0") - pl.col("ye"), pl.col("x0") - pl.col("xe"))
    radial = pl.arctan2(pl.col("ye") - geometry.centre_y, pl.col("xe") - geometry.centre_x)
    long_approach = ((pl.col("x0") - pl.col("xe")) ** 2 + (pl.col("y0") - pl.col("ye")) ** 2).sqrt() >= 2.0
    targets = (stats.filter(pl.col("frame_a").is_not_null() & (pl.col("r_min") >= geometry.inner_radius)
                            & (pl.col("r_first") > outer + margin))
               .with_columns(phi=pl.when(long_approach).then(arm).otherwise(radial)))
    return stats, targets


def extract_situations(tracks: pl.DataFrame, geometry: RoundaboutGeometry) -> pl.DataFrame:
    """Gap-acceptance situations of one recording (module docstring): one row per (target, ego, conflict frame)
    with gap, t_A, t_C, decision frame, t0, critical frame, n_future_max and entry arm. Situations whose t0 is at
    or after the critical frame are still listed, marked ``after_critical``; the caller drops (and counts) them."""
    motor = _polar(motor_tracks(tracks), geometry)
    stats, targets = _targets(motor, geometry)
    outer = geometry.outer_radius
    target_rows = motor.join(targets.select("agent_id", "phi", "frame_a", "theta_a"), on="agent_id").select(
        pl.col("agent_id").alias("target_id"), "frame", pl.col("r").alias("r_t"), "phi", "frame_a", "theta_a")
    # an ego matters only inside the carriageway (its conflict-zone arrival and its open-gap frames lie there),
    # which keeps the pair table to a fraction of all co-present vehicle pairs
    ego_rows = motor.filter(pl.col("r") <= outer).select(
        pl.col("agent_id").alias("ego_id"), "frame", pl.col("r").alias("r_e"), pl.col("theta").alias("theta_e"),
        circulating_speed(geometry).alias("v_e"), pl.col("length").alias("length_e"))
    pair = ["target_id", "ego_id"]
    psi = _wrap((pl.col("theta_e") - pl.col("phi")) * geometry.direction)
    contested = (pl.col("psi") > 0) & (pl.col("psi") < geometry.conflict_angle)
    pairs = (target_rows.join(ego_rows, on="frame").filter(pl.col("ego_id") != pl.col("target_id"))
             .with_columns(psi=psi).with_columns(contested=contested).sort(*pair, "frame"))
    # entering the conflict zone from the previous frame inside the carriageway (rows are sorted by pair, frame)
    follows = ((pl.col("target_id").shift(1) == pl.col("target_id")) & (pl.col("ego_id").shift(1) == pl.col("ego_id"))
               & (pl.col("frame").shift(1) == pl.col("frame") - 1))
    arrives = pl.col("contested") & follows & ~pl.col("contested").shift(1).fill_null(False)
    spans = stats.select("agent_id", "first_frame", "last_frame")
    events = (pairs.filter(arrives).select(*pair, pl.col("frame").alias("conflict_frame"), "frame_a", "theta_a")
              .join(spans.rename({"agent_id": "ego_id", "first_frame": "ego_first", "last_frame": "ego_last"}),
                    on="ego_id")
              .filter(pl.col("ego_first") <= pl.col("frame_a")))
    rejected = events.filter(pl.col("conflict_frame") <= pl.col("frame_a")).with_columns(gap=pl.lit("rejected"))
    accepted = (events.filter(pl.col("conflict_frame") > pl.col("frame_a"))
                .sort("target_id", "conflict_frame", "ego_id")
                .group_by("target_id", maintain_order=True).first().with_columns(gap=pl.lit("accepted")))
    situations = pl.concat([rejected, accepted.select(rejected.columns)]).with_columns(
        decision_frame=pl.when(pl.col("gap") == "accepted").then(pl.col("frame_a")).otherwise(pl.col("conflict_frame")))
    return _prediction_times(pairs, situations, spans, geometry)


def _prediction_times(pairs: pl.DataFrame, situations: pl.DataFrame, spans: pl.DataFrame,
                      geometry: RoundaboutGeometry) -> pl.DataFrame:
    """t_S, t0 and the horizons of each situation; situations without an open gap or enough data are dropped."""
    key = ["target_id", "ego_id", "conflict_frame"]
    outer = geometry.outer_radius
    undecided = ((pl.col("r_e") <= outer) & (pl.col("r_e") >= outer - geometry.ego_band) & (pl.col("psi") < 0)
                 & (pl.col("r_t") > outer))
    rows = (pairs.select("target_id", "ego_id", "frame", "r_t", "r_e", "psi", "v_e", "length_e")
            .join(situations.select(*key, "decision_frame"), on=["target_id", "ego_id"])
            .filter(pl.col("frame") < pl.col("decision_frame"))
            .sort(*key, "frame")
            .with_columns(open=undecided))
    # a run of open frames starts where the previous frame of the situation is missing or not open; t_S is the
    # start of the last run before the decision
    follows = pl.all_horizontal([pl.col(name).shift(1) == pl.col(name) for name in key]) & (
        pl.col("frame").shift(1) == pl.col("frame") - 1)
    starts = (rows.filter(pl.col("open") & ~(follows & pl.col("open").shift(1)).fill_null(False))
              .group_by(key).agg(pl.col("frame").max().alias("start_frame")))
    critical = critical_frames(rows.join(starts, on=key), key, geometry)
    target_span = spans.rename({"agent_id": "target_id", "first_frame": "target_first", "last_frame": "target_last"})
    t0 = pl.max_horizontal("start_frame", pl.col("target_first") + N_PAST - 1, pl.col("ego_first") + N_PAST - 1)
    common_last = pl.min_horizontal("target_last", "ego_last")
    needed = pl.max_horizontal(pl.lit(N_FUTURE), pl.min_horizontal(pl.lit(DECISION_HORIZON_CAP),
                                                                  pl.col("conflict_frame") - pl.col("t0_frame"))
                               + HORIZON_MARGIN)
    arms = np.asarray(geometry.entry_angles, dtype=np.float64)
    timed = (situations.join(starts, on=key).join(target_span, on="target_id")
             .join(critical, on=key, how="left")
             .with_columns(t0_frame=t0, common_last=common_last)
             .filter((pl.col("t0_frame") < pl.col("decision_frame"))
                     & (pl.col("t0_frame") + N_FUTURE <= pl.col("common_last")))
             .with_columns(n_future_max=pl.min_horizontal(needed, pl.col("common_last") - pl.col("t0_frame"),
                                                          pl.lit(N_FUTURE_MAX)).cast(pl.Int64),
                           after_critical=(pl.col("t0_frame") >= pl.col("critical_frame")).fill_null(False)))
    entry_arm = (_nearest_arm(timed.get_column("theta_a").to_numpy(), arms) if len(arms)
                 else np.full(timed.height, -1, dtype=np.int64))
    return (timed.with_columns(entry_arm=pl.Series(entry_arm, dtype=pl.Int64))
            .select("target_id", "ego_id", "gap", "frame_a", "conflict_frame", "decision_frame", "start_frame",
                    "critical_frame", "t0_frame", "after_critical", "n_future_max", "entry_arm")
            .sort("t0_frame", "target_id", "ego_id", "conflict_frame"))


def circulating_speed(geometry: RoundaboutGeometry) -> pl.Expr:
    """Speed (m/s) along the circulation direction: the velocity's component tangential to the roundabout, positive
    when the vehicle moves with the traffic (needs the polar angle ``theta`` and ``vx`` / ``vy``)."""
    return geometry.direction * (pl.col("vy") * pl.col("theta").cos() - pl.col("vx") * pl.col("theta").sin())


def critical_frames(rows: pl.DataFrame, key: Sequence[str], geometry: RoundaboutGeometry,
                    deceleration: float = CRITICAL_DECELERATION) -> pl.DataFrame:
    """t_crit per situation: the first frame in [t_S, decision) at which the ego can no longer stop before the
    conflict zone by braking at `deceleration`.

    Why: the prediction serves the ego, which offers the gap and has to react if the target takes it. Once its
    front is closer to the conflict zone than its braking distance v^2 / (2 * deceleration), yielding is no
    longer possible, the situation is no longer a decision and predicting it is of no use (Schumann et al.'s
    framework drops such prediction times; its gap-acceptance scenario brakes at a_brake = 4 m/s^2 and its
    template takes the first such time after t_start, or t_start itself when the gap opens already critical).

    The ego's distance is the arc from its position to the target's arm at its current radius, r_e * (-psi),
    less half its length; its speed ``v_e`` is the velocity component along the circulation (negative speeds
    count as standing). Inside the zone (0 <= psi < conflict_angle) the distance is negative, so the ego is
    critical; further downstream (psi >= conflict_angle) it has passed and is not. (The framework measures the
    arc on the lane centre, R - 1.75 m, for a 5 m vehicle, and takes the speed from the change of that distance
    over 0.2 s; the tracks give each ego's own radius, length and velocity. Its rule, t_D < D / (2 a t_D) with
    t_D = D / v, is the same inequality D < v^2 / (2 a).)

    `rows` holds one row per situation (`key`) and frame with frame, start_frame, decision_frame, psi, r_e, v_e
    and length_e. Returns `key` + ``critical_frame`` for the situations that have one.
    """
    distance = pl.col("r_e") * -pl.col("psi") - pl.col("length_e") / 2
    braking = pl.col("v_e").clip(lower_bound=0.0) ** 2 / (2 * deceleration)
    cannot_stop = (pl.col("psi") < geometry.conflict_angle) & (distance < braking)
    window = (pl.col("frame") >= pl.col("start_frame")) & (pl.col("frame") < pl.col("decision_frame"))
    return (rows.filter(window & cannot_stop)
            .group_by(list(key)).agg(pl.col("frame").min().alias("critical_frame")))


def _nearest_arm(angles: np.ndarray, arms: np.ndarray) -> np.ndarray:
    """Index of the entry arm closest (circularly) to each angle."""
    difference = np.abs((angles[:, None] - arms[None, :] + np.pi) % (2 * np.pi) - np.pi)
    return difference.argmin(axis=1).astype(np.int64)


def situation_samples(situations: pl.DataFrame, scene_id: str) -> pl.DataFrame:
    """Two samples per situation (target first, then ego) with a recording-local `pair` index."""
    base = situations.with_row_index("pair").with_columns(pl.col("pair").cast(pl.Int64), scene_id=pl.lit(scene_id))
    common = ["scene_id", "pair", "t0_frame", "gap", "decision_frame", "conflict_frame", "critical_frame", "entry_arm",
              "n_future_max"]
    target = base.select(*common, pl.col("target_id").alias("agent_id"), pl.col("ego_id").alias("partner_id"),
                         pl.lit("target").alias("role"))
    ego = base.select(*common, pl.col("ego_id").alias("agent_id"), pl.col("target_id").alias("partner_id"),
                      pl.lit("ego").alias("role"))
    return (pl.concat([target, ego]).sort("pair", pl.col("role") != "target")
            .with_columns(n_past=pl.lit(N_PAST, dtype=pl.Int64), n_future=pl.lit(N_FUTURE, dtype=pl.Int64)))


# ------------------------------------------------------------------------------------------------ folds, groups


def assign_splits(samples: pl.DataFrame) -> pl.DataFrame:
    """Global ids (sample, joint, group, situation) and the seeded fold / train-val assignment by situation.

    `samples` are the per-recording samples of every recording, each with its `input_key`.
    """
    samples = (samples.sort("scene_id", "t0_frame", "pair", pl.col("role") != "target")
               .with_columns(joint_id=pl.struct("scene_id", "pair").rank("dense").cast(pl.Int64) - 1)
               .with_row_index("sample_id").with_columns(pl.col("sample_id").cast(pl.Int64)))
    first_seen = pl.col("sample_id").min().over("input_key")
    samples = samples.with_columns(group_id=first_seen.rank("dense").cast(pl.Int64) - 1)
    # a situation is one target's entering manoeuvre: all its gaps (rejected ones and the accepted one) with
    # their egos; the samples of a situation share the target's trajectory and stay in one fold
    target = pl.when(pl.col("role") == "target").then(pl.col("agent_id")).otherwise(pl.col("partner_id"))
    first = pl.col("sample_id").min().over("scene_id", target)
    samples = samples.with_columns(situation_id=first.rank("dense").cast(pl.Int64) - 1)
    count = int(samples.get_column("situation_id").max() or 0) + 1
    fold_of, is_val = fold_arrays(count, FOLDS, ceiled_share(count, VAL_FRACTION), SPLIT_SEED)
    situation = samples.get_column("situation_id").to_numpy()
    return samples.with_columns(
        fold=pl.Series(fold_of[situation].astype(str), dtype=pl.String),
        split=pl.Series(np.where(is_val[situation], "val", "train"), dtype=pl.String),
    ).select(*SAMPLE_SCHEMA)


# ----------------------------------------------------------------------------------------------------- pipeline


def _geometry(config: GeometryConfig | None, meta: RecordingMeta, tracks: pl.DataFrame,
              recording: Recording) -> RoundaboutGeometry | None:
    """The configured geometry of the recording's location, else one inferred from its traffic (None + warning
    when there is too little circulating traffic to infer it)."""
    given = geometry_for(config, meta.location_id)
    if given is not None:
        return given
    try:
        return infer_geometry(motor_tracks(tracks), DT, where=str(recording.path("tracks.csv")))
    except GeometryError as error:
        warn(f"{error}; recording {recording.number:02d} contributes no samples")
        return None


def ingest_recording(recording: Recording, root: Path, geometry: GeometryConfig | None,
                     step: Callable[[str], None] = lambda _: None) -> RecordingResult:
    """Read, check, resample and search one recording; store its map under `root`.

    `step` is called after each of the four stages (reading, map, scenarios, groups) with the name of the next.
    """
    meta = read_recording_meta(recording)
    tracks_meta = read_tracks_meta(recording, ROUND, meta)
    raw = read_raw_tracks(recording, tracks_meta, ROUND, meta)
    raw_rows = raw.height
    tracks = resample(raw, tracks_meta, meta, recording, DT)
    del raw
    step("map")
    map_columns = background_map(recording, meta, root, tracks, ROUND)
    step("scenarios")
    used = _geometry(geometry, meta, tracks, recording)
    situations = extract_situations(tracks, used) if used is not None else None
    after_critical = 0
    if situations is not None:
        # the framework's exclusion of prediction times at or after t_crit (too late for the ego to act on)
        after_critical = int(situations.get_column("after_critical").sum())
        situations = situations.filter(~pl.col("after_critical"))
    if situations is not None and situations.height == 0:
        dropped = f" ({after_critical} found too late, at or after their critical time)" if after_critical else ""
        warn(f"{recording.path('tracks.csv')}: no gap-acceptance situation (a vehicle entering while another "
              f"circulates towards its arm){dropped}; the recording contributes no samples")
    step("groups")
    if situations is not None and situations.height:
        samples = situation_samples(situations, recording.scene_id)
        samples = samples.with_columns(input_key=input_keys(samples, tracks, N_PAST))
    else:
        samples = pl.DataFrame()
    step("done")
    geometry_values = used.to_dict() if used is not None else {}
    scene = {"dataset": DATASET, "scene_id": recording.scene_id, "location": f"location{meta.location_id}",
             "dt": DT, "source": ";".join(recording.path(kind).name for kind in FILE_KINDS), "fold": None,
             **map_columns, "recording_id": meta.recording_id, "location_id": meta.location_id,
             "frame_rate": meta.frame_rate,
             **{column: geometry_values.get(name) for column, name in GEOMETRY_COLUMNS.items()}}
    gaps = (situations.get_column("gap").value_counts().rows() if situations is not None and situations.height
            else [])
    summary = {"recording": f"{recording.number:02d}", "location_id": meta.location_id, "raw_rows": raw_rows,
               "track_rows": tracks.height, "map": map_columns["map_path"], "geometry": geometry_values or None,
               "situations": dict(gaps), "excluded_after_critical": after_critical,
               "needing_more_than_n_future": (int((situations.get_column("n_future_max") > N_FUTURE).sum())
                                              if situations is not None else 0)}
    return RecordingResult(tracks=tracks, scene=scene, samples=samples, summary=summary)


def ingest_round(raw: str | Path, out: str | Path, *, recordings: Sequence[int | str] | None = None,
                 geometry: GeometryConfig | None = None, problems: str = GAP_ACCEPTANCE,
                 classes: Sequence[str] | str | None = None, stride: int | None = None, overwrite: bool = False,
                 quiet: bool = False) -> Path:
    """Ingest rounD recordings from `raw` (a folder, its data/ sub-folder or one recording's file) into `out`.

    `recordings` selects recording numbers; `geometry` is one RoundaboutGeometry for all recordings or a mapping
    locationId -> geometry (locations not in it are inferred from their own traffic). `problems` "all-agents"
    predicts every agent of `classes` every `stride` frames instead of the gap-acceptance pairs (levelx_pipeline).
    Recordings are processed one at a time; the dataset appears at `out` only when complete. Returns `out`.
    """
    if check_problems(problems, (GAP_ACCEPTANCE,), classes, stride) == ALL_AGENTS:
        if geometry is not None:
            raise UsageError("--geometry belongs to the gap-acceptance problems, not to --problems all-agents")
        return ingest_levelx(ROUND, raw, out, horizons=Horizons(DT, N_PAST, N_FUTURE), scenario=None,
                             classes=parse_classes(classes, DEFAULT_CLASSES), stride=stride or STRIDE,
                             recordings=recordings, overwrite=overwrite, quiet=quiet)
    raw, out = Path(raw), Path(out)
    selected = discover_recordings(raw, recordings)
    meta = DatasetMeta(dataset=DATASET, dt=DT, protocol=PROTOCOL_FOLDS)
    scenes, sample_parts, summaries = [], [], []
    with collect_warnings() as warnings, DatasetWriter(out, meta, overwrite=overwrite, shard_rows=SHARD_ROWS) as writer:
        with make_progress(quiet) as progress:
            for recording in selected:
                name = f"recording {recording.number:02d}"
                task = progress.add_task(f"{name}: reading", total=4)

                def step(stage: str, task: Any = task, name: str = name) -> None:
                    progress.update(task, advance=1, description=f"{name}: {stage}")

                result = ingest_recording(recording, writer.root, geometry, step)
                writer.add_tracks(result.tracks)
                scenes.append(result.scene)
                summaries.append(result.summary)
                if result.samples.height:
                    sample_parts.append(result.samples)
        if sample_parts:
            samples = assign_splits(pl.concat(sample_parts))
        else:
            samples = pl.DataFrame(schema=SAMPLE_SCHEMA)
            warn(f"{raw}: no gap-acceptance situation in any recording; the dataset has no samples")
        scene_table = pl.DataFrame(scenes, schema_overrides=SCENE_SCHEMA)
        writer.finish(scene_table, samples, lineage={
            "raw": str(raw.resolve()), "n_past": N_PAST, "n_future": N_FUTURE, "n_future_max": N_FUTURE_MAX,
            "raw_frame_rates": sorted({scene["frame_rate"] for scene in scenes}),
            "critical_deceleration": CRITICAL_DECELERATION,
            "excluded_after_critical": sum(summary["excluded_after_critical"] for summary in summaries),
            "background_scale_down": BACKGROUND_SCALE_DOWN, "folds": FOLDS, "val_fraction": VAL_FRACTION,
            "split_seed": SPLIT_SEED, "recordings": summaries, "warnings": warnings})
    return out


def wrote_line(out: Path, summary: dict[str, Any]) -> Text:
    """The line after the ingest: recordings, rows, samples (two per target/ego pair), folds and maps."""
    if (summary.get("lineage") or {}).get("problems") == ALL_AGENTS:
        return all_agents_line(out, summary)
    return styled(("wrote", "green"), f" {out}: {summary['scenes']} recordings, {summary['track_rows']} track rows, "
                  f"{summary['samples']} samples ({summary['samples'] // 2} target/ego pairs), "
                  f"{len(summary['folds'])} folds, maps: {summary['has_map']}")


ADAPTER = Ingest(name="round", dataset=DATASET, dt=DT, folds=tuple(str(fold) for fold in range(FOLDS)),
                 raw="the folder of levelX rounD recordings", function=ingest_round, summary=wrote_line,
                 converters={"geometry": geometry_option})
