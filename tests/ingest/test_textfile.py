"""The batched numeric-text reader: its one-read fast path must agree with the line-by-line reader exactly."""

from __future__ import annotations

from pathlib import Path

import polars as pl
import pytest

from trajflow_pipeline.errors import DataError
from trajflow_pipeline.ingest.textfile import read_numeric_table, read_numeric_tables

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


@pytest.mark.parametrize("inside", ["\f", "\v", "\u2028", "\u2029", "\u0085", "\x1c", "\r"])
def test_line_break_characters_inside_a_line_do_not_shift_line_numbers(tmp_path: Path, inside: str) -> None:
    """Only \\n ends a line (\\r\\n too), as an editor or `sed -n Np` counts: str.splitlines would also split on
    these characters and name a later line than the bad one."""
    text = f"10\t1\t0.5{inside}1.5\n20\t1\t0.6\t1.6\r\n30\t1\tbad\t1.7\n"  # whitespace: a separator
    path = tmp_path / "odd.txt"
    path.write_text(text, encoding="utf-8", newline="")
    with pytest.raises(DataError) as error:
        read_numeric_tables([path], COLUMNS)
    message = str(error.value)
    if inside == "\x1c":  # not whitespace: the first line itself is wrong, and named as line 1
        assert "odd.txt:1: expected 4 columns" in message
    else:
        assert "odd.txt:3: column 'x' is not a number: 'bad'" in message
    fixed = tmp_path / "fixed.txt"
    fixed.write_text(text.replace("bad", "0.7").replace("\x1c", "\t"), encoding="utf-8", newline="")
    assert read_numeric_tables([fixed], COLUMNS).get_column("line").to_list() == [1, 2, 3]


@pytest.mark.parametrize("value", ["1e300", "-1e39", "9.1e15"])
def test_numbers_beyond_two_to_the_53_are_refused_at_their_line(tmp_path: Path, value: str) -> None:
    """Both the one-read TAB path and the line reader refuse magnitudes beyond 2^53 (float32 overflow, Int64 grid)."""
    for separator in ("\t", " "):
        path = write(tmp_path / "big.txt", separator.join(["10", "1", "0.5", "1.5"]) + "\n"
                     + separator.join(["20", "1", value, "1.6"]) + "\n")
        with pytest.raises(DataError, match=r"big\.txt:2: column 'x' is beyond the largest magnitude"):
            read_numeric_tables([path], COLUMNS)
    assert read_numeric_tables([write(tmp_path / "edge.txt", f"10\t1\t{2.0 ** 53}\t-1.5\n")], COLUMNS).height == 1
