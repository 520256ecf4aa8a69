"""`trajflow ingest csv`: bring-your-own trajectories from a CSV or Parquet file.

The file has one row per (scene, agent, time) with x / y in metres; column names are mapped by options.
Samples follow the strict ETH/UCY-style protocol (every agent at every frame with n_past + n_future consecutive
positions); samples with identical inputs share a group_id (even across scenes), so multi-future data brought
this way gets JSD evaluation too.

Splits: with `--split-col` a column of the file says train / val / test (read at each sample's t0 row; fixed
protocol); otherwise each scene's timeline is cut into `--folds` equal time blocks, a block is a fold, and the
last `val_fraction` of every block validates when the block trains. Windows that cross a cut are test-only.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import polars as pl

from ..errors import DataError, UsageError
from ..schemas import PROTOCOL_FIXED, PROTOCOL_FOLDS, DatasetMeta, DatasetWriter
from ..schemas.tables import SPLITS
from ..util import tablefiles
from .windows import complete_windows, identical_input_groups

#: common class labels of public datasets mapped onto the contract's agent types
TYPE_ALIASES: dict[str, str] = {
    "person": "pedestrian", "ped": "pedestrian", "pedestrian": "pedestrian", "human": "pedestrian",
    "car": "vehicle", "van": "vehicle", "truck": "vehicle", "bus": "vehicle", "trailer": "vehicle",
    "vehicle": "vehicle", "bicycle": "bicycle", "bike": "bicycle", "cyclist": "bicycle",
    "motorcycle": "motorcycle", "motorbike": "motorcycle", "unknown": "unknown",
}

ROLES = ("scene", "agent", "frame", "time", "x", "y", "type")


@dataclass(frozen=True)
class ColumnMap:
    """Which input column plays which role; `frame` or `time` is required, `scene` and `type` optional."""

    agent: str = "agent_id"
    x: str = "x"
    y: str = "y"
    frame: str | None = "frame"
    time: str | None = None
    scene: str | None = "scene_id"
    type: str | None = None

    @classmethod
    def parse(cls, spec: str | None) -> "ColumnMap":
        """Parse `role=column,...` (roles: scene, agent, frame, time, x, y, type); unnamed roles keep defaults."""
        if not spec:
            return cls()
        values: dict[str, str | None] = {}
        for item in spec.split(","):
            role, sep, column = item.partition("=")
            role, column = role.strip(), column.strip()
            if not sep or role not in ROLES or not column:
                raise UsageError(f"--columns: '{item}' is not role=column with a role among {', '.join(ROLES)}")
            values[role] = column
        if "time" in values and "frame" not in values:
            values["frame"] = None
        return cls(**values)


def _read_strings(path: Path) -> pl.DataFrame:
    """The file's cells as strings (Parquet columns are cast), with the error located where possible."""
    if not path.is_file():
        raise DataError("input file not found", path=path)
    if path.suffix.lower() in (".parquet", ".pq"):
        try:
            frame = tablefiles.read_parquet(path)
        except Exception as error:  # polars raises several unrelated types for unreadable files
            raise DataError(f"cannot read Parquet file ({error})", path=path) from None
        return frame.with_columns(pl.all().cast(pl.String))
    try:
        frame = tablefiles.read_csv(path, infer_schema=False)
    except (pl.exceptions.ComputeError, pl.exceptions.NoDataError) as error:
        raise _locate_csv_error(path, error) from None
    return frame


def _locate_csv_error(path: Path, error: Exception) -> DataError:
    """Find the first line whose field count differs from the header (polars does not say which)."""
    with open(path, newline="", encoding="utf-8", errors="replace") as handle:
        rows = csv.reader(handle)
        header = next(rows, None)
        if not header:
            return DataError("file is empty", path=path)
        for number, row in enumerate(rows, start=2):
            if row and len(row) != len(header):
                return DataError(f"expected {len(header)} fields as in the header, found {len(row)}",
                                 path=path, line=number)
    return DataError(f"cannot parse CSV ({str(error).splitlines()[0]})", path=path)


def _location(path: Path, row: int) -> dict[str, int]:
    """Error location for a 0-based data row: a line number for CSV (header is line 1), a row for Parquet."""
    return {"row": row} if path.suffix.lower() in (".parquet", ".pq") else {"line": row + 2}


def _numeric(frame: pl.DataFrame, column: str, path: Path, dtype: pl.DataType) -> pl.Expr:
    """Cast a string column, raising a DataError at the first cell that is missing, non-numeric or non-finite."""
    values = frame.get_column(column).str.strip_chars().cast(pl.Float64, strict=False)
    bad = values.is_null() | ~values.is_finite()
    if bad.any():
        row = int(bad.arg_true()[0])
        raise DataError(f"column '{column}' holds {frame[column][row]!r}, not a finite number",
                        path=path, **_location(path, row))
    if dtype == pl.Int64:
        fractional = values != values.round()
        if fractional.any():
            row = int(fractional.arg_true()[0])
            raise DataError(f"column '{column}' must hold whole numbers, got {frame[column][row]!r}",
                            path=path, **_location(path, row))
    return pl.lit(values).cast(dtype)


def _tracks(raw: pl.DataFrame, columns: ColumnMap, dt: float, path: Path, scene_default: str) -> pl.DataFrame:
    """Map the input's columns onto the tracks contract, checking every cell."""
    wanted = [c for c in (columns.scene, columns.agent, columns.frame, columns.time, columns.x, columns.y,
                          columns.type) if c]
    missing = [c for c in wanted if c not in raw.columns]
    if missing:
        raise DataError(f"missing column(s) {', '.join(missing)}; found {', '.join(raw.columns)} "
                        "(map columns with --columns role=name,...)", path=path)
    if columns.frame is None and columns.time is None:
        raise UsageError("--columns must name a frame or a time column")
    if columns.frame:
        frame = _numeric(raw, columns.frame, path, pl.Int64)
    else:
        seconds = raw.select(_numeric(raw, columns.time, path, pl.Float64)).to_series()
        steps = seconds / dt
        off_grid = (steps - steps.round()).abs() > 1e-3
        if off_grid.any():
            row = int(off_grid.arg_true()[0])
            raise DataError(f"time {seconds[row]} is not on the --dt {dt} grid; resample the data first",
                            path=path, **_location(path, row))
        frame = pl.lit(steps.round()).cast(pl.Int64)
    agent = raw.get_column(columns.agent)
    numeric_agent = agent.str.strip_chars().cast(pl.Int64, strict=False)
    agent_expr = (pl.lit(numeric_agent) if numeric_agent.null_count() == 0
                  else pl.lit(agent).rank("dense").cast(pl.Int64).alias("agent_id"))
    if columns.type:
        labels = raw.get_column(columns.type).str.strip_chars().str.to_lowercase()
        agent_type = pl.lit(labels.replace_strict(TYPE_ALIASES, default="unknown", return_dtype=pl.String))
    else:
        agent_type = pl.lit("pedestrian")
    scene = pl.col(columns.scene).cast(pl.String) if columns.scene else pl.lit(scene_default)
    tracks = raw.select(
        scene.alias("scene_id"), agent_expr.alias("agent_id"), agent_type.alias("agent_type"),
        frame.alias("frame"),
        _numeric(raw, columns.x, path, pl.Float64).alias("x"), _numeric(raw, columns.y, path, pl.Float64).alias("y"),
        *([pl.col(columns.agent).alias("agent_label")] if numeric_agent.null_count() else []),
    ).with_row_index("__row").with_columns(t=pl.col("frame").cast(pl.Float64) * dt)
    duplicated = tracks.filter(pl.struct("scene_id", "agent_id", "frame").is_duplicated())
    if duplicated.height:
        first = duplicated.row(0, named=True)
        raise DataError(f"duplicate row for scene {first['scene_id']!r}, agent {first['agent_id']}, "
                        f"frame {first['frame']}", path=path, **_location(path, int(first["__row"])))
    return tracks.sort("scene_id", "agent_id", "frame")


def _fold_assignment(windows: pl.DataFrame, tracks: pl.DataFrame, folds: int, val_fraction: float,
                     n_past: int, n_future: int) -> pl.DataFrame:
    """Cut each scene's timeline into `folds` equal blocks; tag each window with its block and train/val part."""
    extent = tracks.group_by("scene_id").agg(pl.col("frame").min().alias("first"), pl.col("frame").max().alias("last"))
    span = (pl.col("last") - pl.col("first") + 1).cast(pl.Float64)
    start, end = pl.col("t0_frame") - (n_past - 1), pl.col("t0_frame") + n_future
    block_of = lambda frame: ((frame - pl.col("first")).cast(pl.Float64) * folds / span).floor().cast(pl.Int64)  # noqa: E731
    position = lambda frame: (frame - pl.col("first")).cast(pl.Float64) * folds / span - block_of(frame)  # noqa: E731
    tagged = windows.join(extent, on="scene_id").with_columns(block=block_of(start), end_block=block_of(end))
    crosses = pl.col("block") != pl.col("end_block")
    in_val = position(start) >= 1 - val_fraction
    in_train = position(end) < 1 - val_fraction
    return tagged.with_columns(
        fold=pl.when(crosses).then(None).otherwise(pl.col("block").cast(pl.String)),
        split=pl.when(crosses).then(None).when(in_train).then(pl.lit("train")).when(in_val).then(pl.lit("val"))
        .otherwise(None),
    ).drop("first", "last", "block", "end_block")


def ingest_csv(file: str | Path, out: str | Path, *, dt: float, columns: ColumnMap | None = None,
               n_past: int = 8, n_future: int = 12, dataset: str | None = None, split_col: str | None = None,
               folds: int = 5, val_fraction: float = 0.2, overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest a bring-your-own trajectory table into the dataset directory `out`; returns `out`."""
    del quiet  # one file, read in one pass: nothing worth a progress bar
    path, out = Path(file), Path(out)
    if not (math.isfinite(dt) and dt > 0):
        raise UsageError(f"--dt must be a positive number of seconds, got {dt}")
    if n_past < 2 or n_future < 1:
        raise UsageError("--past must be at least 2 and --future at least 1")
    if split_col is None and folds < 2:
        raise UsageError(f"--folds must be at least 2, got {folds}")
    columns = columns or ColumnMap()
    raw = _read_strings(path)
    if raw.height == 0:
        raise DataError("file has no rows", path=path)
    tracks = _tracks(raw, columns, dt, path, scene_default=path.stem)
    windows = complete_windows(tracks, n_past, n_future)
    if split_col:
        if split_col not in raw.columns:
            raise DataError(f"split column '{split_col}' not found; found {', '.join(raw.columns)}", path=path)
        labels = tracks.select("scene_id", "agent_id", pl.col("frame").alias("t0_frame"),
                               pl.lit(raw.get_column(split_col)).gather(pl.col("__row")).str.strip_chars()
                               .str.to_lowercase().alias("split"))
        bad = labels.filter(~pl.col("split").is_in(SPLITS))
        if bad.height:
            first = bad.row(0, named=True)
            raise DataError(f"split column '{split_col}' holds {first['split']!r}; use train, val or test",
                            path=path)
        windows = windows.join(labels, on=["scene_id", "agent_id", "t0_frame"]).with_columns(
            fold=pl.lit(None, dtype=pl.String))
        protocol = PROTOCOL_FIXED
    else:
        windows = _fold_assignment(windows, tracks, folds, val_fraction, n_past, n_future)
        protocol = PROTOCOL_FOLDS
    samples = (windows.sort("scene_id", "t0_frame", "agent_id").with_row_index("sample_id")
               .select(pl.col("sample_id").cast(pl.Int64), "scene_id", "agent_id", "t0_frame",
                       pl.lit(n_past, dtype=pl.Int64).alias("n_past"),
                       pl.lit(n_future, dtype=pl.Int64).alias("n_future"), "split", "fold",
                       pl.struct("scene_id", "t0_frame").rank("dense").cast(pl.Int64).sub(1).alias("joint_id")))
    if samples.height == 0:
        raise DataError(f"no agent has {n_past + n_future} consecutive frames: no samples", path=path)
    tracks = tracks.drop("__row")
    samples = samples.with_columns(group_id=identical_input_groups(samples, tracks))
    name = dataset or path.stem
    scenes = (tracks.group_by("scene_id", maintain_order=True).agg()
              .with_columns(dataset=pl.lit(name), location=pl.col("scene_id"), dt=pl.lit(dt, dtype=pl.Float64),
                            source=pl.lit(str(path)), fold=pl.lit(None, dtype=pl.String)))
    meta = DatasetMeta(dataset=name, dt=dt, protocol=protocol)
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        for _, scene_tracks in tracks.group_by("scene_id", maintain_order=True):
            writer.add_tracks(scene_tracks)
        writer.finish(scenes, samples, lineage={"raw": str(path.resolve()), "columns": vars(columns),
                                                "n_past": n_past, "n_future": n_future, "split_col": split_col,
                                                "folds": None if split_col else folds,
                                                "val_fraction": val_fraction})
    return out
