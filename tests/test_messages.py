"""Messages and tables print exactly as composed: text that looks like rich markup or an emoji code is kept."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.stages.ingest_synthetic import ingest_synthetic_bimodal
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
    assert "d [x] :100:" in result.output and "💯" not in result.output
