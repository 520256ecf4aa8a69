"""The ingest every levelX member shares: one recording at a time (bounded memory), its rows brought into the
contract (centres, y up, heading in radians, classes mapped, resampled from the raw frame rate to the member's dt),
its image stored as the map, its prediction problems found (every agent, ``all-agents``, or the member's scenario)
and, once all recordings are read, the global ids and the seeded folds of whole episodes. The specification:
docs/datasets/levelx.md.
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from PIL import Image, UnidentifiedImageError
from rich.text import Text

from ..errors import DataError, UsageError
from ..schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter
from ..util import input_files
from ..util.progress import make_progress, styled
from .base import collect_warnings, warn
from .folds import ceiled_share, fold_arrays
from .levelx import Layout, Recording, RecordingMeta, discover_recordings, read_raw_tracks, read_recording_meta, \
    read_tracks_meta
from .windows import GROUP_TOLERANCE_M, _window_hashes, complete_windows

#: every levelX class -> the contract's agent type (anything else is "unknown", with a warning)
CLASS_TYPES: dict[str, str] = {"car": "vehicle", "van": "vehicle", "truck": "vehicle", "bus": "vehicle",
                               "trailer": "vehicle", "truck_bus": "vehicle", "motorcycle": "motorcycle",
                               "bicycle": "bicycle", "pedestrian": "pedestrian"}
#: classes that drive a motor vehicle of their own (a trailer rides behind its tractor; VRUs are context only)
MOTOR_CLASSES = ("car", "van", "truck", "bus", "truck_bus", "motorcycle")
#: fewer positions than this inside the background image means its scale convention does not fit the tracks
MIN_INSIDE_IMAGE = 0.9
#: highD: below this speed (m/s) the heading is the driving direction's, not the velocity's
HEADING_MIN_SPEED = 1.0
ALL_AGENTS = "all-agents"
#: all-agents: the classes predicted unless --classes says otherwise (a trailer rides behind its tractor)
DEFAULT_CLASSES = tuple(name for name in CLASS_TYPES if name != "trailer")
#: all-agents: a sample every STRIDE frames of an agent (1 s at 0.2 s; neighbouring windows overlap but for one step)
STRIDE = 5
FOLDS = 5
VAL_FRACTION = 0.1
SPLIT_SEED = 0
SHARD_ROWS = 500_000

BASE_SAMPLE_SCHEMA = {"sample_id": pl.Int64, "scene_id": pl.String, "agent_id": pl.Int64, "t0_frame": pl.Int64,
                      "n_past": pl.Int64, "n_future": pl.Int64, "group_id": pl.Int64, "split": pl.String,
                      "fold": pl.String, "episode_id": pl.Int64}
JOINT_SAMPLE_SCHEMA = {**BASE_SAMPLE_SCHEMA, "joint_id": pl.Int64, "role": pl.String, "partner_id": pl.Int64,
                       "decision_frame": pl.Int64}
SCENE_SCHEMA = {"fold": pl.String, "map_world_to_px": pl.List(pl.Float64), "recording_id": pl.Int64,
                "location_id": pl.Int64, "frame_rate": pl.Float64, "upper_lane_markings": pl.List(pl.Float64),
                "lower_lane_markings": pl.List(pl.Float64)}


@dataclass(frozen=True)
class Horizons:
    """Seconds per step and the steps observed (including t0) and predicted."""

    dt: float
    n_past: int
    n_future: int


@dataclass(frozen=True)
class Scenario:
    """A member's joint prediction problem: its name (the --problems value), what it is, and the function that finds
    its pairs in one recording's contract tracks.

    `find(tracks, horizons)` returns one row per pair: target_id, ego_id, t0_frame, decision_frame and any extra
    columns the scenario describes its pairs with (kept on both samples).
    """

    name: str
    description: str
    find: Callable[[pl.DataFrame, Horizons], pl.DataFrame]


@dataclass
class RecordingResult:
    """One recording's contribution: its tracks, scene row, samples and a summary for the lineage."""

    tracks: pl.DataFrame
    scene: dict[str, Any]
    samples: pl.DataFrame
    summary: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------- contract rows


def centred(raw: pl.DataFrame, tracks_meta: pl.DataFrame, layout: Layout) -> pl.DataFrame:
    """Raw rows in the drone layout's columns (xCenter, yCenter, heading in degrees, width, length, x/yVelocity;
    y up). The drone layouts already are; highD's bounding boxes (upper-left corner, y down the image, width along
    x) become centres with y up, its heading the velocity's direction (the driving direction's when nearly
    standing: 180 degrees on the upper lanes, 0 on the lower ones), and its lane and neighbour columns are kept."""
    if "xCenter" in raw.columns:
        return raw
    direction = raw.select("trackId").join(tracks_meta.select("trackId", "drivingDirection"), on="trackId",
                                           how="left").get_column("drivingDirection")
    vx, vy = pl.col("xVelocity"), -pl.col("yVelocity")
    moving = (vx ** 2 + vy ** 2).sqrt() >= HEADING_MIN_SPEED
    return raw.with_columns(direction=direction).select(
        "__row", "trackId", "frame",
        (pl.col("x") + pl.col("width") / 2).alias("xCenter"),
        (-(pl.col("y") + pl.col("height") / 2)).alias("yCenter"),
        pl.when(moving).then(pl.arctan2(vy, vx).degrees())
        .otherwise(pl.when(pl.col("direction") == 1).then(180.0).otherwise(0.0)).alias("heading"),
        pl.col("height").alias("width"), pl.col("width").alias("length"),
        vx.alias("xVelocity"), vy.alias("yVelocity"),
        pl.col("laneId").alias("lane_id"), pl.col("precedingId").alias("preceding_id"),
        pl.col("followingId").alias("following_id"))


def resample(raw: pl.DataFrame, tracks_meta: pl.DataFrame, meta: RecordingMeta, recording: Recording,
             dt: float) -> pl.DataFrame:
    """Contract tracks at `dt`: every (frameRate * dt)-th raw frame, classes mapped, heading in radians; the raw
    class is kept as ``agent_class`` and highD's lane columns as lane_id, preceding_id, following_id."""
    step = meta.frame_rate * dt
    if abs(step - round(step)) > 1e-6 or round(step) < 1:
        raise DataError(f"frameRate {meta.frame_rate:g} Hz cannot be resampled to {1 / dt:g} Hz by keeping every "
                        f"n-th frame", path=recording.path("recordingMeta.csv"), line=2)
    step = int(round(step))
    kept = raw.filter(pl.col("frame") % step == 0).join(
        tracks_meta.select("trackId", pl.col("class").alias("agent_class")), on="trackId", how="left")
    frame = (pl.col("frame") // step).cast(pl.Int64)
    extra = [name for name in ("lane_id", "preceding_id", "following_id") if name in kept.columns]
    return kept.select(
        pl.lit(recording.scene_id).alias("scene_id"),
        pl.col("trackId").alias("agent_id"),
        pl.col("agent_class").replace_strict(CLASS_TYPES, default="unknown", return_dtype=pl.String)
        .alias("agent_type"),
        frame.alias("frame"),
        (frame.cast(pl.Float64) * dt).alias("t"),
        pl.col("xCenter").alias("x"), pl.col("yCenter").alias("y"),
        ((pl.col("heading") + 180.0) % 360.0 - 180.0).radians().alias("heading"),
        pl.col("xVelocity").alias("vx"), pl.col("yVelocity").alias("vy"),
        "length", "width", "agent_class", *extra,
    ).sort("agent_id", "frame")


def background_map(recording: Recording, meta: RecordingMeta, root: Path, tracks: pl.DataFrame,
                   layout: Layout) -> dict[str, Any]:
    """Store the recording's image as a grey-scale PNG under root/maps (once per distinct image) and return the
    scene's map columns: metres per pixel = orthoPxToMeter * the member's scale-down factor, pixel = (x, -y) / that.
    Warns when the tracks do not fall on the image under this convention."""
    path = recording.path(layout.image)
    try:
        with Image.open(input_files.regular_file(path)) as image:
            grey = image.convert("L")
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as error:
        raise DataError(f"cannot open the background image ({error})", path=path) from None
    buffer = io.BytesIO()
    grey.save(buffer, format="PNG")
    data = buffer.getvalue()
    name = f"maps/{hashlib.sha256(data).hexdigest()[:16]}.png"
    target = root / name
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    metres = meta.ortho_px_to_meter * layout.scale_down
    affine = [1.0 / metres, 0.0, 0.0, 0.0, -1.0 / metres, 0.0]
    if tracks.height:
        width, height = grey.size
        inside = tracks.select(((pl.col("x") * affine[0]).is_between(-0.5, width - 0.5)
                                & (pl.col("y") * affine[4]).is_between(-0.5, height - 0.5)).mean()).item()
        if inside < MIN_INSIDE_IMAGE:
            what = "orthoPxToMeter" if layout.ortho_px_to_meter is None else f"{layout.ortho_px_to_meter:g}"
            warn(f"{path}: only {inside:.0%} of the positions fall on the image with metres per pixel = "
                 f"{what} * {layout.scale_down} and pixel = (x, -y) / scale; map crops may be misaligned")
    return {"map_path": name, "map_m_per_px": metres, "map_world_to_px": affine}


def unknown_classes(tracks_meta: pl.DataFrame, recording: Recording) -> None:
    """Warn (once per recording) about classes no agent type is known for: their tracks are kept as "unknown"."""
    unknown = sorted(set(tracks_meta.get_column("class").unique().to_list()) - set(CLASS_TYPES))
    if unknown:
        warn(f"{recording.path('tracksMeta.csv')}: class(es) {', '.join(unknown)} are not levelX classes known to the "
             "ingest; their tracks are kept with agent_type 'unknown' and predicted by no problem")


# ----------------------------------------------------------------------------------------------------- problems


def check_problems(problems: str, scenarios: Sequence[str], classes: object, stride: object) -> str:
    """`problems` checked: all-agents or one of the member's `scenarios`; --classes and --stride belong to
    all-agents only."""
    if problems not in (*scenarios, ALL_AGENTS):
        raise UsageError(f"--problems: {problems!r} is not a problem of this dataset; choose from "
                         f"{', '.join((*scenarios, ALL_AGENTS))}")
    if problems != ALL_AGENTS and (classes is not None or stride is not None):
        raise UsageError(f"--classes and --stride choose the samples of --problems {ALL_AGENTS}, not of {problems}")
    return problems


def parse_classes(classes: Sequence[str] | str | None, default: Sequence[str]) -> tuple[str, ...]:
    """The levelX classes whose agents are predicted (`--classes car,truck`); None keeps the member's default."""
    if classes is None:
        return tuple(default)
    items = classes.split(",") if isinstance(classes, str) else list(classes)
    chosen = tuple(dict.fromkeys(item.strip().lower() for item in items if item.strip()))
    unknown = [name for name in chosen if name not in CLASS_TYPES]
    if not chosen or unknown:
        raise UsageError(f"--classes: {', '.join(unknown) or 'nothing'} is not a levelX class; choose from "
                         f"{', '.join(CLASS_TYPES)}")
    return chosen


def all_agent_samples(tracks: pl.DataFrame, horizons: Horizons, classes: Sequence[str], stride: int) -> pl.DataFrame:
    """Every agent of `classes` at every `stride`-th frame (counted from its first) with n_past + n_future
    consecutive rows: one sample each, its episode the agent (all windows of one agent share a fold)."""
    chosen = tracks.filter(pl.col("agent_class").is_in(list(classes)))
    windows = complete_windows(chosen.select("scene_id", "agent_id", "frame"), horizons.n_past, horizons.n_future)
    first = chosen.group_by("agent_id").agg(pl.col("frame").min().alias("first"))
    return (windows.join(first, on="agent_id")
            .filter((pl.col("t0_frame") - pl.col("first") - (horizons.n_past - 1)) % stride == 0)
            .select("scene_id", "agent_id", "t0_frame", pl.col("agent_id").alias("episode"))
            .with_columns(n_past=pl.lit(horizons.n_past, dtype=pl.Int64),
                          n_future=pl.lit(horizons.n_future, dtype=pl.Int64))
            .sort("t0_frame", "agent_id"))


def joint_samples(pairs: pl.DataFrame, scene_id: str, horizons: Horizons) -> pl.DataFrame:
    """Two samples per pair (target first, then ego) with a recording-local `pair` index; the episode is the
    target (every pair of one target's manoeuvres shares its trajectory, so they share a fold)."""
    base = (pairs.sort("t0_frame", "target_id", "ego_id").with_row_index("pair")
            .with_columns(pl.col("pair").cast(pl.Int64), scene_id=pl.lit(scene_id)))
    extra = [name for name in pairs.columns if name not in ("target_id", "ego_id", "t0_frame")]
    common = ["scene_id", "pair", "t0_frame", *extra, pl.col("target_id").alias("episode")]
    target = base.select(*common, pl.col("target_id").alias("agent_id"), pl.col("ego_id").alias("partner_id"),
                         pl.lit("target").alias("role"))
    ego = base.select(*common, pl.col("ego_id").alias("agent_id"), pl.col("target_id").alias("partner_id"),
                      pl.lit("ego").alias("role"))
    return (pl.concat([target, ego]).sort("pair", pl.col("role") != "target")
            .with_columns(n_past=pl.lit(horizons.n_past, dtype=pl.Int64),
                          n_future=pl.lit(horizons.n_future, dtype=pl.Int64)))


def input_keys(samples: pl.DataFrame, tracks: pl.DataFrame, n_past: int) -> pl.Series:
    """Per sample a hash of its inputs (target window and the windows of everyone present at t0), as
    :func:`windows.identical_input_groups` keys them, so group ids can be assigned across recordings later."""
    windows = _window_hashes(tracks, n_past, GROUP_TOLERANCE_M)
    context = (windows.group_by("scene_id", "frame").agg(pl.col("window_hash").sort().alias("context"))
               .select("scene_id", "frame", pl.col("context").hash(seed=1).alias("context_hash")))
    return (samples.select("scene_id", "agent_id", "t0_frame").with_row_index("__order")
            .join(windows, left_on=["scene_id", "agent_id", "t0_frame"], right_on=["scene_id", "agent_id", "frame"],
                  how="left")
            .join(context, left_on=["scene_id", "t0_frame"], right_on=["scene_id", "frame"], how="left")
            .sort("__order")
            .select(pl.struct("window_hash", "context_hash").hash(seed=2).alias("input_key")).to_series())


def assign_splits(samples: pl.DataFrame, joint: bool) -> pl.DataFrame:
    """Global ids (sample, joint, group, episode) and the seeded fold / train-val assignment by episode.

    `samples` are the per-recording samples of every recording with their `input_key` and `episode` (an agent
    id of the recording); an episode's samples never straddle folds.
    """
    order = ["scene_id", "t0_frame", "pair", pl.col("role") != "target"] if joint else ["scene_id", "t0_frame",
                                                                                      "agent_id"]
    samples = samples.sort(*order).with_row_index("sample_id").with_columns(pl.col("sample_id").cast(pl.Int64))
    if joint:
        samples = samples.with_columns(joint_id=pl.struct("scene_id", "pair").rank("dense").cast(pl.Int64) - 1)
    first_seen = pl.col("sample_id").min().over("input_key")
    samples = samples.with_columns(group_id=first_seen.rank("dense").cast(pl.Int64) - 1)
    first = pl.col("sample_id").min().over("scene_id", "episode")
    samples = samples.with_columns(episode_id=first.rank("dense").cast(pl.Int64) - 1)
    count = int(samples.get_column("episode_id").max() or 0) + 1
    fold_of, is_val = fold_arrays(count, FOLDS, ceiled_share(count, VAL_FRACTION), SPLIT_SEED)
    episode = samples.get_column("episode_id").to_numpy()
    schema = JOINT_SAMPLE_SCHEMA if joint else BASE_SAMPLE_SCHEMA
    extra = [name for name in samples.columns
             if name not in schema and name not in ("pair", "episode", "input_key")]
    return samples.with_columns(
        fold=pl.Series(fold_of[episode].astype(str), dtype=pl.String),
        split=pl.Series(np.where(is_val[episode], "val", "train"), dtype=pl.String),
    ).select(*schema, *extra)


# ----------------------------------------------------------------------------------------------------- pipeline


def read_recording(recording: Recording, layout: Layout, dt: float) -> tuple[RecordingMeta, pl.DataFrame, int]:
    """One recording's meta and its contract tracks at `dt` (checked, centred, resampled) and its raw row count."""
    meta = read_recording_meta(recording, layout)
    tracks_meta = read_tracks_meta(recording, layout, meta)
    raw = read_raw_tracks(recording, tracks_meta, layout, meta)
    raw_rows = raw.height
    unknown_classes(tracks_meta, recording)
    tracks = resample(centred(raw, tracks_meta, layout), tracks_meta, meta, recording, dt)
    return meta, tracks, raw_rows


def ingest_recording(recording: Recording, root: Path, layout: Layout, horizons: Horizons,
                     scenario: Scenario | None, classes: Sequence[str], stride: int,
                     step: Callable[[str], None] = lambda _: None) -> RecordingResult:
    """Read, check, resample and search one recording; store its map under `root`. `scenario` None: every agent
    of `classes` every `stride` frames. `step` is called after each stage with the name of the next."""
    meta, tracks, raw_rows = read_recording(recording, layout, horizons.dt)
    step("map")
    map_columns = background_map(recording, meta, root, tracks, layout)
    step("problems")
    if scenario is None:
        samples = all_agent_samples(tracks, horizons, classes, stride)
    else:
        pairs = scenario.find(tracks, horizons)
        samples = joint_samples(pairs, recording.scene_id, horizons) if pairs.height else pl.DataFrame()
        if not pairs.height:
            warn(f"{recording.path('tracks.csv')}: no {scenario.description}; the recording contributes no samples")
    step("groups")
    if samples.height:
        samples = samples.with_columns(input_key=input_keys(samples, tracks, horizons.n_past))
    step("done")
    markings = meta.lane_markings
    scene = {"dataset": layout.name, "scene_id": recording.scene_id, "location": f"location{meta.location_id}",
             "dt": horizons.dt, "source": ";".join(recording.path(kind).name for kind in layout.file_kinds),
             "fold": None, **map_columns, "recording_id": meta.recording_id, "location_id": meta.location_id,
             "frame_rate": meta.frame_rate,
             **({"upper_lane_markings": list(markings[0]), "lower_lane_markings": list(markings[1])}
                if markings is not None else {})}
    summary = {"recording": f"{recording.number:02d}", "location_id": meta.location_id, "raw_rows": raw_rows,
               "track_rows": tracks.height, "map": map_columns["map_path"], "samples": samples.height}
    return RecordingResult(tracks=tracks, scene=scene, samples=samples, summary=summary)


def ingest_levelx(layout: Layout, raw: str | Path, out: str | Path, *, horizons: Horizons,
                  scenario: Scenario | None, classes: Sequence[str], stride: int,
                  recordings: Sequence[int | str] | None = None, overwrite: bool = False,
                  quiet: bool = False) -> Path:
    """Ingest the `layout` member's recordings from `raw` into `out`: `scenario`'s joint pairs, or (None) every
    agent of `classes` every `stride` frames. Recordings are processed one at a time; the dataset appears at `out`
    only when complete. Returns `out`."""
    if stride < 1:
        raise UsageError(f"--stride must be at least 1, got {stride}")
    raw, out = Path(raw), Path(out)
    selected = discover_recordings(raw, recordings, layout)
    meta = DatasetMeta(dataset=layout.name, dt=horizons.dt, protocol=PROTOCOL_FOLDS)
    scenes, sample_parts, summaries = [], [], []
    problems = scenario.name if scenario is not None else ALL_AGENTS
    with collect_warnings() as warnings, DatasetWriter(out, meta, overwrite=overwrite, shard_rows=SHARD_ROWS) as writer:
        with make_progress(quiet) as progress:
            for recording in selected:
                name = f"recording {recording.number:02d}"
                task = progress.add_task(f"{name}: reading", total=4)

                def step(stage: str, task: Any = task, name: str = name) -> None:
                    progress.update(task, advance=1, description=f"{name}: {stage}")

                result = ingest_recording(recording, writer.root, layout, horizons, scenario, classes, stride, step)
                writer.add_tracks(result.tracks)
                scenes.append(result.scene)
                summaries.append(result.summary)
                if result.samples.height:
                    sample_parts.append(result.samples)
        joint = scenario is not None
        if sample_parts:
            samples = assign_splits(pl.concat(sample_parts, how="diagonal_relaxed"), joint)
        else:
            samples = pl.DataFrame(schema=JOINT_SAMPLE_SCHEMA if joint else BASE_SAMPLE_SCHEMA)
            warn(f"{raw}: no {scenario.description if joint else 'agent with a complete window'} in any recording; "
                 "the dataset has no samples")
        scene_table = pl.DataFrame(scenes, schema_overrides=SCENE_SCHEMA)
        writer.finish(scene_table, samples, lineage={
            "raw": str(raw.resolve()), "member": layout.name, "problems": problems, "n_past": horizons.n_past,
            "n_future": horizons.n_future, "classes": list(classes) if not joint else None,
            "stride": stride if not joint else None,
            "raw_frame_rates": sorted({scene["frame_rate"] for scene in scenes}),
            "background_scale_down": layout.scale_down, "folds": FOLDS, "val_fraction": VAL_FRACTION,
            "split_seed": SPLIT_SEED, "recordings": summaries, "warnings": warnings})
    return out


def wrote_line(out: Path, summary: dict[str, Any]) -> Text:
    """The line after a levelX ingest: recordings, rows, samples (and pairs, for a joint scenario), folds, maps."""
    problems = (summary.get("lineage") or {}).get("problems", ALL_AGENTS)
    pairs = f" ({summary['samples'] // 2} {problems} pairs)" if problems != ALL_AGENTS else ""
    return styled(("wrote", "green"), f" {out}: {summary['scenes']} recordings, {summary['track_rows']} track rows, "
                  f"{summary['samples']} samples{pairs}, {len(summary['folds'])} folds, maps: {summary['has_map']}")
