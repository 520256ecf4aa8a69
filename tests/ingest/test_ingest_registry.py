"""The ingest registry: every adapter resolves, unknown names list the registered ones, and the CLI and experiment
configs reach exactly the registered ingests; the warnings channel prints each problem once and collects it."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import typer

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.ingest.base import Ingest, collect_warnings, warn
from trajflow_pipeline.ingest.registry import LEVELX, NAMES, get_ingest
from trajflow_pipeline.stages.experiment_config import INGESTS, load_experiment

MODULES = {"eth-ucy": "eth_ucy", "synthetic-bimodal": "synthetic", "csv": "csv", "round": "round",
           "nuscenes": "nuscenes", "forking-paths": "forking_paths", "highd": "highd", "ind": "ind", "exid": "exid",
           "unid": "unid"}


@pytest.mark.parametrize("name", NAMES)
def test_every_name_resolves_to_its_modules_adapter(name: str) -> None:
    adapter = get_ingest(name)
    module = importlib.import_module(f"trajflow_pipeline.ingest.{MODULES[name]}")
    assert isinstance(adapter, Ingest) and adapter.name == name and adapter is module.ADAPTER
    assert adapter.function.__module__ == module.__name__
    assert adapter.dataset == getattr(module, "DATASET", None) and adapter.dt == getattr(module, "DT", None)
    assert "overwrite" not in adapter.options and "quiet" not in adapter.options


def test_the_datasets_are_registered() -> None:
    assert set(NAMES) == set(MODULES)


def test_unknown_name_is_a_usage_error_listing_the_names() -> None:
    with pytest.raises(UsageError) as error:
        get_ingest("argoverse")
    assert "'argoverse'" in str(error.value) and all(name in str(error.value) for name in NAMES)


def test_cli_ingest_subcommands_are_the_registry() -> None:
    ingest_group = typer.main.get_command(app).commands["ingest"]  # type: ignore[attr-defined]
    levelx = ingest_group.commands["levelx"].commands
    assert sorted(levelx) == sorted(LEVELX)
    assert sorted(set(ingest_group.commands) - {"levelx"} | set(levelx)) == sorted(NAMES)


def test_an_experiment_may_name_every_registered_ingest_and_no_other(tmp_path: Path) -> None:
    assert set(INGESTS) == set(NAMES)
    config = tmp_path / "exp.toml"
    for name in NAMES:
        raw = 'raw = "somewhere"\n' if get_ingest(name).raw is not None else ""
        dt = "dt = 0.4\n" if name == "csv" else ""  # the CSV ingest's one option without a default
        config.write_text(f'[data]\npath = "data"\ningest = "{name}"\n{raw}{dt}')
        assert load_experiment(config).ingest == name
    config.write_text('[data]\npath = "data"\ningest = "argoverse"\n')
    with pytest.raises(UsageError) as error:
        load_experiment(config)
    assert "got 'argoverse'" in str(error.value) and all(n in str(error.value) for n in NAMES)
    config.write_text('[data]\npath = "data"\ningest = "synthetic-bimodal"\nsamples = 40\nraw = "x"\n')
    with pytest.raises(UsageError, match="raw: ingest synthetic-bimodal generates its data and reads no raw input"):
        load_experiment(config)


def test_run_checks_raw_input_and_options(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="ingest eth-ucy needs the raw ETH/UCY folder"):
        get_ingest("eth-ucy").run(None, tmp_path / "out")
    with pytest.raises(UsageError, match="synthetic-bimodal generates its data"):
        get_ingest("synthetic-bimodal").run(tmp_path, tmp_path / "out")
    with pytest.raises(UsageError, match="unknown option.*sample.*allowed: samples, seed"):
        get_ingest("synthetic-bimodal").run(None, tmp_path / "out", sample=10)
    assert not (tmp_path / "out").exists()


def test_warn_prints_one_line_and_reaches_every_collector(capsys: pytest.CaptureFixture[str]) -> None:
    with collect_warnings() as outer:
        warn("no map expansion")
        with collect_warnings() as inner:
            warn("recording 03 contributes no samples")
    warn("after the blocks")
    assert outer == ["no map expansion", "recording 03 contributes no samples"]
    assert inner == ["recording 03 contributes no samples"]
    assert capsys.readouterr().err.splitlines() == ["warning: no map expansion",
                                                    "warning: recording 03 contributes no samples",
                                                    "warning: after the blocks"]
