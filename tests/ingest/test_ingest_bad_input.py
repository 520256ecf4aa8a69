"""Bad raw input through the CLI: one line naming the file and line, a non-zero exit, no traceback, no damage."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.ingest.eth_ucy import SEQUENCES

runner = CliRunner()


def write_flat_eth(folder: Path, peds: int = 3, frames: int = 25) -> Path:
    """Eight small sequences in the raw format: TAB-separated `frame ped x y`, frame step 10, float frames."""
    folder.mkdir(parents=True, exist_ok=True)
    for index, name in enumerate(SEQUENCES):
        lines = [f"{10.0 * f:.1f}\t{float(p):.1f}\t{0.4 * f + index:.2f}\t{float(p):.2f}"
                 for f in range(frames) for p in range(1, peds + 1)]
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return folder


def ingest(raw: Path, out: Path, *extra: str):
    return runner.invoke(app, ["ingest", "eth-ucy", str(raw), "-o", str(out), "--quiet", *extra])


def assert_one_line_error(result, *fragments: str) -> None:
    assert result.exit_code != 0
    assert result.exception is None or isinstance(result.exception, SystemExit)
    text = result.output.strip()
    assert "Traceback" not in text
    assert text.startswith("error: "), text
    assert len(text.splitlines()) == 1 or all(len(line) > 0 for line in text.splitlines())
    for fragment in fragments:
        assert fragment in text.replace("\n", ""), (fragment, text)


def test_small_flat_folder_ingests(tmp_path: Path) -> None:
    result = ingest(write_flat_eth(tmp_path / "raw"), tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "dataset.json").exists()


@pytest.mark.parametrize(("line", "fragments"), [
    ("10.0\t1.0\t2.0", ["biwi_eth.txt:4:", "expected 4 columns"]),
    ("10.0\t1.0\tabc\t2.0", ["biwi_eth.txt:4:", "column 'x' is not a number: 'abc'"]),
    ("10.0\t1.0\tnan\t2.0", ["biwi_eth.txt:4:", "column 'x' is not finite"]),
    ("10.0\t1.0\t1.0\tinf", ["biwi_eth.txt:4:", "column 'y' is not finite"]),
    ("10.0\t1.0\t1e300\t2.0", ["biwi_eth.txt:4:", "column 'x' is beyond the largest magnitude accepted"]),
    ("15.0\t1.0\t1.0\t1.0", ["biwi_eth.txt:4:", "not a multiple of the frame step 10"]),
    ("10.0\t1.5\t1.0\t1.0", ["biwi_eth.txt:4:", "ped must be a whole number"]),
    ("0.0\t1.0\t5.0\t5.0", ["biwi_eth.txt:4:", "duplicate row for frame 0, pedestrian 1", "biwi_eth.txt:1"]),
])
def test_malformed_lines_are_located(tmp_path: Path, line: str, fragments: list[str]) -> None:
    raw = write_flat_eth(tmp_path / "raw")
    path = raw / "biwi_eth.txt"
    lines = path.read_text().splitlines()
    lines.insert(3, line)
    path.write_text("\n".join(lines) + "\n")
    result = ingest(raw, tmp_path / "out")
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "out").exists()


def test_line_breaks_inside_lines_keep_the_line_numbers(tmp_path: Path) -> None:
    """A form feed, U+2028 or U+0085 between the fields of earlier lines is whitespace: the bad line keeps the
    number an editor shows."""
    raw = write_flat_eth(tmp_path / "raw")
    path = raw / "biwi_eth.txt"
    lines = path.read_text().splitlines()
    lines[0], lines[1], lines[2] = (line.replace("\t", sep, 1) for line, sep in zip(lines[:3], "\f\u2028\u0085"))
    lines.insert(5, "10.0\t1.0\tabc\t2.0")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert_one_line_error(ingest(raw, tmp_path / "out"), "biwi_eth.txt:6:", "column 'x' is not a number: 'abc'")


def test_empty_file_and_empty_folder(tmp_path: Path) -> None:
    raw = write_flat_eth(tmp_path / "raw")
    (raw / "students003.txt").write_text("\n\n")
    assert_one_line_error(ingest(raw, tmp_path / "out"), "students003.txt: file is empty")
    (tmp_path / "empty").mkdir()
    assert_one_line_error(ingest(tmp_path / "empty", tmp_path / "out"), "empty: folder is empty")
    assert_one_line_error(ingest(tmp_path / "nowhere", tmp_path / "out"), "raw ETH/UCY folder not found")


def test_missing_sequence_file(tmp_path: Path) -> None:
    raw = write_flat_eth(tmp_path / "raw")
    (raw / "uni_examples.txt").unlink()
    assert_one_line_error(ingest(raw, tmp_path / "out"), "missing sequence file(s) uni_examples.txt")


def test_output_holding_another_dataset_is_refused_and_kept(tmp_path: Path) -> None:
    other = tmp_path / "other"
    assert runner.invoke(app, ["ingest", "synthetic-bimodal", "-o", str(other), "--samples", "10", "-q"]).exit_code == 0
    before = (other / "samples.parquet").read_bytes()
    result = ingest(write_flat_eth(tmp_path / "raw"), other)
    assert_one_line_error(result, "already holds dataset 'synthetic_bimodal', not 'eth_ucy'")
    assert (other / "samples.parquet").read_bytes() == before
    assert ingest(tmp_path / "raw", other, "--overwrite").exit_code == 0


def test_failed_reingest_keeps_the_previous_dataset(tmp_path: Path) -> None:
    raw = write_flat_eth(tmp_path / "raw")
    out = tmp_path / "out"
    assert ingest(raw, out).exit_code == 0
    before = {p.name: p.read_bytes() for p in out.rglob("*.parquet")}
    (raw / "biwi_hotel.txt").write_text("0.0\t1.0\tbad\t0.0\n")
    assert_one_line_error(ingest(raw, out), "biwi_hotel.txt:1:")
    assert {p.name: p.read_bytes() for p in out.rglob("*.parquet")} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "raw"]


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    result = runner.invoke(app, ["--debug", "ingest", "eth-ucy", str(tmp_path / "none"), "-o", str(tmp_path / "o")])
    assert result.exit_code != 0
    assert result.exception is not None and not isinstance(result.exception, SystemExit)
