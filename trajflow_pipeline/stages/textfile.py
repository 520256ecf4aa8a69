"""Parsing whitespace-separated numeric text files with errors that name the file and line."""

from __future__ import annotations

import math
from pathlib import Path

import polars as pl

from ..errors import DataError


def read_numeric_table(path: Path, columns: tuple[str, ...]) -> pl.DataFrame:
    """Read a TAB- or space-separated file of numbers into Float64 columns plus its 1-based `line` number.

    Blank lines are skipped. A line with the wrong number of fields, a field that is not a number, or a
    non-finite value raises a DataError naming the file and the first offending line.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DataError(f"not a text file ({error.reason} at byte {error.start})", path=path) from None
    except OSError as error:
        raise DataError(f"cannot read file ({error.strerror})", path=path) from None
    lines = (pl.DataFrame({"raw": pl.Series(text.splitlines(), dtype=pl.String)})
             .with_row_index("line", offset=1)
             .with_columns(pl.col("raw").str.strip_chars())
             .filter(pl.col("raw") != ""))
    if lines.height == 0:
        raise DataError("file is empty", path=path)
    fields = lines.with_columns(pl.col("raw").str.replace_all(r"\s+", " ").str.split(" ").alias("fields"))
    values = fields.select(
        "line", "raw", pl.col("fields").list.len().alias("__count"),
        *[pl.col("fields").list.get(i, null_on_oob=True).alias(name) for i, name in enumerate(columns)],
    ).with_columns(*[pl.col(name).cast(pl.Float64, strict=False).alias(f"__{name}") for name in columns])
    bad = pl.col("__count") != len(columns)
    for name in columns:
        bad = bad | ~pl.col(f"__{name}").is_finite().fill_null(False)
    if values.select(bad.any()).item():
        _raise_first_problem(path, values.filter(bad), columns)
    return values.select("line", *[pl.col(f"__{name}").alias(name) for name in columns])


def _raise_first_problem(path: Path, problems: pl.DataFrame, columns: tuple[str, ...]) -> None:
    """Explain the first bad line: wrong field count, a field that is not a number, or a non-finite value."""
    first = problems.row(0, named=True)
    if first["__count"] != len(columns):
        raise DataError(f"expected {len(columns)} columns ({' '.join(columns)}), found "
                        f"{first['__count']}: {first['raw'][:80]!r}", path=path, line=first["line"])
    for name in columns:
        if first[f"__{name}"] is None:
            raise DataError(f"column '{name}' is not a number: {first[name]!r}", path=path, line=first["line"])
        if not math.isfinite(first[f"__{name}"]):
            raise DataError(f"column '{name}' is not finite: {first[name]!r}", path=path, line=first["line"])
