"""An experiment's data stages (stages/data_stages.py): a config chaining a CSV ingest, an augmentation, quick
runs and the report; each stage built only when its options or inputs changed, asserted from the stage records."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.schemas.stage_record import read_stage_record
from trajflow_pipeline.stages.data_stages import data_status
from trajflow_pipeline.stages.experiment import run_experiment
from trajflow_pipeline.stages.experiment_config import apply_overrides, load_experiment, load_saved_experiment
from trajflow_pipeline.stages.status import experiment_status

CONFIG = """
name = "csv_chain"
[data]
path = "{data}/walk"
ingest = "csv"
raw = "{raw}"
dt = 0.4
columns = {{ scene = "scene", agent = "id" }}
n_past = 4
n_future = 6
folds = 2
[[augment]]
kind = "scale-rotate"
copies = 3
[protocol]
models = ["trajflow", "cv"]
folds = ["0"]
[train]
set = ["train.ae_max_epochs=1", "train.ae_min_epochs=1", "train.flow_max_epochs=1", "train.flow_min_epochs=1",
       "model.flow_layers=2"]
[eval]
samples = 5
k = 3
workers = 1
metrics = ["min_ade", "min_fde", "nll"]
"""


def write_walkers(path: Path, seed: int = 0) -> Path:
    """A CSV of 4 scenes x 4 pedestrians walking straight for 40 frames, with its own column names."""
    rng = np.random.default_rng(seed)
    scene, agent, frame = np.meshgrid(np.arange(4), np.arange(4), np.arange(40), indexing="ij")
    start, velocity = rng.normal(size=(4, 4, 1, 2)) * 5, rng.normal(size=(4, 4, 1, 2))
    xy = start + velocity * (frame[..., None] * 0.4)
    pl.DataFrame({"scene": np.char.add("s", scene.ravel().astype(str)),
                  "id": np.char.add("p", agent.ravel().astype(str)),
                  "frame": frame.ravel(), "x": xy[..., 0].ravel(), "y": xy[..., 1].ravel()}).write_csv(path)
    return path


@pytest.fixture()
def chain(tmp_path: Path) -> Path:
    raw = write_walkers(tmp_path / "walk.csv")
    config = tmp_path / "chain.toml"
    config.write_text(CONFIG.format(data=(tmp_path / "data").as_posix(), raw=raw.as_posix()))
    return config


def builds(data: Path) -> dict[str, int]:
    """Builds per data stage directory, from the stage records."""
    return {path.name: record.builds for path in sorted(data.iterdir())
            if path.is_dir() and (record := read_stage_record(path)) is not None}


def finished(exp: Path) -> dict[str, str]:
    """When each run's training finished (run.json)."""
    return {run.name: json.loads((run / "run.json").read_text())["finished"] for run in sorted((exp / "runs").iterdir())
            if run.is_dir()}


def test_csv_to_augmentation_to_runs_to_report_builds_each_stage_only_when_its_inputs_change(chain: Path) -> None:
    exp, data = chain.parent / "exp", chain.parent / "data"
    run_experiment(chain, exp, quiet=True, report=True)  # as the command does unless --no-report
    assert builds(data) == {"walk": 1, "walk_scale_rotate": 1}
    assert "trajflow" in (exp / "report" / "report.md").read_text().lower()
    first = finished(exp)
    assert set(first) == {"trajflow-0-s0", "cv-0-s0"}

    run_experiment(chain, exp, quiet=True)  # unchanged: nothing is built or trained again
    assert builds(data) == {"walk": 1, "walk_scale_rotate": 1} and finished(exp) == first

    run_experiment(chain, exp, quiet=True, overrides=["augment.0.copies=2"])
    assert builds(data) == {"walk": 1, "walk_scale_rotate": 2}  # the augmentation only, not the ingest
    again = finished(exp)
    assert set(again) == set(first) and all(again[run] != first[run] for run in first)  # every run trained again
    assert sorted(p.name for p in (exp / "superseded").iterdir()) == sorted(first)  # the old runs kept aside
    assert read_stage_record(data / "walk_scale_rotate").options == {"copies": 2}
    assert load_saved_experiment(exp).augment[0].options == {"copies": 2}  # status sees what it ran with

    status = experiment_status(exp)
    assert [(s.stage.label, s.state, s.record.builds) for s in status.data] == [
        ("ingest csv", "reused", 1), ("augment scale-rotate", "reused", 2)]
    assert {run.state for run in status.runs} == {"done"}
    # back to the file's 3 copies: the status tells before anything runs
    assert [s.state for s in data_status(load_experiment(chain))] == ["reused", "stale"]


def test_raw_content_decides_not_its_place_or_time(chain: Path, tmp_path: Path) -> None:
    config = load_experiment(chain)
    run_experiment(chain, tmp_path / "exp", quiet=True, overrides=['protocol.models=["cv"]'])
    raw = tmp_path / "walk.csv"
    os.utime(raw, ns=(raw.stat().st_atime_ns, raw.stat().st_mtime_ns + 10**9))  # touched, same content
    moved = tmp_path / "elsewhere" / "walk.csv"
    moved.parent.mkdir()
    shutil.copy(raw, moved)  # the same file in another place (another machine)
    assert [s.state for s in data_status(config)] == ["reused", "reused"]
    run_experiment(chain, tmp_path / "exp", quiet=True,
                   overrides=['protocol.models=["cv"]', f"data.raw={moved.as_posix()}"])
    assert builds(tmp_path / "data") == {"walk": 1, "walk_scale_rotate": 1}
    write_walkers(raw, seed=1)  # other content
    states = data_status(config)
    assert [(s.state, s.reason) for s in states] == [("stale", "the raw input changed"),
                                                     ("stale", "the stage before it is built again first")]


@pytest.mark.parametrize("override, message", [
    ("data.ingest=argoverse", r"\[data\] ingest must be one of .*got 'argoverse'"),
    ("data.camera=cam4", r"unknown key\(s\) camera in \[data\]: ingest csv takes dt, columns"),
    ("data.n_past=2.5", r"\[data\] n_past must be int, got 2.5"),
    ("data.raw=nowhere.csv", r"\[data\] raw: nowhere.csv does not exist"),
    ("augment.0.kind=mirror", r"\[\[augment\]\] 0 \(augment.0\) kind must be one of forking, scale-rotate"),
    ("augment.0.copies=many", r"\[\[augment\]\] 0 \(augment.0\) copies must be int"),
    ("augment.0.mirror=true", r"unknown key\(s\) mirror in \[\[augment\]\] 0"),
    ("augment.1.copies=2", r"--set 'augment.1.copies=2': augment has 1 item\(s\)"),
])
def test_bad_data_stages_are_refused_before_any_work_naming_file_and_key(chain: Path, override: str,
                                                                         message: str) -> None:
    with pytest.raises(UsageError, match=message) as error:
        run_experiment(chain, chain.parent / "exp", quiet=True, overrides=[override])
    assert override.startswith("augment.1") or str(chain) in str(error.value)
    assert not (chain.parent / "exp").exists() and not (chain.parent / "data").exists()


def test_forking_is_refused_for_an_ingest_without_multi_future_data(tmp_path: Path) -> None:
    config = tmp_path / "eth.toml"
    config.write_text('[data]\npath = "d"\ningest = "eth-ucy"\nraw = "r"\n[[augment]]\nkind = "forking"\n')
    with pytest.raises(UsageError, match=r"eth.toml: \[\[augment\]\] 0 \(augment.0\) kind = 'forking' needs "
                                         r"multi-future data.*ingest eth-ucy does not make"):
        load_experiment(config)


def test_overrides_set_dotted_keys_as_toml_values_or_strings() -> None:
    raw = {"data": {"path": "d"}, "augment": [{"kind": "forking"}]}
    result = apply_overrides(raw, ["data.raw=/some where/x", "augment.0.copies=5", "eval.metrics=[\"nll\"]",
                                   'data.name="007"'], Path("c.toml"))
    assert result == {"data": {"path": "d", "raw": "/some where/x", "name": "007"},
                      "augment": [{"kind": "forking", "copies": 5}], "eval": {"metrics": ["nll"]}}
    assert raw == {"data": {"path": "d"}, "augment": [{"kind": "forking"}]}  # the config itself is left as it was
    with pytest.raises(UsageError, match="expected KEY=VALUE"):
        apply_overrides(raw, ["data.raw"], Path("c.toml"))
    with pytest.raises(UsageError, match="data.path is not a table"):
        apply_overrides(raw, ["data.path.x=1"], Path("c.toml"))


def test_a_stage_never_replaces_what_is_not_a_dataset(chain: Path) -> None:
    notes = chain.parent / "data" / "walk" / "notes.txt"
    notes.parent.mkdir(parents=True)
    notes.write_text("mine")
    with pytest.raises(UsageError, match="walk: holds something that is not a trajflow dataset.*ingest csv"):
        run_experiment(chain, chain.parent / "exp", quiet=True)
    assert notes.read_text() == "mine"


def test_the_command_ends_with_the_report_and_status_lists_the_data_stages(chain: Path) -> None:
    from typer.testing import CliRunner

    from trajflow_pipeline.cli.app import app

    exp = chain.parent / "exp"
    result = CliRunner().invoke(app, ["experiment", str(chain), "-o", str(exp), "--set", 'protocol.models=["cv"]'])
    assert result.exit_code == 0, result.output
    assert (exp / "report" / "report.html").is_file() and "report:" in result.output
    status = json.loads(CliRunner().invoke(app, ["status", str(exp), "--json"]).output)
    assert [(s["name"], s["state"], s["builds"]) for s in status["data"]] == [("csv", "reused", 1),
                                                                              ("scale-rotate", "reused", 1)]
    (exp / "report" / "report.html").unlink()
    result = CliRunner().invoke(app, ["experiment", str(chain), "-o", str(exp), "--set", 'protocol.models=["cv"]',
                                      "--no-report"])
    assert result.exit_code == 0 and not (exp / "report" / "report.html").exists()


def test_a_config_without_ingest_needs_its_dataset(tmp_path: Path) -> None:
    config = tmp_path / "given.toml"
    config.write_text(f'[data]\npath = "{(tmp_path / "nothing").as_posix()}"\n[protocol]\nmodels = ["cv"]\n')
    with pytest.raises(UsageError, match="nothing: dataset not found, and the experiment config names no ingest"):
        run_experiment(config, tmp_path / "exp", quiet=True)
