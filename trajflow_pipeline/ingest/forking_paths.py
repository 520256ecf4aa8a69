"""`trajflow ingest forking-paths`: the Forking Paths multi-future release as a unified Parquet dataset: the x-agent
of every annotated future with a past shared by its moment (one group), 8 past + 12 future steps at 0.4 s, 5 folds
of whole moments. The specification (file names, pixel scale, resampling, forks): docs/datasets/forking_paths.md.
"""

from __future__ import annotations

import io
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

from ..errors import DataError, TrajflowError, UsageError
from ..schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter
from ..util import input_files
from ..util.bounds import check_seed
from ..util.progress import make_progress
from .base import Ingest, warn
from .folds import assign_folds
from .windows import identical_input_groups

DATASET = "forking_paths"
DT = 0.4
N_PAST, N_FUTURE = 8, 12
DEFAULT_CAMERA = "cam4"
#: x-agent positions of two futures closer than this (metres) count as the same (shared past)
FORK_TOLERANCE_M = 0.01
#: vehicles' agent ids are their track ids plus this offset, so that people and vehicles never share an id
VEHICLE_ID_OFFSET = 1_000_000
FOLDS = 5
VAL_FRACTION = 0.1

#: ETH/UCY scenes of the release are rendered at 25 fps, the VIRAT ones at 30 fps (release README)
ETHUCY_PREFIXES = ("zara", "eth", "hotel")
ETHUCY_FPS, VIRAT_FPS = 25.0, 30.0
#: last observed raw frame of the release's own multi-future split (get_prepared_data_multifuture.py): the fork
#: of a moment whose futures never diverge
ETHUCY_OBS_END_FRAME, VIRAT_OBS_END_FRAME = 102, 124

IMAGE_WIDTH_PX = 1920
#: cam4 (top-down) pose per scene from Multiverse's recording_cameras: height above z = 0 (m), pitch (deg), fov (deg)
CAM4_GEOMETRY: dict[str, tuple[float, float, float]] = {
    "zara01": (54.799969, -84.997345, 35.0),
    "zara02": (54.799969, -84.997345, 35.0),
    "eth": (91.099937, -79.995010, 50.0),
    "hotel": (30.865358, -88.958252, 50.0),
    "0000": (48.219952, -87.999031, 70.0),
    "0400": (101.969933, -83.868240, 55.0),
    "0401": (70.706039, -80.815720, 65.0),
    "0500": (52.925720, -78.599899, 70.0),
}

CLASS_TYPES: dict[str, str] = {"Person": "pedestrian", "Vehicle": "vehicle"}
RECORD_FIELDS = ("class_name", "is_x_agent", "bbox", "frame_id", "track_id")
NAME_PATTERN = re.compile(r"^(?P<scene>.+)_(?P<moment>\d+)_(?P<xagent>\d+)_(?P<dest>\d+)_(?P<annotator>[^_]+)_"
                          r"(?P<camera>cam\d+)$")
NAME_FORMAT = "<scene>_<moment>_<xagentID>_<destIdx>_<annotatorID>_<cam>.json"
#: tolerance (in raw frames) of the grid arithmetic
_EPS = 1e-6


def cam4_metres_per_pixel(scene: str) -> float:
    """Default ground sampling distance of the top-down camera at the image centre (see the module docstring)."""
    height, pitch, fov = CAM4_GEOMETRY[scene]
    distance = height / math.sin(math.radians(abs(pitch)))
    return 2.0 * distance * math.tan(math.radians(fov / 2.0)) / IMAGE_WIDTH_PX


def default_fps(scene: str) -> float:
    """25 fps for the ETH/UCY scenes of the release, 30 fps for the VIRAT ones."""
    return ETHUCY_FPS if scene.startswith(ETHUCY_PREFIXES) else VIRAT_FPS


def default_scale(scene: str, camera: str) -> float | None:
    """Metres per pixel when none is given: known for the top-down cam4 of the release's scenes only."""
    return cam4_metres_per_pixel(scene) if camera == DEFAULT_CAMERA and scene in CAM4_GEOMETRY else None


def fallback_fork_frame(scene: str) -> int:
    """The release's last observed raw frame: the fork of a moment whose annotated futures never diverge."""
    return ETHUCY_OBS_END_FRAME if scene.startswith(ETHUCY_PREFIXES) else VIRAT_OBS_END_FRAME


@dataclass(frozen=True)
class BboxFile:
    """One annotation file and what its name says: which moment, x-agent, destination, annotator and camera."""

    path: Path
    scene: str
    moment: int
    xagent: int
    dest: int
    annotator: str
    camera: str

    @property
    def stem(self) -> str:
        return self.path.stem

    @property
    def moment_key(self) -> str:
        """`<scene>_<moment>_<xagentID>`: the files sharing it are futures of one past."""
        return f"{self.scene}_{self.moment}_{self.xagent}"


def parse_name(path: Path) -> BboxFile:
    """Split a file name into its fields, from the right (scene names may hold digits and underscores)."""
    match = NAME_PATTERN.match(path.stem)
    if path.suffix != ".json" or match is None:
        raise DataError(f"file name does not follow {NAME_FORMAT}", path=path)
    return BboxFile(path=path, scene=match["scene"], moment=int(match["moment"]), xagent=int(match["xagent"]),
                    dest=int(match["dest"]), annotator=match["annotator"], camera=match["camera"])


def find_bbox_folder(raw: Path) -> Path:
    """Accept the release root, its `next_x_v1_dataset` folder or the `bbox` folder itself."""
    if not raw.exists():
        raise DataError("Forking Paths folder not found", path=raw)
    if not raw.is_dir():
        raise DataError("expected a folder (the release root, next_x_v1_dataset/ or its bbox/ folder)", path=raw)
    for candidate in (raw / "next_x_v1_dataset" / "bbox", raw / "bbox", raw):
        if candidate.is_dir() and any(candidate.glob("*.json")):
            return candidate
    raise DataError("no bounding-box annotations: expected next_x_v1_dataset/bbox/*.json, bbox/*.json or *.json",
                    path=raw)


def discover_files(bbox_dir: Path, camera: str) -> list[BboxFile]:
    """The chosen camera's annotation files, sorted by name; other cameras' files are ignored."""
    parsed = [parse_name(path) for path in sorted(bbox_dir.glob("*.json"))]
    chosen = [item for item in parsed if item.camera == camera]
    if not chosen:
        found = sorted({item.camera for item in parsed})
        raise DataError(f"no {camera} files among {len(parsed)} annotation files (cameras present: "
                        f"{', '.join(found)}); choose one with --camera", path=bbox_dir)
    return chosen


# --- reading one annotation file -------------------------------------------------------------------------------

def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _record_problem(record: Any) -> str | None:
    """What is structurally wrong with one parsed record (missing field, wrong type), or None."""
    if not isinstance(record, dict):
        return f"expected an object with {', '.join(RECORD_FIELDS)}, got {type(record).__name__}"
    for name in RECORD_FIELDS:
        if name not in record or record[name] is None:
            return f"missing field '{name}'"
    if not isinstance(record["class_name"], str):
        return f"class_name must be a string, got {record['class_name']!r}"
    for name in ("is_x_agent", "frame_id", "track_id"):
        if not (_is_number(record[name]) or (name == "is_x_agent" and isinstance(record[name], bool))):
            return f"{name} must be a number, got {record[name]!r}"
    bbox = record["bbox"]
    if not isinstance(bbox, list) or len(bbox) != 4 or not all(_is_number(value) for value in bbox):
        return f"bbox must be a list of four numbers [x, y, w, h], got {bbox!r}"
    return None


def _parse_slowly(path: Path, data: bytes) -> pl.DataFrame:
    """Parse with the standard library to locate a format error; returns the records when there is none."""
    try:
        records = json.loads(data)
    except UnicodeDecodeError:
        raise DataError("not UTF-8 text", path=path) from None
    except json.JSONDecodeError as error:
        raise DataError(f"unparseable JSON: {error.msg} (column {error.colno})", path=path,
                        line=error.lineno) from None
    if not isinstance(records, list):
        raise DataError(f"expected a JSON list of bounding-box records, found a JSON {type(records).__name__}",
                        path=path)
    if not records:
        raise DataError("holds no bounding-box records", path=path)
    for index, record in enumerate(records):
        problem = _record_problem(record)
        if problem:
            raise DataError(f"record {index} (0-based): {problem}", path=path)
    numbers = ("is_x_agent", "frame_id", "track_id")
    columns: dict[str, list[Any]] = {
        "class_name": [record["class_name"] for record in records],
        "bbox": [[float(value) for value in record["bbox"]] for record in records],
        **{name: [float(record[name]) for record in records] for name in numbers},
    }
    return pl.DataFrame(columns, schema={"class_name": pl.String, "bbox": pl.List(pl.Float64),
                                         **{name: pl.Float64 for name in numbers}})


def _has_record_types(frame: pl.DataFrame) -> bool:
    """Whether a fast (polars) parse produced the expected columns with usable types."""
    schema = frame.schema
    if any(name not in schema for name in RECORD_FIELDS) or frame.height == 0:
        return False
    numeric = all(schema[name].is_numeric() for name in ("is_x_agent", "frame_id", "track_id"))
    bbox = schema["bbox"]
    return (numeric and schema["class_name"] == pl.String and isinstance(bbox, pl.List)
            and bbox.inner is not None and bbox.inner.is_numeric())


def _first(frame: pl.DataFrame, condition: pl.Expr) -> dict[str, Any] | None:
    """The first row (as a dict) where `condition` holds, or None."""
    hits = frame.filter(condition)
    return hits.row(0, named=True) if hits.height else None


def _fail_record(path: Path, row: dict[str, Any], message: str) -> DataError:
    return DataError(f"record {row['record']} (0-based): {message}", path=path)


def _check_records(frame: pl.DataFrame, path: Path) -> None:
    """Content checks over all records at once; the first offending record is named."""
    for name in RECORD_FIELDS:
        row = _first(frame, pl.col(name).is_null())
        if row:
            raise _fail_record(path, row, f"missing or null field '{name}'")
    checks: list[tuple[pl.Expr, Any]] = [
        (~pl.col("class_name").is_in(list(CLASS_TYPES)),
         lambda r: f"class_name {r['class_name']!r} is not one of {', '.join(CLASS_TYPES)}"),
        (~pl.col("is_x_agent").is_in([0.0, 1.0]), lambda r: f"is_x_agent must be 0 or 1, got {r['is_x_agent']}"),
        (pl.col("bbox").list.len() != 4,
         lambda r: f"bbox must be [x, y, w, h], got {len(r['bbox'])} values"),
    ]
    for condition, message in checks:
        row = _first(frame, condition)
        if row:
            raise _fail_record(path, row, message(row))
    boxes = frame.with_columns(*[pl.col("bbox").list.get(i).alias(n) for i, n in enumerate(("bx", "by", "bw", "bh"))])
    finite = pl.all_horizontal([pl.col(n).is_finite() for n in ("bx", "by", "bw", "bh", "frame_id", "track_id")])
    more: list[tuple[pl.Expr, Any]] = [
        (~finite, lambda r: f"non-finite value in bbox {r['bbox']} / frame_id {r['frame_id']} / "
                            f"track_id {r['track_id']}"),
        ((pl.col("bw") < 0) | (pl.col("bh") < 0),
         lambda r: f"bbox has negative size (w={r['bw']:g}, h={r['bh']:g})"),
        ((pl.col("frame_id") < 0) | (pl.col("frame_id") != pl.col("frame_id").round()),
         lambda r: f"frame_id must be a whole number >= 0, got {r['frame_id']:g}"),
        ((pl.col("track_id") < 0) | (pl.col("track_id") != pl.col("track_id").round()),
         lambda r: f"track_id must be a whole number >= 0, got {r['track_id']:g}"),
        (pl.col("frame_id") < pl.col("frame_id").shift(1),
         lambda r: f"frame_id {r['frame_id']:g} follows a larger frame_id (frame ids go backwards)"),
    ]
    for condition, message in more:
        row = _first(boxes, condition)
        if row:
            raise _fail_record(path, row, message(row))
    key = pl.struct("class_name", "track_id", "frame_id")
    row = _first(frame, ~key.is_first_distinct())
    if row:
        first = _first(frame, (pl.col("class_name") == row["class_name"]) & (pl.col("track_id") == row["track_id"])
                       & (pl.col("frame_id") == row["frame_id"]))
        assert first is not None
        raise _fail_record(path, row, f"second box of {row['class_name']} {row['track_id']:g} at frame_id "
                                      f"{row['frame_id']:g} (first at record {first['record']})")


def _check_x_agent(frame: pl.DataFrame, item: BboxFile) -> None:
    """Exactly one person is the x-agent, marked so in all its records, and it is the one the name says."""
    marked = frame.filter(pl.col("is_x_agent") == 1).select("class_name", "track_id").unique()
    if marked.height == 0:
        raise DataError("no record has is_x_agent = 1 (the controlled agent is missing)", path=item.path)
    if marked.height > 1:
        agents = ", ".join(f"{c} {t:g}" for c, t in marked.sort("class_name", "track_id").iter_rows())
        raise DataError(f"several agents are marked is_x_agent = 1 ({agents})", path=item.path)
    class_name, track_id = marked.row(0)
    if class_name != "Person" or track_id != item.xagent:
        raise DataError(f"the x-agent is {class_name} {track_id:g}, but the file name says person {item.xagent}",
                        path=item.path)
    row = _first(frame, (pl.col("class_name") == "Person") & (pl.col("track_id") == track_id)
                 & (pl.col("is_x_agent") == 0))
    if row:
        raise _fail_record(item.path, row, f"person {track_id:g} is the x-agent elsewhere but has is_x_agent = 0 here")


def read_bbox_file(item: BboxFile) -> pl.DataFrame:
    """One validated annotation file as columns: record, class_name, is_x_agent, bbox, frame_id, track_id.

    The fast path parses with polars; anything it cannot type as expected is re-parsed with the standard library
    to name the offending line or record.
    """
    path = item.path
    data = input_files.read_bytes(path)
    frame: pl.DataFrame | None = None
    if data.lstrip()[:1] == b"[":
        try:
            frame = pl.read_json(io.BytesIO(data))
        except Exception:  # polars raises several unrelated types for malformed JSON; the slow path names the spot
            frame = None
    if frame is None or not _has_record_types(frame):
        frame = _parse_slowly(path, data)
    frame = frame.select(
        pl.int_range(pl.len(), dtype=pl.Int64).alias("record"), "class_name",
        pl.col("is_x_agent").cast(pl.Float64), pl.col("bbox").cast(pl.List(pl.Float64)),
        pl.col("frame_id").cast(pl.Float64), pl.col("track_id").cast(pl.Float64))
    _check_records(frame, path)
    _check_x_agent(frame, item)
    return frame


def _to_ground(frame: pl.DataFrame, item: BboxFile, scale: float) -> pl.DataFrame:
    """Foot points in metres (y flipped) with contract agent ids and types, one row per (agent, raw frame)."""
    person_ids = frame.filter(pl.col("class_name") == "Person").get_column("track_id")
    if person_ids.len() and person_ids.max() >= VEHICLE_ID_OFFSET:  # type: ignore[operator]
        raise DataError(f"person track_id {person_ids.max():g} is not below {VEHICLE_ID_OFFSET} (the id offset of "
                        "vehicles)", path=item.path)
    track = pl.col("track_id").cast(pl.Int64)
    return frame.select(
        pl.lit(item.stem).alias("scene_id"),
        pl.when(pl.col("class_name") == "Vehicle").then(track + VEHICLE_ID_OFFSET).otherwise(track).alias("agent_id"),
        pl.col("class_name").replace_strict(CLASS_TYPES).alias("agent_type"),
        (pl.col("is_x_agent") == 1).alias("is_x"),
        pl.col("frame_id").cast(pl.Int64),
        ((pl.col("bbox").list.get(0) + pl.col("bbox").list.get(2) / 2) * scale).alias("x"),
        (-(pl.col("bbox").list.get(1) + pl.col("bbox").list.get(3)) * scale).alias("y"),
    )


# --- one moment: fork, shared past, resampling -----------------------------------------------------------------

@dataclass
class MomentResult:
    """Resampled tracks and sample rows of one moment, plus the futures that had to be skipped."""

    tracks: pl.DataFrame
    samples: list[dict[str, Any]]
    skipped: list[dict[str, str]]


def find_fork(raw: pl.DataFrame, n_files: int, tolerance: float, fallback: int) -> int | None:
    """Last raw frame up to which every future places the x-agent at the same spot; None if they never agree.

    Frames where the x-agent is annotated in some futures but not in others count as disagreement. Futures that
    never diverge (or a single future) fork at `fallback`.
    """
    per_frame = (raw.filter(pl.col("is_x"))
                 .group_by("frame_id")
                 .agg(pl.len().alias("n"), (pl.col("x").max() - pl.col("x").min()).alias("dx"),
                      (pl.col("y").max() - pl.col("y").min()).alias("dy"))
                 .with_columns(agree=(pl.col("n") == n_files) & (pl.col("dx") <= tolerance)
                               & (pl.col("dy") <= tolerance))
                 .sort("frame_id"))
    if n_files == 1 or per_frame.get_column("agree").all():
        return fallback
    first_disagreement = per_frame.filter(~pl.col("agree")).get_column("frame_id").min()
    before = per_frame.filter(pl.col("frame_id") < first_disagreement).get_column("frame_id")
    return int(before.max()) if before.len() else None  # type: ignore[arg-type]


def share_past(raw: pl.DataFrame, canonical: str, fork: int) -> pl.DataFrame:
    """Every future's rows up to the fork replaced by the canonical future's, so a group's inputs are identical."""
    scenes = raw.select("scene_id").unique()
    past = raw.filter((pl.col("scene_id") == canonical) & (pl.col("frame_id") <= fork)).drop("scene_id")
    return pl.concat([raw.filter(pl.col("frame_id") > fork), scenes.join(past, how="cross")], how="diagonal")


def resample(raw: pl.DataFrame, fork: int, fps: float) -> tuple[pl.DataFrame, int]:
    """All agents on the dt grid anchored at the fork; returns the tracks and the fork's grid frame.

    Grid frame g lies at raw frame ``fork + (g - g_fork) * dt * fps``; exact raw frames are picked, fractional
    ones interpolated between the two neighbouring raw frames, and grid points without annotation dropped.
    """
    step = DT * fps
    g_fork = int(math.floor(fork / step + _EPS))
    spans = raw.group_by("scene_id", "agent_id", "agent_type").agg(
        pl.col("frame_id").min().alias("first"), pl.col("frame_id").max().alias("last"))
    lo_g = ((pl.col("first") - fork) / step - _EPS).ceil().cast(pl.Int64) + g_fork
    hi_g = ((pl.col("last") - fork) / step + _EPS).floor().cast(pl.Int64) + g_fork
    grid = (spans.with_columns(lo_g.alias("g0"), hi_g.alias("g1"))
            .filter(pl.col("g1") >= pl.col("g0"))
            .with_columns(frame=pl.int_ranges("g0", pl.col("g1") + 1))
            .explode("frame")
            .with_columns(raw_pos=fork + (pl.col("frame") - g_fork).cast(pl.Float64) * step))
    grid = grid.with_columns(lo=(pl.col("raw_pos") + _EPS).floor().cast(pl.Int64),
                             hi=(pl.col("raw_pos") - _EPS).ceil().cast(pl.Int64))
    points = raw.select("scene_id", "agent_id", "frame_id", "x", "y", "is_x")
    joined = (grid.join(points.rename({"frame_id": "lo", "x": "x0", "y": "y0"}), on=["scene_id", "agent_id", "lo"])
              .join(points.drop("is_x").rename({"frame_id": "hi", "x": "x1", "y": "y1"}),
                    on=["scene_id", "agent_id", "hi"]))
    weight = (pl.col("raw_pos") - pl.col("lo")).clip(0.0, 1.0)
    tracks = joined.select(
        "scene_id", "agent_id", "agent_type", "frame", (pl.col("raw_pos") / fps).alias("t"),
        (pl.col("x0") + weight * (pl.col("x1") - pl.col("x0"))).alias("x"),
        (pl.col("y0") + weight * (pl.col("y1") - pl.col("y0"))).alias("y"), "is_x",
    ).sort("scene_id", "agent_id", "frame")
    return tracks, g_fork


def process_moment(items: list[BboxFile], raws: list[pl.DataFrame], fps: float, tolerance: float,
                   root: Path) -> MomentResult:
    """Fork, shared past and resampling of all annotated futures of one moment (vectorised over its files)."""
    raw = pl.concat(raws)
    scene = items[0].scene
    fork = find_fork(raw, len(items), tolerance, fallback_fork_frame(scene))
    if fork is None:
        reason = "the annotated futures of this moment disagree from the x-agent's first annotated frame"
        return MomentResult(pl.DataFrame(), [], [{"file": _relative(i.path, root), "reason": reason} for i in items])
    raw = share_past(raw, items[0].stem, fork)
    tracks, g_fork = resample(raw, fork, fps)
    window = (tracks.filter(pl.col("is_x") & pl.col("frame").is_between(g_fork - N_PAST + 1, g_fork + N_FUTURE))
              .group_by("scene_id")
              .agg((pl.col("frame") <= g_fork).sum().alias("past"), (pl.col("frame") > g_fork).sum().alias("future")))
    counts = {row["scene_id"]: row for row in window.iter_rows(named=True)}
    kept, skipped, samples = [], [], []
    for item in items:
        have = counts.get(item.stem, {"past": 0, "future": 0})
        if have["past"] == N_PAST and have["future"] == N_FUTURE:
            kept.append(item.stem)
            samples.append({"scene_id": item.stem, "agent_id": item.xagent, "t0_frame": g_fork,
                            "moment": item.moment_key, "dest_idx": item.dest, "annotator": item.annotator,
                            "fork_raw_frame": fork})
        else:
            skipped.append({"file": _relative(item.path, root),
                            "reason": f"x-agent has {have['past']} of {N_PAST} past and {have['future']} of "
                                      f"{N_FUTURE} future steps at dt {DT} s around the fork (raw frame {fork})"})
    tracks = tracks.filter(pl.col("scene_id").is_in(kept)).drop("is_x")
    return MomentResult(tracks, samples, skipped)


# --- options, folds, groups ------------------------------------------------------------------------------------

def _per_scene(value: float | dict[str, float] | None, scenes: list[str], default: Callable[[str], float | None],
               option: str) -> dict[str, float]:
    """Resolve a number-or-per-scene option into one positive value per scene (defaults where not given)."""
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(scenes))
        if unknown:
            raise UsageError(f"{option} names scene(s) {', '.join(unknown)} not in the data "
                             f"(scenes: {', '.join(scenes)})")
        resolved = {scene: value.get(scene) for scene in scenes}
    else:
        resolved = {scene: value for scene in scenes}
    out: dict[str, float] = {}
    missing = []
    for scene, given in resolved.items():
        chosen = given if given is not None else default(scene)
        if chosen is None:
            missing.append(scene)
            continue
        if not (isinstance(chosen, (int, float)) and math.isfinite(chosen) and chosen > 0):
            raise UsageError(f"{option} for scene '{scene}' must be a positive number, got {chosen!r}")
        out[scene] = float(chosen)
    if missing:
        raise UsageError(f"{option}: no default for scene(s) {', '.join(missing)}; give one value for all scenes or "
                         "scene=value pairs")
    return out


def check_groups(samples: pl.DataFrame, tracks: pl.DataFrame, root: Path) -> None:
    """The moment groups must be exactly the groups of identical inputs (`identical_input_groups`)."""
    inputs = samples.select("moment", "group_id", identical_input_groups(samples, tracks).alias("input_group"))
    split = inputs.group_by("moment").agg(pl.col("input_group").n_unique().alias("n")).filter(pl.col("n") > 1)
    if split.height:
        raise TrajflowError(f"moment {split.get_column('moment').sort()[0]}: its futures do not have identical "
                            "inputs after sharing the past (internal error)")
    merged = (inputs.unique("moment").group_by("input_group").agg(pl.col("moment").sort())
              .filter(pl.col("moment").list.len() > 1))
    if merged.height:
        names = merged.get_column("moment")[0].to_list()
        raise DataError(f"moments {' and '.join(names[:2])} have identical inputs (same agents and pasts) but are "
                        "different moments; remove the duplicated files", path=root)


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def ingest_forking_paths(raw: str | Path, out: str | Path, *, camera: str = DEFAULT_CAMERA,
                         fps: float | dict[str, float] | None = None, scale: float | dict[str, float] | None = None,
                         folds: int = FOLDS, val_fraction: float = VAL_FRACTION, seed: int = 0,
                         fork_tolerance: float = FORK_TOLERANCE_M, overwrite: bool = False,
                         quiet: bool = False) -> Path:
    """Ingest the Forking Paths bounding boxes under `raw` into the dataset directory `out`; returns `out`.

    `fps` and `scale` (metres per pixel) are one number for every scene or a dict scene -> value; scenes left out
    take the defaults of the module docstring (cam4 only for the scale).
    """
    raw, out = Path(raw), Path(out)
    if not re.fullmatch(r"cam\d+", camera):
        raise UsageError(f"--camera must look like cam4, got {camera!r}")
    if folds < 2:
        raise UsageError(f"--folds must be at least 2, got {folds}")
    check_seed(seed, "--seed")
    if not 0 <= val_fraction < 1:
        raise UsageError(f"val fraction must be in [0, 1), got {val_fraction}")
    if not fork_tolerance >= 0:
        raise UsageError(f"fork tolerance must be >= 0 metres, got {fork_tolerance}")
    bbox_dir = find_bbox_folder(raw)
    files = discover_files(bbox_dir, camera)
    scenes = sorted({item.scene for item in files})
    fps_of = _per_scene(fps, scenes, default_fps, "fps")
    scale_of = _per_scene(scale, scenes, lambda scene: default_scale(scene, camera), "scale (metres per pixel)")

    moments: dict[str, list[BboxFile]] = {}
    for item in files:
        moments.setdefault(item.moment_key, []).append(item)
    results: list[MomentResult] = []
    with make_progress(quiet) as progress:
        task = progress.add_task(f"reading Forking Paths {camera} files", total=len(files))
        for key in sorted(moments):
            items = moments[key]
            raws = []
            for item in items:
                raws.append(_to_ground(read_bbox_file(item), item, scale_of[item.scene]))
                progress.advance(task)
            results.append(process_moment(items, raws, fps_of[items[0].scene], fork_tolerance, raw))
    skipped = [entry for result in results for entry in result.skipped]
    rows = [row for result in results for row in result.samples]
    if not rows:
        raise TrajflowError(f"{raw}: no annotated future has {N_PAST} past and {N_FUTURE} future steps around its "
                            f"fork; no samples ({len(skipped)} futures skipped)")
    tracks = pl.concat([r.tracks for r in results if r.tracks.height]).sort("scene_id", "agent_id", "frame")
    groups = assign_folds(sorted({row["moment"] for row in rows}), folds, val_fraction, seed)
    if groups.height < folds:
        raise UsageError(f"{raw}: only {groups.height} moment(s) for {folds} folds; pass --folds {groups.height} or "
                         "fewer")
    samples = (pl.DataFrame(rows, schema_overrides={"agent_id": pl.Int64, "t0_frame": pl.Int64,
                                                    "dest_idx": pl.Int64, "fork_raw_frame": pl.Int64})
               .sort("scene_id")
               .join(groups, on="moment", how="left")
               .with_row_index("sample_id")
               .select(pl.col("sample_id").cast(pl.Int64), "scene_id", "agent_id", "t0_frame",
                       pl.lit(N_PAST, dtype=pl.Int64).alias("n_past"),
                       pl.lit(N_FUTURE, dtype=pl.Int64).alias("n_future"),
                       "group_id", "split", "fold", "moment", "dest_idx", "annotator", "fork_raw_frame"))
    check_groups(samples, tracks, raw)
    by_name = {item.stem: item for item in files}
    scene_rows = [{"dataset": DATASET, "scene_id": sid, "location": by_name[sid].scene, "dt": DT,
                   "source": _relative(by_name[sid].path, raw), "fold": fold, "camera": camera,
                   "fps": fps_of[by_name[sid].scene], "m_per_px": scale_of[by_name[sid].scene]}
                  for sid, fold in samples.select("scene_id", "fold").iter_rows()]
    scenes_table = pl.DataFrame(scene_rows, schema_overrides={"fold": pl.String})
    single = samples.group_by("group_id").len().filter(pl.col("len") == 1).height
    if skipped:
        warn(f"skipped {len(skipped)} annotated future(s) without {N_PAST} + {N_FUTURE} steps around the fork "
             "(listed in dataset.json, lineage.skipped)")
    meta = DatasetMeta(dataset=DATASET, dt=DT, protocol=PROTOCOL_FOLDS)
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        for _, scene_tracks in tracks.group_by("scene_id", maintain_order=True):
            writer.add_tracks(scene_tracks)
        writer.finish(scenes_table, samples, lineage={
            "raw": str(raw.resolve()), "camera": camera, "fps": fps_of, "m_per_px": scale_of,
            "fork_tolerance_m": fork_tolerance, "n_past": N_PAST, "n_future": N_FUTURE, "folds": folds,
            "val_fraction": val_fraction, "seed": seed, "vehicle_id_offset": VEHICLE_ID_OFFSET,
            "single_future_groups": single, "skipped": skipped})
    return out


def read_files(raw: Path, options: dict[str, Any]) -> list[Path]:
    """The annotation files an ingest of `raw` with `options` reads (the camera's; the videos are not read)."""
    return [item.path for item in discover_files(find_bbox_folder(raw), options.get("camera", DEFAULT_CAMERA))]


ADAPTER = Ingest(name="forking-paths", dataset=DATASET, dt=DT, folds=None, raw="the Forking Paths release",
                 function=ingest_forking_paths, inputs=read_files, multi_future=True)
