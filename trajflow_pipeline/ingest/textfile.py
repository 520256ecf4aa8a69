"""Reading input text files with errors that name the file and the line a text editor shows (only \\n ends a line):
whitespace-separated numeric tables, and the starting line of each record of a CSV file.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import polars as pl

from ..errors import DataError
from ..util import input_files

#: The largest magnitude an input number may have. Integers up to it are exact in float64 (frames, ids, times on a
#: grid); coordinates up to it stay finite in the float32 tensors models train on and fit the Int64 grid on which
#: identical inputs are compared (1 mm steps: 2^53 / 1e-3 < 2^63). Anything larger is a unit or parsing mistake.
MAX_MAGNITUDE = 2.0 ** 53


def in_range(value: pl.Expr) -> pl.Expr:
    """True where a Float64 value is finite and within :data:`MAX_MAGNITUDE` (null stays null)."""
    return value.is_finite() & (value.abs() <= MAX_MAGNITUDE)


def range_problem(value: float) -> str:
    """Why a parsed number that fails :func:`in_range` is refused: not finite, or too large."""
    if not math.isfinite(value):
        return "not finite"
    return f"beyond the largest magnitude accepted (2^53 = {MAX_MAGNITUDE:.4g})"


def split_lines(text: str) -> list[str]:
    """The lines of `text` as a text editor (or `sed -n Np`) numbers them: only \\n ends a line, a \\r before it is
    dropped. (str.splitlines also splits on \\r, \\v, \\f, \\x1c-\\x1e, U+0085, U+2028 and U+2029, which shifts the
    numbers of every line after one of those.)"""
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()
    return [line[:-1] if line.endswith("\r") else line for line in lines]


def _csv_lines(path: Path) -> Iterator[str]:
    """The lines of a CSV file for the csv module, numbered as :func:`split_lines` numbers them. A \\r that does
    not end a line is field content (as polars reads it) and is passed on as a space: the csv module would end a
    record there."""
    with open(input_files.regular_file(path), "rb") as handle:
        for raw in handle:  # binary files iterate on \n only
            text = raw.decode("utf-8", errors="replace")
            if text.endswith("\r\n"):
                text = text[:-2] + "\n"
            yield text.replace("\r", " ")


def csv_records(path: Path, *, strict: bool = False) -> Iterator[tuple[int, list[str]]]:
    """Each record of a CSV file, the header first, with the 1-based line it starts on (a quoted field may hold
    line breaks, so a record can span lines). Blank lines are records with no fields, as polars reads them (rows
    of nulls). With `strict`, malformed quoting (text after a closing quote) is a DataError at its line."""
    reader = csv.reader(_csv_lines(path), strict=strict)
    line = 1
    try:
        for record in reader:
            yield line, record
            line = reader.line_num + 1
    except csv.Error as error:
        raise DataError(f"malformed CSV ({error})", path=path, line=reader.line_num) from None


def csv_record_line(path: Path, row: int) -> int | None:
    """The line on which data row `row` (0-based, after the header) of a CSV file starts, or None past the end."""
    for index, (line, _) in enumerate(csv_records(path)):
        if index == row + 1:
            return line
    return None


def read_numeric_table(path: Path, columns: tuple[str, ...]) -> pl.DataFrame:
    """Read a TAB- or space-separated file of numbers into Float64 columns plus its 1-based `line` number.

    Blank lines are skipped; lines are numbered by :func:`split_lines` (other line-break characters inside a line
    are whitespace between fields). A line with the wrong number of fields, a field that is not a number, or a
    value that is not finite or beyond :data:`MAX_MAGNITUDE` raises a DataError naming the file and the first
    offending line.
    """
    try:
        text = input_files.read_bytes(path).decode("utf-8")  # not read_text: universal newlines end lines at \r
    except UnicodeDecodeError as error:
        raise DataError(f"not a text file ({error.reason} at byte {error.start})", path=path) from None
    except OSError as error:
        raise DataError(f"cannot read file ({error.strerror})", path=path) from None
    lines = (pl.DataFrame({"raw": pl.Series(split_lines(text), dtype=pl.String)})
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
        bad = bad | ~in_range(pl.col(f"__{name}")).fill_null(False)
    if values.select(bad.any()).item():
        _raise_first_problem(path, values.filter(bad), columns)
    return values.select("line", *[pl.col(f"__{name}").alias(name) for name in columns])


def read_numeric_tables(paths: Sequence[Path], columns: tuple[str, ...]) -> pl.DataFrame:
    """Read many numeric text files at once: `file` (position in `paths`), 1-based `line` and Float64 `columns`.

    Rows come in file order, then line order. Files that are cleanly TAB-separated (the common case) are parsed
    together by one CSV read, which is several times faster than splitting lines; any file with spaces, CR or an
    irregularity, and all files whenever that one read finds a problem, go through :func:`read_numeric_table`,
    so the errors (file, line, what is wrong) are the same on both paths.
    """
    contents = [_read_bytes(path) for path in paths]
    tab_only = [i for i, data in enumerate(contents) if data and b" " not in data and b"\r" not in data]
    parsed = _parse_tab_separated([contents[i] for i in tab_only], tab_only, columns) if tab_only else None
    fast = set(tab_only) if parsed is not None else set()
    parts = [] if parsed is None else [parsed]
    parts.extend(read_numeric_table(path, columns).select(pl.lit(i, dtype=pl.Int64).alias("file"),
                                                          pl.col("line").cast(pl.Int64), *columns)
                 for i, path in enumerate(paths) if i not in fast)
    return pl.concat(parts).sort("file", "line") if len(parts) > 1 else parts[0]


def _read_bytes(path: Path) -> bytes:
    try:
        return input_files.read_bytes(path)
    except OSError as error:
        raise DataError(f"cannot read file ({error.strerror})", path=path) from None


def _parse_tab_separated(contents: list[bytes], file_ids: list[int],
                         columns: tuple[str, ...]) -> pl.DataFrame | None:
    """One CSV read over the concatenated files, or None when any line is not exactly len(columns) finite
    numbers within :data:`MAX_MAGNITUDE` separated by single TABs (the caller then falls back to the line-by-line
    reader)."""
    chunks = [data if data.endswith(b"\n") else data + b"\n" for data in contents]
    line_counts = np.asarray([chunk.count(b"\n") for chunk in chunks], dtype=np.int64)
    buffer = b"".join(chunks)
    total = int(line_counts.sum())
    if buffer.count(b"\t") != (len(columns) - 1) * total:
        return None
    try:
        table = pl.read_csv(buffer, separator="\t", has_header=False, quote_char=None,
                            schema={name: pl.Float64 for name in columns})
    except (pl.exceptions.PolarsError, UnicodeDecodeError):
        return None
    if table.height != total or not table.select(pl.all_horizontal(in_range(pl.all()).fill_null(False)).all()
                                                 ).item():
        return None
    starts = np.repeat(np.cumsum(line_counts) - line_counts, line_counts)
    return table.select(pl.Series("file", np.repeat(np.asarray(file_ids, dtype=np.int64), line_counts)),
                        pl.Series("line", np.arange(total, dtype=np.int64) - starts + 1), *columns)


def _raise_first_problem(path: Path, problems: pl.DataFrame, columns: tuple[str, ...]) -> None:
    """Explain the first bad line: wrong field count, a field that is not a number, or one out of range."""
    first = problems.row(0, named=True)
    if first["__count"] != len(columns):
        raise DataError(f"expected {len(columns)} columns ({' '.join(columns)}), found "
                        f"{first['__count']}: {first['raw'][:80]!r}", path=path, line=first["line"])
    for name in columns:
        if first[f"__{name}"] is None:
            raise DataError(f"column '{name}' is not a number: {first[name]!r}", path=path, line=first["line"])
        if not (math.isfinite(first[f"__{name}"]) and abs(first[f"__{name}"]) <= MAX_MAGNITUDE):
            raise DataError(f"column '{name}' is {range_problem(first[f'__{name}'])}: {first[name]!r}", path=path,
                            line=first["line"])
