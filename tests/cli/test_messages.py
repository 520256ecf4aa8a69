"""Messages and tables print exactly as composed: text that looks like rich markup or an emoji code is kept."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console
from rich.table import Table
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.cli.render import show
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


def _console(width: int, terminal: bool) -> Console:
    return Console(file=io.StringIO(), width=width, force_terminal=terminal, color_system=None, markup=False,
                   emoji=False, highlight=False)


def _runs(leave_out: tuple[str, ...]) -> Table:
    """A status-like table: a no-wrap name, cells with spaces, one optional column."""
    headers = ("run", "state", "stage: epoch", "trained", "minADE/FDE")
    cells = ("trajflow-zara2-s1", "training or interrupted", "autoencoder: 35/5000", "70 min", "0.243/0.435")
    table = Table(title="experiment x")
    for header in headers:
        if header not in leave_out:
            table.add_column(header, no_wrap=header == "run")
    table.add_row(*(cell for header, cell in zip(headers, cells) if header not in leave_out))
    return table


def test_tables_written_to_a_pipe_keep_their_natural_width() -> None:
    """Not a terminal (a file, a pipe, CI's log): rich would assume 80 columns and cut cells with an ellipsis."""
    table = Table(title="wide")
    table.add_column("a")
    table.add_column("b")
    table.add_row("a" * 70, "b" * 70)
    out = _console(80, terminal=False)
    assert show(table, out) == []
    text = out.file.getvalue()
    assert "a" * 70 in text and "b" * 70 in text and "…" not in text


def test_tables_in_a_narrow_terminal_leave_out_optional_columns_then_wrap_at_spaces() -> None:
    narrow = _console(66, terminal=True)  # the longest words need 64 columns with the borders
    assert show(_runs, narrow, optional=("trained",)) == ["trained"]
    lines = narrow.file.getvalue().splitlines()
    assert max(len(line) for line in lines) <= 66 and "…" not in "".join(lines)
    assert "trained" not in "".join(lines)
    words = " ".join(lines).split()  # wrapped at spaces: every word whole, numbers never split
    for word in ("trajflow-zara2-s1", "training", "interrupted", "autoencoder:", "35/5000", "0.243/0.435"):
        assert word in words
    wide = _console(200, terminal=True)
    assert show(_runs, wide, optional=("trained",)) == []
    assert "70 min" in wide.file.getvalue()


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
