"""The batched numeric-text reader: its one-read fast path must agree with the line-by-line reader exactly."""

from __future__ import annotations

from pathlib import Path

import polars as pl
import pytest

from trajflow_pipeline.errors import DataError
from trajflow_pipeline.stages.textfile import read_numeric_table, read_numeric_tables

COLUMNS = ("frame", "ped", "x", "y")


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def line_by_line(paths: list[Path]) -> pl.DataFrame:
    """What read_numeric_tables must return, built from the reference reader file by file."""
    return pl.concat([read_numeric_table(path, COLUMNS).select(pl.lit(i, dtype=pl.Int64).alias("file"),
                                                               pl.col("line").cast(pl.Int64), *COLUMNS)
                      for i, path in enumerate(paths)])


def test_tab_files_read_in_one_pass_match_the_line_reader(tmp_path: Path) -> None:
    paths = [write(tmp_path / "a.txt", "10\t1\t0.5\t1.5\n20\t1\t0.6\t1.6\n"),
             write(tmp_path / "b.txt", "10.0\t2.0\t-3e-1\t4\n30\t7\t1\t2")]  # no trailing newline
    result = read_numeric_tables(paths, COLUMNS)
    assert result.equals(line_by_line(paths))
    assert result.get_column("line").to_list() == [1, 2, 1, 2]
    assert result.get_column("file").to_list() == [0, 0, 1, 1]


def test_spaces_blank_lines_and_crlf_fall_back_with_true_line_numbers(tmp_path: Path) -> None:
    paths = [write(tmp_path / "tab.txt", "10\t1\t0.5\t1.5\n"),
             write(tmp_path / "spaces.txt", "10  1 0.5   1.5\n20 1 0.6 1.6\n"),
             write(tmp_path / "blank.txt", "10\t1\t0.5\t1.5\n\n\n20\t1\t0.6\t1.6\n"),
             write(tmp_path / "crlf.txt", "10\t1\t0.5\t1.5\r\n20\t1\t0.6\t1.6\r\n")]
    result = read_numeric_tables(paths, COLUMNS)
    assert result.equals(line_by_line(paths))
    assert result.filter(pl.col("file") == 2).get_column("line").to_list() == [1, 4]


@pytest.mark.parametrize(("bad", "message"), [
    ("10\t1\t0.5", "expected 4 columns"),
    ("10\t1\tx\t1.5", "column 'x' is not a number"),
    ("10\t1\tnan\t1.5", "column 'x' is not finite"),
    ("10\t1\t0.5\t1.5\t9", "expected 4 columns"),
])
def test_a_bad_line_in_a_tab_file_is_named_by_file_and_line(tmp_path: Path, bad: str, message: str) -> None:
    good = write(tmp_path / "good.txt", "10\t1\t0.5\t1.5\n")
    broken = write(tmp_path / "broken.txt", f"10\t1\t0.5\t1.5\n20\t1\t0.6\t1.6\n{bad}\n")
    with pytest.raises(DataError, match=message) as error:
        read_numeric_tables([good, broken], COLUMNS)
    assert "broken.txt:3" in str(error.value)
