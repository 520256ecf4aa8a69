"""Validation of dataset tables against the contract, with errors that name the file and offending rows."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from ..errors import DataError
from .tables import AGENT_TYPES, SAMPLES, TRACKS, TableSpec

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
    """Validate one table's columns and content; raise DataError naming `path` and the offending rows."""
    validate_columns(frame.schema, spec, path)
    present = [name for name in spec.columns if name in frame.columns]
    for name in present:
        if name not in spec.nullable and frame.get_column(name).null_count():
            _fail(path, spec.name, f"null values in column '{name}'", _offending_rows(frame, pl.col(name).is_null()))
    for name in spec.finite:
        if name in frame.columns:
            bad = pl.col(name).is_nan() | pl.col(name).is_infinite()
            if frame.select(bad.any()).item():
                _fail(path, spec.name, f"NaN or infinite values in column '{name}'", _offending_rows(frame, bad))
    if spec is TRACKS:
        unknown = ~pl.col("agent_type").is_in(AGENT_TYPES)
        if frame.select(unknown.any()).item():
            values = frame.filter(unknown).get_column("agent_type").unique().sort().head(5).to_list()
            _fail(path, spec.name, f"agent_type {values} not one of {', '.join(AGENT_TYPES)}",
                  _offending_rows(frame, unknown))
    if spec is SAMPLES:
        bad = (pl.col("n_past") < 1) | (pl.col("n_future") < 1)
        if frame.select(bad.any()).item():
            _fail(path, spec.name, "n_past and n_future must be at least 1", _offending_rows(frame, bad))
    if spec.key:
        duplicated = pl.struct(list(spec.key)).is_duplicated()
        if frame.select(duplicated.any()).item():
            _fail(path, spec.name, f"duplicated key ({', '.join(spec.key)})", _offending_rows(frame, duplicated))
    if spec.sort:
        _validate_sorted(frame, spec, path)


def _validate_sorted(frame: pl.DataFrame, spec: TableSpec, path: str | Path) -> None:
    """Rows must be strictly increasing in the spec's sort key (lexicographic over its columns)."""
    increasing = pl.lit(False)
    equal_so_far = pl.lit(True)
    for name in spec.sort:
        previous = pl.col(name).shift(1)
        increasing = increasing | (equal_so_far & (pl.col(name) > previous))
        equal_so_far = equal_so_far & (pl.col(name) == previous)
    out_of_order = ~increasing & pl.int_range(pl.len()).gt(0)
    if frame.select(out_of_order.any()).item():
        _fail(path, spec.name, f"rows are not sorted by ({', '.join(spec.sort)})",
              _offending_rows(frame, out_of_order))


def validate_references(samples: pl.DataFrame, scenes: pl.DataFrame, path: str | Path) -> None:
    """Every sample must point at a scene of the dataset."""
    orphan = ~pl.col("scene_id").is_in(scenes.get_column("scene_id").implode())
    if samples.select(orphan.any()).item():
        _fail(path, "samples", "scene_id not present in the scenes table", _offending_rows(samples, orphan))
