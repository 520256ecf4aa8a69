"""`trajflow train` command line: options reach the stage, errors are one line with a non-zero exit code."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from trajflow_pipeline import data as data_module
from trajflow_pipeline.cli.train_cmd import train_command
from trajflow_pipeline.model.config import load_config
from trajflow_pipeline.model.toy import bimodal_batch
from train_fakes import FakeProblems


@pytest.fixture
def app(monkeypatch: pytest.MonkeyPatch) -> typer.Typer:
    def load_problems(dataset_dir: object, fold: str | None = None, split: str = "train") -> FakeProblems:
        batch, _ = bimodal_batch(48 if split == "train" else 16, seed=0 if split == "train" else 1)
        return FakeProblems(batch=batch, n_past=batch.n_past, n_future=batch.n_future)

    monkeypatch.setattr(data_module, "load_problems", load_problems)
    application = typer.Typer()
    application.command("train")(train_command)
    application.command("noop")(lambda: None)     # two commands, so that "train" is a sub-command as in the app
    return application


def test_options_reach_the_run(app: typer.Typer, tmp_path: Path) -> None:
    config = tmp_path / "cfg.toml"
    config.write_text("[train]\nflow_max_epochs = 2\nflow_min_epochs = 0\n[model]\nflow_layers = 3\n")
    result = CliRunner().invoke(app, ["train", str(tmp_path / "data"), "-o", str(tmp_path / "run"),
                                      "--model", "trajflow-no-ae", "--config", str(config), "--set",
                                      "model.flow_hidden=[8, 8]", "--set", "train.flow_batch_size=16", "--seed", "3",
                                      "--device", "cpu", "--quiet"])
    assert result.exit_code == 0, result.output
    resolved = load_config(tmp_path / "run" / "config.toml")
    assert (resolved.model.name, resolved.model.flow_layers, resolved.model.flow_hidden) == ("trajflow-no-ae", 3,
                                                                                              (8, 8))
    assert (resolved.train.seed, resolved.train.flow_batch_size, resolved.train.device) == (3, 16, "cpu")
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "finished"
    again = CliRunner().invoke(app, ["train", str(tmp_path / "data"), "-o", str(tmp_path / "run"), "--resume",
                                     "--quiet"])
    assert again.exit_code == 0, again.output


@pytest.mark.parametrize("args, message, code", [
    (["--set", "train.bogus=1"], "unknown config key 'train.bogus'", 2),
    (["--model", "nope"], "unknown model 'nope'", 2),
    (["--set", "flow_lr"], "key=value", 2),
])
def test_errors_are_one_line(app: typer.Typer, tmp_path: Path, args: list[str], message: str, code: int) -> None:
    result = CliRunner().invoke(app, ["train", str(tmp_path / "d"), "-o", str(tmp_path / "run"), "--quiet", *args])
    assert result.exit_code == code
    assert message in result.output and "Traceback" not in result.output


def test_autoencoder_from_reaches_the_run(app: typer.Typer, tmp_path: Path) -> None:
    budget = ["--set", "train.ae_max_epochs=1", "--set", "train.flow_max_epochs=1", "--set", "train.ae_min_epochs=0",
              "--set", "train.flow_min_epochs=0", "--quiet"]
    source = CliRunner().invoke(app, ["train", str(tmp_path / "data"), "-o", str(tmp_path / "source"), *budget])
    assert source.exit_code == 0, source.output
    result = CliRunner().invoke(app, ["train", str(tmp_path / "data"), "-o", str(tmp_path / "run"), *budget,
                                      "--set", "train.flow_lr=3e-4", "--autoencoder-from", str(tmp_path / "source")])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "run" / "run.json").read_text())["autoencoder_from"]["run"] == str(
        (tmp_path / "source").resolve())
    refused = CliRunner().invoke(app, ["train", str(tmp_path / "data"), "-o", str(tmp_path / "run2"), *budget,
                                       "--set", "train.ae_lr=3e-4", "--autoencoder-from", str(tmp_path / "source")])
    assert refused.exit_code == 2 and "train.ae_lr" in refused.output and "Traceback" not in refused.output
