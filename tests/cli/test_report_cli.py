"""`trajflow report` through Typer: arguments, the printed location, one-line errors and exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from typer.testing import CliRunner

from test_report_stage import write_experiment, write_run
from trajflow_pipeline.cli.report_cmd import report_command

app = typer.Typer()
app.command("report")(report_command)
app.command("noop")(lambda: None)  # a second command, so `report` is a subcommand as in the real CLI
runner = CliRunner()


def test_cli_writes_the_report_and_says_where(tmp_path: Path) -> None:
    experiment = write_experiment(tmp_path / "exp", "eth_ucy", models=("trajflow",), folds=("eth",), seeds=(0, 1))
    result = runner.invoke(app, ["report", str(experiment), "-o", str(tmp_path / "rep"), "--examples", "1"])
    assert result.exit_code == 0, result.output
    assert "report.html" in result.output.replace("\n", "")
    figures = json.loads((tmp_path / "rep" / "report.json").read_text())["figures"]
    assert "figures/eth_ucy-examples.png" in figures


def test_cli_no_figures_and_quiet(tmp_path: Path) -> None:
    run = write_run(tmp_path, model="cv", dataset="eth_ucy", fold="eth", seed=0)
    result = runner.invoke(app, ["report", str(run), "--out", str(tmp_path / "rep"), "--no-figures", "--quiet"])
    assert result.exit_code == 0, result.output
    assert result.output == ""
    assert not list((tmp_path / "rep" / "figures").iterdir())


def test_cli_errors_are_one_line(tmp_path: Path) -> None:
    (tmp_path / "nothing").mkdir()
    result = runner.invoke(app, ["report", str(tmp_path / "nothing"), "-o", str(tmp_path / "rep")])
    assert result.exit_code == 1
    text = result.output.strip().replace("\n", "")
    assert text.startswith("error: ") and "nor an experiment" in text and "Traceback" not in text
    result = runner.invoke(app, ["report", str(tmp_path / "nothing"), "-o", str(tmp_path / "rep"),
                                 "--examples", "-1"])
    assert result.exit_code == 2
    result = runner.invoke(app, ["report", "-o", str(tmp_path / "rep")])
    assert result.exit_code == 2
