"""`trajflow ingest csv`: bring-your-own trajectories from a CSV or Parquet file (one row per scene, agent and
time; columns mapped by options), with folds, fixed splits or train-is-test made of time cuts, scenes or groups.
The options, protocols and checks: docs/datasets/csv.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from ..errors import DataError, UsageError
from ..schemas import PROTOCOL_FIXED, PROTOCOL_FOLDS, PROTOCOL_TRAIN_IS_TEST, PROTOCOLS, DatasetMeta, DatasetWriter
from ..schemas.tables import SPLITS
from ..util import input_files
from .base import Ingest
from .folds import assign_folds
from .textfile import csv_record_line, csv_records, in_range, range_problem
from .windows import complete_windows, identical_input_groups

#: common class labels of public datasets mapped onto the contract's agent types
TYPE_ALIASES: dict[str, str] = {
    "person": "pedestrian", "ped": "pedestrian", "pedestrian": "pedestrian", "human": "pedestrian",
    "car": "vehicle", "van": "vehicle", "truck": "vehicle", "bus": "vehicle", "trailer": "vehicle",
    "vehicle": "vehicle", "bicycle": "bicycle", "bike": "bicycle", "cyclist": "bicycle",
    "motorcycle": "motorcycle", "motorbike": "motorcycle", "unknown": "unknown",
}

ROLES = ("scene", "agent", "frame", "time", "x", "y", "type")

#: what folds, holdouts and validation sets are made of (`--split-by`)
SPLIT_UNITS = ("auto", "time", "scene", "group")


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

    @classmethod
    def from_config(cls, value: Any) -> "ColumnMap":
        """The mapping as an experiment config gives it: a table {role = "column", ...} or the `role=column,...`
        string of --columns."""
        if isinstance(value, str):
            return cls.parse(value)
        if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
            raise UsageError(f"must be a table of role = \"column\" (roles {', '.join(ROLES)}), got {value!r}")
        return cls.parse(",".join(f"{role}={column}" for role, column in value.items()))

    def required(self) -> dict[str, str]:
        """role -> column of the roles every row must fill (the type column may be empty: unknown)."""
        return {role: column for role in ("scene", "agent", "frame", "time", "x", "y")
                if (column := getattr(self, role))}


@dataclass(frozen=True)
class SplitOptions:
    """How samples are split (see the module docstring): the protocol, its units and fractions, the seed."""

    protocol: str | None = None
    split_col: str | None = None
    split_by: str = "auto"
    folds: int = 5
    val_fraction: float = 0.2
    test_fraction: float | None = None
    seed: int = 0

    @property
    def resolved_protocol(self) -> str:
        """The protocol asked for, or the default: fixed with a split column, else folds."""
        return self.protocol or (PROTOCOL_FIXED if self.split_col else PROTOCOL_FOLDS)

    def check(self) -> None:
        """Refuse option combinations that cannot mean anything, before any file is read."""
        protocol = self.resolved_protocol
        if protocol not in PROTOCOLS:
            raise UsageError(f"--protocol must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")
        if self.split_by not in SPLIT_UNITS:
            raise UsageError(f"--split-by must be one of {', '.join(SPLIT_UNITS)}, got {self.split_by!r}")
        if not (math.isfinite(self.val_fraction) and 0 <= self.val_fraction < 1):
            raise UsageError(f"--val-fraction must be at least 0 and below 1, got {self.val_fraction}")
        if self.split_col and protocol != PROTOCOL_FIXED:
            raise UsageError(f"--split-col gives the fixed protocol, not {protocol}; drop one of them")
        if self.split_col and (self.test_fraction is not None or self.split_by != "auto"):
            raise UsageError("--split-col says each row's split; drop --test-fraction and --split-by")
        if protocol == PROTOCOL_FIXED and not self.split_col:
            if self.test_fraction is None:
                raise UsageError("--protocol fixed needs --split-col COLUMN or --test-fraction F")
            if not (math.isfinite(self.test_fraction) and 0 < self.test_fraction < 1
                    and self.test_fraction + self.val_fraction < 1):
                raise UsageError(f"--test-fraction must be above 0 and, with --val-fraction, below 1; got "
                                 f"{self.test_fraction} and {self.val_fraction}")
        elif self.test_fraction is not None:
            raise UsageError(f"--test-fraction holds out a test set of the fixed protocol, not of {protocol}")
        if protocol == PROTOCOL_FOLDS and self.folds < 2:
            raise UsageError(f"--folds must be at least 2, got {self.folds}")


def _read_strings(path: Path) -> pl.DataFrame:
    """The file's cells as strings (Parquet columns are cast), with the error located where possible."""
    if not path.is_file():
        raise DataError("input file not found", path=path)
    if path.suffix.lower() in (".parquet", ".pq"):
        try:
            frame = input_files.read_parquet(path)
        except Exception as error:  # polars raises several unrelated types for unreadable files
            raise DataError(f"cannot read Parquet file ({error})", path=path) from None
        return frame.with_columns(pl.all().cast(pl.String))
    try:
        frame = input_files.read_csv(path, infer_schema=False)
    except (pl.exceptions.ComputeError, pl.exceptions.NoDataError) as error:
        raise _locate_csv_error(path, error) from None
    return frame


def _locate_csv_error(path: Path, error: Exception) -> DataError:
    """Find the first line whose field count differs from the header (polars does not say which)."""
    records = csv_records(path, strict=True)
    _, header = next(records, (1, []))
    if not header:
        return DataError("file is empty", path=path)
    for line, row in records:
        if row and len(row) != len(header):
            return DataError(f"expected {len(header)} fields as in the header, found {len(row)}", path=path,
                             line=line)
    return DataError(f"cannot parse CSV ({str(error).splitlines()[0]})", path=path)


def _location(path: Path, row: int) -> dict[str, int]:
    """Error location for a 0-based data row: its line for CSV (where its record starts), a row for Parquet."""
    line = None if path.suffix.lower() in (".parquet", ".pq") else csv_record_line(path, row)
    return {"row": row} if line is None else {"line": line}


def _first(mask: pl.Series) -> int | None:
    """The first row where a boolean series is true (null counts as false), or None."""
    hits = mask.fill_null(False).arg_true()
    return int(hits[0]) if len(hits) else None


def _check_filled(raw: pl.DataFrame, columns: dict[str, str], path: Path) -> None:
    """Every cell of the required columns (role -> column) holds something; the error names the earliest line."""
    first: tuple[int, str, str] | None = None
    for role, column in columns.items():
        cells = raw.get_column(column)
        row = _first(cells.is_null() | (cells.str.strip_chars() == ""))
        if row is not None and (first is None or row < first[0]):
            first = (row, role, column)
    if first is not None:
        row, role, column = first
        blank = all(value is None for value in raw.row(row))  # polars reads a blank line as a row of nulls
        raise DataError("blank line" if blank else f"empty {role} cell (column '{column}')", path=path,
                        **_location(path, row))


def _numeric(frame: pl.DataFrame, column: str, path: Path, dtype: pl.DataType) -> pl.Series:
    """Cast a filled string column, raising a DataError at the first cell that is not a number, not finite or
    beyond :data:`textfile.MAX_MAGNITUDE` (or, for Int64, not whole)."""
    values = frame.get_column(column).str.strip_chars().cast(pl.Float64, strict=False)
    row = _first(~in_range(values).fill_null(False))
    if row is not None:
        value = values[row]
        why = ("not a number" if value is None else
               "not a finite number" if not math.isfinite(value) else range_problem(value))
        raise DataError(f"column '{column}' holds {frame[column][row]!r}, {why}", path=path, **_location(path, row))
    if dtype == pl.Int64:
        row = _first(values != values.round())
        if row is not None:
            raise DataError(f"column '{column}' must hold whole numbers, got {frame[column][row]!r}",
                            path=path, **_location(path, row))
    return values.cast(dtype)


def _frames(raw: pl.DataFrame, columns: ColumnMap, dt: float, path: Path) -> pl.Series:
    """Each row's frame: the frame column, or the time column on the --dt grid; its time must be finite too."""
    if columns.frame:
        frame = _numeric(raw, columns.frame, path, pl.Int64)
    else:
        assert columns.time is not None
        seconds = _numeric(raw, columns.time, path, pl.Float64)
        steps = seconds / dt
        row = _first((steps - steps.round()).abs() > 1e-3)
        if row is not None:
            raise DataError(f"time {seconds[row]} is not on the --dt {dt} grid; resample the data first",
                            path=path, **_location(path, row))
        row = _first(~in_range(steps))
        if row is not None:
            raise DataError(f"time {raw[columns.time][row]!r} at --dt {dt} is frame {steps[row]:.4g}, "
                            f"{range_problem(steps[row])}", path=path, **_location(path, row))
        frame = steps.round().cast(pl.Int64)
    row = _first(~(frame.cast(pl.Float64) * dt).is_finite())
    if row is not None:
        raise DataError(f"frame {frame[row]} at --dt {dt} is a time that is not finite", path=path,
                        **_location(path, row))
    return frame


def _tracks(raw: pl.DataFrame, columns: ColumnMap, dt: float, path: Path, scene_default: str) -> pl.DataFrame:
    """Map the input's columns onto the tracks contract, checking every cell (errors name the file and line)."""
    wanted = [c for c in (columns.scene, columns.agent, columns.frame, columns.time, columns.x, columns.y,
                          columns.type) if c]
    missing = [c for c in wanted if c not in raw.columns]
    if missing:
        raise DataError(f"missing column(s) {', '.join(missing)}; found {', '.join(raw.columns)} "
                        "(map columns with --columns role=name,...)", path=path)
    if columns.frame is None and columns.time is None:
        raise UsageError("--columns must name a frame or a time column")
    _check_filled(raw, columns.required(), path)
    frame = _frames(raw, columns, dt, path)
    x, y = _numeric(raw, columns.x, path, pl.Float64), _numeric(raw, columns.y, path, pl.Float64)
    agent = raw.get_column(columns.agent)
    numeric_agent = agent.str.strip_chars().cast(pl.Int64, strict=False)
    agent_expr = (pl.lit(numeric_agent) if numeric_agent.null_count() == 0
                  else pl.lit(agent).rank("dense").cast(pl.Int64).alias("agent_id"))
    if columns.type:
        labels = raw.get_column(columns.type).str.strip_chars().str.to_lowercase()
        agent_type = pl.lit(labels.replace_strict(TYPE_ALIASES, default="unknown", return_dtype=pl.String)
                            .fill_null("unknown"))
    else:
        agent_type = pl.lit("pedestrian")
    scene = pl.col(columns.scene).cast(pl.String) if columns.scene else pl.lit(scene_default)
    tracks = raw.select(
        scene.alias("scene_id"), agent_expr.alias("agent_id"), agent_type.alias("agent_type"),
        pl.lit(frame).alias("frame"), pl.lit(x).alias("x"), pl.lit(y).alias("y"),
        *([pl.col(columns.agent).alias("agent_label")] if numeric_agent.null_count() else []),
    ).with_row_index("__row").with_columns(t=pl.col("frame").cast(pl.Float64) * dt)
    row = _first(~tracks.select(pl.struct("scene_id", "agent_id", "frame").is_first_distinct()).to_series())
    if row is not None:
        again = tracks.row(row, named=True)
        earlier = _first((tracks.get_column("scene_id") == again["scene_id"])
                         & (tracks.get_column("agent_id") == again["agent_id"])
                         & (tracks.get_column("frame") == again["frame"]))
        assert earlier is not None
        where = _location(path, earlier)
        first = f"line {where['line']}" if "line" in where else f"row {where['row']}"
        raise DataError(f"duplicate row for scene {again['scene_id']!r}, agent {again['agent_id']}, frame "
                        f"{again['frame']} (first at {first})", path=path, **_location(path, row))
    return tracks.sort("scene_id", "agent_id", "frame")


def _split_labels(raw: pl.DataFrame, tracks: pl.DataFrame, split_col: str, path: Path) -> pl.DataFrame:
    """(scene_id, agent_id, t0_frame, split) from the split column at every track row, checked row by row."""
    if split_col not in raw.columns:
        raise DataError(f"split column '{split_col}' not found; found {', '.join(raw.columns)}", path=path)
    _check_filled(raw, {"split": split_col}, path)
    values = raw.get_column(split_col).str.strip_chars().str.to_lowercase()
    row = _first(~values.is_in(SPLITS))
    if row is not None:
        raise DataError(f"split column '{split_col}' holds {raw[split_col][row]!r}; use train, val or test",
                        path=path, **_location(path, row))
    return tracks.select("scene_id", "agent_id", pl.col("frame").alias("t0_frame"),
                         pl.lit(values).gather(pl.col("__row")).alias("split"))


# --- protocols ------------------------------------------------------------------------------------------------
# Working columns: window offsets from the scene's first frame and the scene's span of frames.
_START, _END, _SPAN, _UNIT = "__start", "__end", "__span", "__unit"


def _timeline(samples: pl.DataFrame, tracks: pl.DataFrame) -> pl.DataFrame:
    """Adds where each sample's window starts and ends (offsets of its first and last frame from its scene's first
    frame) and the scene's span of frames; a fraction `f` of the timeline is offset `f * span`."""
    extent = tracks.group_by("scene_id").agg(pl.col("frame").min().alias("__first"),
                                             (pl.col("frame").max() - pl.col("frame").min() + 1).alias(_SPAN))
    return (samples.join(extent, on="scene_id", how="left", maintain_order="left")
            .with_columns((pl.col("t0_frame") - pl.col("n_past") + 1 - pl.col("__first")).alias(_START),
                          (pl.col("t0_frame") + pl.col("n_future") - pl.col("__first")).alias(_END))
            .drop("__first"))


def _time_folds(timeline: pl.DataFrame, folds: int, val_fraction: float) -> pl.DataFrame:
    """Each scene's timeline cut into `folds` equal blocks: a window inside block b has fold b and trains, or
    validates in the block's last `val_fraction`; windows across a block's edge have no fold, across its
    validation cut no split (test-only)."""
    def position(offset: str) -> pl.Expr:
        return (pl.col(offset) * folds).cast(pl.Float64) / pl.col(_SPAN)

    block = position(_START).floor()
    crosses = block != position(_END).floor()
    return timeline.with_columns(
        fold=pl.when(crosses).then(None).otherwise(block.cast(pl.Int64).cast(pl.String)),
        split=pl.when(crosses).then(None).when(position(_END) - block < 1 - val_fraction).then(pl.lit("train"))
        .when(position(_START) - block >= 1 - val_fraction).then(pl.lit("val")).otherwise(None))


def _time_parts(timeline: pl.DataFrame, parts: list[tuple[str, float, float]]) -> pl.DataFrame:
    """split = the part (name, from, to: fractions of each scene's timeline) that holds a window whole, else null;
    no fold."""
    split = pl.lit(None, dtype=pl.String)
    for name, low, high in reversed(parts):
        inside = ((pl.col(_START).cast(pl.Float64) >= low * pl.col(_SPAN))
                  & (pl.col(_END).cast(pl.Float64) < high * pl.col(_SPAN)))
        split = pl.when(inside).then(pl.lit(name)).otherwise(split)
    return timeline.with_columns(split=split, fold=pl.lit(None, dtype=pl.String))


def _holdout(units: list[str], test_fraction: float, val_fraction: float, seed: int) -> pl.DataFrame:
    """unit -> split: a seeded `test_fraction` of the units (at least one) test, a `val_fraction` validate."""
    n = len(units)
    order = np.random.default_rng(seed).permutation(n)
    n_test = min(n, max(1, round(test_fraction * n)))
    n_val = min(n - n_test, round(val_fraction * n))
    split = np.full(n, "train", dtype=object)
    split[order[:n_test]] = "test"
    split[order[n_test:n_test + n_val]] = "val"
    return pl.DataFrame({_UNIT: units, "split": split.astype(str)})


def _unit_splits(samples: pl.DataFrame, unit: str, options: SplitOptions) -> pl.DataFrame:
    """fold and split of every sample from its unit (whole scenes or groups), seeded."""
    key = pl.col("scene_id") if unit == "scene" else pl.col("group_id").cast(pl.String)
    keyed = samples.with_columns(key.alias(_UNIT))
    units = (samples.get_column("scene_id").unique().sort() if unit == "scene"
             else samples.get_column("group_id").unique().sort().cast(pl.String)).to_list()
    protocol = options.resolved_protocol
    if protocol == PROTOCOL_FIXED:
        assert options.test_fraction is not None
        table = _holdout(units, options.test_fraction, options.val_fraction, options.seed)
        table = table.with_columns(fold=pl.lit(None, dtype=pl.String))
    else:
        folds = options.folds if protocol == PROTOCOL_FOLDS else 1
        table = assign_folds(units, folds, options.val_fraction, options.seed).select(
            pl.col("moment").alias(_UNIT), "split",
            pl.col("fold") if protocol == PROTOCOL_FOLDS else pl.lit(None, dtype=pl.String).alias("fold"))
    return keyed.join(table, on=_UNIT, how="left", maintain_order="left").drop(_UNIT)


def _time_splits(timeline: pl.DataFrame, options: SplitOptions) -> pl.DataFrame:
    """fold and split of every sample from where its window lies on its scene's timeline."""
    protocol, val = options.resolved_protocol, options.val_fraction
    if protocol == PROTOCOL_FOLDS:
        return _time_folds(timeline, options.folds, val)
    if protocol == PROTOCOL_FIXED:
        assert options.test_fraction is not None
        # cut points rounded so that 1 - 0.2 - 0.2 is the 0.6 a user means, not 0.6000000000000001
        val_cut, test_cut = round(1 - options.test_fraction - val, 12), round(1 - options.test_fraction, 12)
        return _time_parts(timeline, [("train", 0.0, val_cut), ("val", val_cut, test_cut), ("test", test_cut, 1.0)])
    return _time_parts(timeline, [("train", 0.0, round(1 - val, 12)), ("val", round(1 - val, 12), 1.0)])


def assign_splits(samples: pl.DataFrame, tracks: pl.DataFrame, options: SplitOptions) -> tuple[pl.DataFrame, str]:
    """Samples with `fold` and `split` under the options' protocol, and the unit they were made of (`auto`
    resolved: time unless its cuts drop more than half of the windows, then scene)."""
    timeline = _timeline(samples, tracks)
    by_time = _time_splits(timeline, options)
    unit = options.split_by
    if unit == "auto":
        kept = by_time.get_column("fold" if options.resolved_protocol == PROTOCOL_FOLDS else "split").count()
        unit = "time" if 2 * kept >= samples.height else "scene"
    chosen = by_time if unit == "time" else _unit_splits(samples, unit, options)
    return chosen.select(*samples.columns, "split", "fold"), unit


def _counts(samples: pl.DataFrame, options: SplitOptions) -> list[tuple[str, int, int]]:
    """(test fold or "", test samples, training samples) of each test the protocol defines, as the loader selects
    them."""
    protocol, split = options.resolved_protocol, pl.col("split")
    if protocol == PROTOCOL_FOLDS:
        return [(str(fold), *samples.select((pl.col("fold") == str(fold)).sum().alias("test"),
                                            (pl.col("fold").ne_missing(str(fold)) & (split == "train")).sum()
                                            .alias("train")).row(0))
                for fold in range(options.folds)]
    test = samples.height if protocol == PROTOCOL_TRAIN_IS_TEST else samples.select((split == "test").sum()).item()
    return [("", test, samples.select((split == "train").sum()).item())]


def check_protocol(samples: pl.DataFrame, options: SplitOptions, unit: str, path: Path) -> None:
    """Refuse, at ingest, a protocol that leaves a test (a fold, or the dataset) without test or training samples,
    saying why and what to change."""
    protocol = options.resolved_protocol
    how = (f"--split-col {options.split_col}" if options.split_col else
           f"--split-by {unit}{' (auto)' if options.split_by == 'auto' else ''}")
    where = f"{path}: --protocol {protocol} {how}"
    count = samples.get_column("scene_id" if unit == "scene" else "group_id").n_unique()
    if unit in ("scene", "group") and protocol == PROTOCOL_FOLDS and count < options.folds:
        raise UsageError(f"{where}: only {count} {unit}(s) for {options.folds} folds; use fewer --folds"
                         + (" or --split-by scene" if unit == "group" else ""))
    for fold, test, train in _counts(samples, options):
        if test and train:
            continue
        missing = "test" if not test else "training"
        what = f"fold {fold} has no {missing} samples" if fold else f"no {missing} samples"
        if options.split_col:
            hint = "the column's value at each sample's t0 row is its split"
        elif unit == "time":
            n = int(samples.get_column("n_past")[0] + samples.get_column("n_future")[0])
            hint = (f"windows of {n} frames that cross a cut of a scene's timeline are dropped, and the scenes are "
                    "too short for these cuts; use --split-by scene or group"
                    + (", or fewer --folds" if protocol == PROTOCOL_FOLDS else ""))
        else:
            hint = f"{count} {unit}(s) to deal out; " + ("use --split-by time or more data" if count < 3 else
                                                          "change the fractions or --seed")
        raise UsageError(f"{where}: {what} ({hint})")


def ingest_csv(file: str | Path, out: str | Path, *, dt: float, columns: ColumnMap | None = None,
               n_past: int = 8, n_future: int = 12, dataset: str | None = None, split_col: str | None = None,
               folds: int = 5, val_fraction: float = 0.2, protocol: str | None = None, split_by: str = "auto",
               test_fraction: float | None = None, seed: int = 0, overwrite: bool = False,
               quiet: bool = False) -> Path:
    """Ingest a bring-your-own trajectory table into the dataset directory `out`; returns `out`."""
    del quiet  # one file, read in one pass: nothing worth a progress bar
    path, out = Path(file), Path(out)
    if not (math.isfinite(dt) and dt > 0):
        raise UsageError(f"--dt must be a positive number of seconds, got {dt}")
    if n_past < 2 or n_future < 1:
        raise UsageError("--past must be at least 2 and --future at least 1")
    options = SplitOptions(protocol=protocol, split_col=split_col, split_by=split_by, folds=folds,
                           val_fraction=val_fraction, test_fraction=test_fraction, seed=seed)
    options.check()
    columns = columns or ColumnMap()
    raw = _read_strings(path)
    if raw.height == 0:
        raise DataError("file has no rows", path=path)
    tracks = _tracks(raw, columns, dt, path, scene_default=path.stem)
    windows = complete_windows(tracks, n_past, n_future)
    if split_col:
        windows = windows.join(_split_labels(raw, tracks, split_col, path), on=["scene_id", "agent_id", "t0_frame"])
    samples = (windows.sort("scene_id", "t0_frame", "agent_id").with_row_index("sample_id")
               .select(pl.col("sample_id").cast(pl.Int64), "scene_id", "agent_id", "t0_frame",
                       pl.lit(n_past, dtype=pl.Int64).alias("n_past"),
                       pl.lit(n_future, dtype=pl.Int64).alias("n_future"),
                       *(["split"] if split_col else []),
                       pl.struct("scene_id", "t0_frame").rank("dense").cast(pl.Int64).sub(1).alias("joint_id")))
    if samples.height == 0:
        raise DataError(f"no agent has {n_past + n_future} consecutive frames: no samples", path=path)
    tracks = tracks.drop("__row")
    samples = samples.with_columns(group_id=identical_input_groups(samples, tracks))
    if split_col:
        samples, unit = samples.with_columns(fold=pl.lit(None, dtype=pl.String)), "column"
    else:
        samples, unit = assign_splits(samples, tracks, options)
    check_protocol(samples, options, unit, path)
    name = dataset or path.stem
    scene_fold = (samples.group_by("scene_id").agg(pl.col("fold").first())
                  if unit == "scene" and options.resolved_protocol == PROTOCOL_FOLDS else None)
    scenes = (tracks.group_by("scene_id", maintain_order=True).agg()
              .with_columns(dataset=pl.lit(name), location=pl.col("scene_id"), dt=pl.lit(dt, dtype=pl.Float64),
                            source=pl.lit(str(path)), fold=pl.lit(None, dtype=pl.String)))
    if scene_fold is not None:
        scenes = scenes.drop("fold").join(scene_fold, on="scene_id", how="left", maintain_order="left")
    meta = DatasetMeta(dataset=name, dt=dt, protocol=options.resolved_protocol)
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        for _, scene_tracks in tracks.group_by("scene_id", maintain_order=True):
            writer.add_tracks(scene_tracks)
        writer.finish(scenes, samples, lineage={
            "raw": str(path.resolve()), "columns": vars(columns), "n_past": n_past, "n_future": n_future,
            "protocol": options.resolved_protocol, "split_col": split_col, "split_by": unit,
            "folds": folds if options.resolved_protocol == PROTOCOL_FOLDS else None,
            "val_fraction": val_fraction, "test_fraction": test_fraction, "seed": seed})
    return out


ADAPTER = Ingest(name="csv", dataset=None, dt=None, folds=None, raw="a CSV or Parquet file", function=ingest_csv,
                 converters={"columns": ColumnMap.from_config}, multi_future=None)
