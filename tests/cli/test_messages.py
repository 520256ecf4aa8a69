"""Messages and tables print exactly as composed: text that looks like rich markup or an emoji code is kept."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal
from trajflow_pipeline.util.progress import say

LOOKS_LIKE_MARKUP = "run[1].csv:100: [red]x[/] :smile: [bold] [/ab]"


def test_say_prints_every_character(capsys: pytest.CaptureFixture[str]) -> None:
    say(("warning:", "yellow"), " ", LOOKS_LIKE_MARKUP)
    assert capsys.readouterr().err.rstrip("\n") == "warning: " + LOOKS_LIKE_MARKUP


def test_cli_errors_name_odd_paths_exactly(tmp_path: Path) -> None:
    odd = tmp_path / "data [1] :100: [red]x[/] :thumbs_up:"
    result = CliRunner().invoke(app, ["inspect", str(odd)])
    assert result.exit_code == 1
    assert str(odd) in result.output and "💯" not in result.output and "👍" not in result.output


def test_tables_show_cells_exactly(tmp_path: Path) -> None:
    """inspect's tables hold data-derived text (the dataset's name and path here)."""
    data = ingest_synthetic_bimodal(tmp_path / "d [x] :100:", samples=40, seed=1, quiet=True)
    result = CliRunner().invoke(app, ["inspect", str(data)], env={"COLUMNS": "400"})
    assert result.exit_code == 0, result.output
    # the table's title wraps to the table's width wherever the temporary path is long: compare without spaces
    assert "d[x]:100:" in "".join(result.output.split()) and "💯" not in result.output


@pytest.mark.parametrize("name", ["n" * 250, "é" * 127], ids=["250 ascii bytes", "254 utf-8 bytes"])
def test_long_output_names_get_legal_temporary_names(tmp_path: Path, name: str) -> None:
    """The temporary sibling of a result adds a prefix and random characters; a final name near the file
    system's 255-byte limit must still work: for a dataset directory, a replaced one and a single file."""
    from trajflow_pipeline.util.atomic import atomic_directory, atomic_write_text

    data = ingest_synthetic_bimodal(tmp_path / name, samples=40, seed=1, quiet=True)
    assert data.name == name
    again = ingest_synthetic_bimodal(tmp_path / name, samples=40, seed=2, quiet=True, overwrite=True)
    assert again == data and [p.name for p in tmp_path.iterdir()] == [name]
    atomic_write_text(tmp_path / name / name, "text")
    assert (tmp_path / name / name).read_text() == "text"
    with atomic_directory(tmp_path / "out" / name) as tmp:
        (tmp / "x").write_text("1")
    assert (tmp_path / "out" / name / "x").read_text() == "1"


def test_long_names_with_undecodable_bytes_get_legal_temporary_names(tmp_path: Path) -> None:
    """POSIX names are bytes: 10 bytes that are not UTF-8 and 122 two-byte characters (254 bytes)."""
    import os

    from trajflow_pipeline.util.atomic import atomic_write_text

    name = os.fsdecode(b"\xff" * 10 + "é".encode() * 122)
    atomic_write_text(tmp_path / name, "text")
    assert (tmp_path / name).read_text() == "text" and len(list(tmp_path.iterdir())) == 1
