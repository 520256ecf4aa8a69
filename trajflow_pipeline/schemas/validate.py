"""Validation of dataset tables against the contract, with errors that name the file and offending rows."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from ..errors import DataError
from .tables import AGENT_TYPES, SAMPLES, SCENES, SPLITS, TRACKS, TableSpec

#: how many offending rows an error message lists
_SHOW_ROWS = 5


def _fail(path: str | Path, table: str, message: str, rows: pl.Series | None = None) -> None:
    where = ""
    if rows is not None and len(rows):
        shown = ", ".join(str(r) for r in rows.head(_SHOW_ROWS).to_list())
        more = f" and {len(rows) - _SHOW_ROWS} more" if len(rows) > _SHOW_ROWS else ""
        where = f" (rows {shown}{more}; 0-based)"
    raise DataError(f"{table} table: {message}{where}", path=path)


def _offending_rows(frame: pl.DataFrame, condition: pl.Expr) -> pl.Series:
    return frame.with_row_index("__row").filter(condition).get_column("__row")


def validate_columns(schema: pl.Schema | dict[str, pl.DataType], spec: TableSpec, path: str | Path) -> None:
    """Check that every required column exists and every known column has the contract's dtype."""
    names = list(schema.keys())
    missing = [name for name in spec.required if name not in names]
    if missing:
        _fail(path, spec.name, f"missing column(s) {', '.join(missing)}; found {', '.join(names) or 'none'}")
    for name, expected in spec.columns.items():
        if name in names and schema[name] != expected:
            _fail(path, spec.name, f"column '{name}' has dtype {schema[name]}, expected {expected}")


def validate_table(frame: pl.DataFrame, spec: TableSpec, path: str | Path) -> None:
    """Validate one table's columns and content; raise DataError naming `path` and the offending rows.

    Every content check is computed in one pass; only a failed check goes back for its offending rows.
    """
    validate_columns(frame.schema, spec, path)
    present = [name for name in spec.columns if name in frame.columns]
    nulls = {name: pl.col(name).is_null() for name in present if name not in spec.nullable}
    non_finite = {name: pl.col(name).is_nan() | pl.col(name).is_infinite() for name in spec.finite
                  if name in frame.columns}
    unknown_type = ~pl.col("agent_type").is_in(AGENT_TYPES) if spec is TRACKS else None
    bad_lengths = (pl.col("n_past") < 1) | (pl.col("n_future") < 1) if spec is SAMPLES else None
    unknown_split = (pl.col("split").is_not_null() & ~pl.col("split").is_in(SPLITS)) if spec is SAMPLES else None
    bad_dt = (pl.col("dt") <= 0) if spec is SCENES else None
    bad_map = _outside_dataset(pl.col("map_path")) if spec is SCENES and "map_path" in frame.columns else None
    out_of_order = _out_of_order(spec) if spec.sort else None
    checks = {**{f"null {name}": bad for name, bad in nulls.items()},
              **{f"finite {name}": bad for name, bad in non_finite.items()},
              **({"type": unknown_type} if unknown_type is not None else {}),
              **({"lengths": bad_lengths} if bad_lengths is not None else {}),
              **({"split": unknown_split} if unknown_split is not None else {}),
              **({"dt": bad_dt} if bad_dt is not None else {}),
              **({"map": bad_map} if bad_map is not None else {}),
              **({"order": out_of_order} if out_of_order is not None else {})}
    failed = frame.select(*[bad.any().alias(label) for label, bad in checks.items()]).row(0, named=True) \
        if checks else {}
    for name, bad in nulls.items():
        if failed[f"null {name}"]:
            _fail(path, spec.name, f"null values in column '{name}'", _offending_rows(frame, bad))
    for name, bad in non_finite.items():
        if failed[f"finite {name}"]:
            _fail(path, spec.name, f"NaN or infinite values in column '{name}'", _offending_rows(frame, bad))
    if unknown_type is not None and failed["type"]:
        _fail_unknown(frame, spec, path, "agent_type", unknown_type, ", ".join(AGENT_TYPES))
    if bad_lengths is not None and failed["lengths"]:
        _fail(path, spec.name, "n_past and n_future must be at least 1", _offending_rows(frame, bad_lengths))
    if unknown_split is not None and failed["split"]:
        _fail_unknown(frame, spec, path, "split", unknown_split, f"{', '.join(SPLITS)} (or null)")
    if bad_dt is not None and failed["dt"]:
        _fail(path, spec.name, "dt must be positive", _offending_rows(frame, bad_dt))
    if bad_map is not None and failed["map"]:
        _fail(path, spec.name, "map_path must be a path inside the dataset directory (relative, without '..')",
              _offending_rows(frame, bad_map))
    # rows strictly increasing in a sort key made of key columns cannot repeat a key: look only when unsorted
    key_implied_by_order = bool(spec.sort) and set(spec.sort) <= set(spec.key)
    if spec.key and not (key_implied_by_order and not failed.get("order")):
        duplicated = pl.struct(list(spec.key)).is_duplicated()
        if frame.select(duplicated.any()).item():
            _fail(path, spec.name, f"duplicated key ({', '.join(spec.key)})", _offending_rows(frame, duplicated))
    if out_of_order is not None and failed["order"]:
        _fail(path, spec.name, f"rows are not sorted by ({', '.join(spec.sort)})",
              _offending_rows(frame, out_of_order))


def _outside_dataset(relative: pl.Expr) -> pl.Expr:
    """True where a path meant to be relative to the dataset directory is absolute (POSIX or Windows style) or
    climbs out of it through a '..' component."""
    return relative.is_not_null() & (relative.str.contains(r"^([/\\]|[A-Za-z]:)")
                                     | relative.str.contains(r"(^|[/\\])\.\.([/\\]|$)"))


def _fail_unknown(frame: pl.DataFrame, spec: TableSpec, path: str | Path, column: str, bad: pl.Expr,
                  allowed: str) -> None:
    """Fail naming up to five of the values of `column` that are not `allowed`, and their rows."""
    values = frame.filter(bad).get_column(column).unique().sort().head(5).to_list()
    _fail(path, spec.name, f"{column} {values} not one of {allowed}", _offending_rows(frame, bad))


def _out_of_order(spec: TableSpec) -> pl.Expr:
    """True on each row that is not strictly greater than the previous one in the spec's sort key
    (lexicographic over its columns)."""
    increasing = pl.lit(False)
    equal_so_far = pl.lit(True)
    for name in spec.sort:
        previous = pl.col(name).shift(1)
        increasing = increasing | (equal_so_far & (pl.col(name) > previous))
        equal_so_far = equal_so_far & (pl.col(name) == previous)
    return ~increasing & pl.int_range(pl.len()).gt(0)


def validate_references(frame: pl.DataFrame, scenes: pl.DataFrame, path: str | Path,
                        table: str = SAMPLES.name) -> None:
    """Every row of `frame` (the samples table, or one tracks shard with `table="tracks"`) must point at a scene
    of the dataset: loaders join on scene_id and would silently drop orphans."""
    orphan = ~pl.col("scene_id").is_in(scenes.get_column("scene_id").implode())
    if frame.select(orphan.any()).item():
        _fail(path, table, "scene_id not present in the scenes table", _offending_rows(frame, orphan))


# --- contents of the tracks against the other tables, shard by shard ------------------------------------------
# Working columns carry a "__" prefix so that they never collide with a dataset's own extra columns.
_ROW, _FIRST, _LAST, _RUN, _SHARD = "__row", "__first", "__last", "__run", "__shard"


def sample_windows(samples: pl.DataFrame) -> pl.DataFrame:
    """Per sample (row number `__row`) its target and the frames its window needs, `__first` .. `__last`.

    The window is what the loader reads: n_past frames up to and including t0_frame, then n_future after it.
    """
    return samples.with_row_index(_ROW).select(
        _ROW, "scene_id", "agent_id", (pl.col("t0_frame") - pl.col("n_past") + 1).alias(_FIRST),
        (pl.col("t0_frame") + pl.col("n_future")).alias(_LAST))


def consecutive_runs(tracks: pl.DataFrame) -> pl.DataFrame:
    """Maximal runs of consecutive frames of each agent of a validated (sorted, unique) tracks shard.

    Columns scene_id, agent_id, `__first`, `__last`: a window is complete exactly when one run contains it, which
    turns the window check into a join on agents (a few runs each) instead of one on every frame of every window.
    """
    frame = pl.col("frame")
    starts = ((frame != frame.shift(1) + 1) | (pl.col("agent_id") != pl.col("agent_id").shift(1))
              | (pl.col("scene_id") != pl.col("scene_id").shift(1))).fill_null(True)
    return (tracks.select("scene_id", "agent_id", frame, starts.cum_sum().alias(_RUN))
            .group_by(_RUN).agg(pl.col("scene_id").first(), pl.col("agent_id").first(),
                                frame.first().alias(_FIRST), frame.last().alias(_LAST))
            .drop(_RUN))


def windows_inside(windows: pl.DataFrame, tracks: pl.DataFrame) -> pl.Series:
    """Row numbers of the `windows` (from :func:`sample_windows`) that `tracks` holds completely."""
    runs = consecutive_runs(tracks)
    return (windows.join(runs, on=["scene_id", "agent_id"], how="inner", suffix="_run")
            .filter((pl.col(f"{_FIRST}_run") <= pl.col(_FIRST)) & (pl.col(f"{_LAST}_run") >= pl.col(_LAST)))
            .get_column(_ROW))


def validate_sample_windows(windows: pl.DataFrame, complete: pl.Series, path: str | Path) -> None:
    """Every sample's window must be complete in the tracks (`complete`: row numbers found complete), else the
    loader fails on it at training or evaluation time; the error names the first such sample."""
    missing = ~pl.col(_ROW).is_in(complete.implode())
    if windows.select(missing.any()).item():
        first = windows.filter(missing).row(0, named=True)
        _fail(path, SAMPLES.name, f"target window not complete in the tracks (first: agent {first['agent_id']} "
              f"of scene '{first['scene_id']}' lacks a frame of {first[_FIRST]}..{first[_LAST]})",
              windows.filter(missing).get_column(_ROW))


def shard_scenes(tracks: pl.DataFrame, path: str | Path) -> pl.DataFrame:
    """The scenes of one tracks shard with the shard's file name, to remember which shard holds which scene."""
    return tracks.select(pl.col("scene_id").unique(), pl.lit(Path(path).name).alias(_SHARD))


def validate_shard_scenes(tracks: pl.DataFrame, earlier: pl.DataFrame, path: str | Path) -> None:
    """No scene may span two shards (`earlier`: :func:`shard_scenes` of the shards before `path`).

    The layout promises it; it is what makes per-shard checks of keys, order and windows cover the whole table.
    """
    spans = pl.col("scene_id").is_in(earlier.get_column("scene_id").implode())
    if tracks.select(spans.any()).item():
        scene = tracks.filter(spans).get_column("scene_id").item(0)
        other = earlier.filter(pl.col("scene_id") == scene).get_column(_SHARD).item(0)
        _fail(path, TRACKS.name, f"scene '{scene}' also has rows in {other}; a scene must not span two shards",
              _offending_rows(tracks, spans))


class TracksContentCheck:
    """The check of the tracks against the samples that a single shard cannot settle (every sample's window is
    complete in some shard), fed one shard at a time so that memory stays bounded by one shard plus a row per
    sample. The shards' own checks, and those against the scenes and the other shards, are made by every read of
    them (:meth:`trajflow_pipeline.schemas.io.Dataset.iter_track_shards`).
    """

    def __init__(self, samples: pl.DataFrame, samples_path: str | Path) -> None:
        self.samples_path = samples_path
        self.windows = sample_windows(samples)
        self.complete: list[pl.Series] = []

    def add_shard(self, tracks: pl.DataFrame) -> None:
        """Note which samples' windows one shard (as read by ``iter_track_shards``) holds complete."""
        self.complete.append(windows_inside(self.windows, tracks))

    def finish(self) -> None:
        """Check, once every shard was added, that no sample's window is missing from the tracks."""
        complete = pl.concat(self.complete) if self.complete else pl.Series(_ROW, [], dtype=pl.UInt32)
        validate_sample_windows(self.windows, complete, self.samples_path)
