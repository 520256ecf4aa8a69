"""Options and run state are checked before any work: a bad setting or seed is one usage line (exit 2) and no run
folder; `--resume` needs a run; a damaged run.json, config.toml, state.pt or model.safetensors is one line naming
the file (exit 1) from train --resume, train --autoencoder-from, eval and status alike."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.model import load_training_state, save_training_state
from trajflow_pipeline.model.config import load_config
from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal
from trajflow_pipeline.training import train
from trajflow_pipeline.util.bounds import check_seed

TINY = ["train.ae_max_epochs=1", "train.ae_min_epochs=0", "train.flow_max_epochs=1", "train.flow_min_epochs=0",
        "model.flow_layers=2", "model.flow_hidden=[8]"]
HUGE_SEED = "1234567890123456789012345"


def invoke(*args: str) -> tuple[int, list[str]]:
    """Run the CLI; its exit code and its output lines (stdout and stderr)."""
    result = CliRunner().invoke(app, list(args))
    assert "Traceback" not in result.output, result.output
    return result.exit_code, result.output.strip().splitlines()


def one_error(lines: list[str], *needles: str) -> None:
    """The output is one `error:` line holding every needle."""
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# ------------------------------------------------------------------------------------------- settings and seeds

@pytest.mark.parametrize("setting, shown", [
    ("train.ae_lr=nan", "nan"), ("train.flow_lr=inf", "inf"), ("train.ae_weight_decay=-1", "-1.0"),
    ("train.flow_weight_decay=nan", "nan"), ("model.alpha=-inf", "-inf"), ("train.val_fraction=1.5", "1.5"),
    ("train.flow_max_epochs=-1", "-1"), ("train.ae_batch_size=0", "0"), ("train.flow_lr_decay=0", "0.0"),
    ("train.grad_clip=nan", "nan"), ("model.flomo_scale_max=0.5", "0.5"), ("model.flow_hidden=[8, 0]", "[8, 0]"),
    ("train.seed=-1", "-1"), (f"train.flow_patience={HUGE_SEED}", HUGE_SEED),
])
def test_a_setting_out_of_bounds_is_a_usage_error_before_the_run_folder(tmp_path: Path, setting: str,
                                                                         shown: str) -> None:
    run = tmp_path / "run"
    code, lines = invoke("train", str(tmp_path / "data"), "-o", str(run), "--set", setting, "--quiet")
    assert code == 2
    one_error(lines, "--set", setting.split("=")[0], f"got {shown}")
    assert not run.exists()


def test_a_config_file_value_out_of_bounds_names_the_file(tmp_path: Path) -> None:
    config = tmp_path / "cfg.toml"
    config.write_text("[train]\nflow_lr = nan\n")
    code, lines = invoke("train", str(tmp_path / "data"), "-o", str(tmp_path / "run"), "--config", str(config))
    assert code == 2
    one_error(lines, str(config), "train.flow_lr", "got nan")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("seed", ["-1", HUGE_SEED])
def test_a_seed_out_of_range_is_a_usage_error_in_every_command(tmp_path: Path, seed: str) -> None:
    code, lines = invoke("train", str(tmp_path / "data"), "-o", str(tmp_path / "run"), "--seed", seed)
    assert code == 2 and not (tmp_path / "run").exists()
    one_error(lines, "--seed", f"got {seed}")
    code, lines = invoke("ingest", "synthetic-bimodal", "-o", str(tmp_path / "syn"), "--seed", seed, "--quiet")
    assert code == 2 and not (tmp_path / "syn").exists()
    one_error(lines, "--seed", f"got {seed}")
    code, lines = invoke("eval", str(tmp_path / "no-run"), "--seed", seed)   # before the run is even looked for
    assert code == 2
    one_error(lines, "--seed", f"got {seed}")
    experiment = tmp_path / "exp.toml"
    experiment.write_text(f"[data]\npath = '{tmp_path / 'data'}'\n[protocol]\nseeds = [0, {seed}]\n")
    code, lines = invoke("experiment", str(experiment), "-o", str(tmp_path / "exp"))
    assert code == 2 and not (tmp_path / "exp").exists()
    one_error(lines, str(experiment), "protocol.seeds", f"got {seed}")


def test_the_seed_rule_is_the_configs() -> None:
    """Every seed is checked by one rule: train.seed's bounds."""
    assert check_seed(2**63 - 1, "--seed") == load_config(overrides=[f"train.seed={2**63 - 1}"]).train.seed
    for bad in (-1, 2**63, True, "3"):
        with pytest.raises(UsageError, match="--seed must be an integer"):
            check_seed(bad, "--seed")


# ---------------------------------------------------------------------------------------------------- --resume

def test_resume_needs_a_run(tmp_path: Path) -> None:
    missing = tmp_path / "new"
    code, lines = invoke("train", str(tmp_path / "data"), "-o", str(missing), "--resume")
    assert code == 2 and not missing.exists()
    one_error(lines, str(missing), "no such run directory")
    (tmp_path / "empty").mkdir()
    code, lines = invoke("train", str(tmp_path / "data"), "-o", str(tmp_path / "empty"), "--resume")
    assert code == 2 and not any((tmp_path / "empty").iterdir())
    one_error(lines, "holds no run to resume", "config.toml")


# ------------------------------------------------------------------------------------------------ damaged state

@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return ingest_synthetic_bimodal(tmp_path_factory.mktemp("data") / "bimodal", samples=60, seed=5, quiet=True)


@pytest.fixture(scope="module")
def finished(data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train(data, tmp_path_factory.mktemp("runs") / "run", model="trajflow", overrides=TINY, quiet=True)


@pytest.fixture
def run(finished: Path, tmp_path: Path) -> Path:
    """A copy of the finished tiny run to damage."""
    return Path(shutil.copytree(finished, tmp_path / "run"))


def _edit_json(path: Path, change: Callable[[dict], object]) -> None:
    info = json.loads(path.read_text())
    change(info)
    path.write_text(json.dumps(info))


def _rewrite_safetensors(path: Path, change: Callable[[dict[str, torch.Tensor]], object]) -> None:
    with safe_open(str(path), framework="pt") as handle:
        metadata, tensors = handle.metadata(), {k: handle.get_tensor(k) for k in handle.keys()}
    change(tensors)
    save_file(tensors, str(path), metadata=metadata)


def _rewrite_state(path: Path, change: Callable[[dict], object]) -> None:
    state = load_training_state(path)
    change(state)
    save_training_state(path, {k: v for k, v in state.items() if k not in ("format", "format_version")})


def _first_weight(weights: dict[str, torch.Tensor]) -> str:
    return sorted(weights)[0]


RUN_JSON: dict[str, Callable[[Path], object]] = {
    "not JSON": lambda p: p.write_text("{broken"),
    "not UTF-8": lambda p: p.write_bytes(b'{"model": "\xff"}'),
    "a list": lambda p: p.write_text("[1, 2]"),
    "no seed": lambda p: _edit_json(p, lambda i: i.pop("seed")),
    "no fingerprint": lambda p: _edit_json(p, lambda i: i.pop("fingerprint")),
    "seed a string": lambda p: _edit_json(p, lambda i: i.update(seed="zero")),
    "fingerprint a list": lambda p: _edit_json(p, lambda i: i.update(fingerprint=[])),
    "revisions of numbers": lambda p: _edit_json(p, lambda i: i.update(code_revisions=[1])),
}
CONFIG_TOML: dict[str, Callable[[Path], object]] = {
    "not TOML": lambda p: p.write_text("[train\n"),
    "not UTF-8": lambda p: p.write_bytes(b"[train]\nflow_lr = '\xff'\n"),
    "wrong type": lambda p: p.write_text(p.read_text().replace("flow_lr = 0.001", "flow_lr = 'fast'")),
    "out of bounds": lambda p: p.write_text(p.read_text().replace("flow_lr = 0.001", "flow_lr = nan")),
    "unknown key": lambda p: p.write_text(p.read_text() + "bogus = 1\n"),
}
STATE_PT: dict[str, Callable[[Path], object]] = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:200]),
    "wrong shape": lambda p: _rewrite_state(p, lambda s: s["weights"].update(
        {_first_weight(s["weights"]): torch.zeros(3, 3)})),
    "missing tensor": lambda p: _rewrite_state(p, lambda s: s["weights"].pop(_first_weight(s["weights"]))),
    "no epoch": lambda p: _rewrite_state(p, lambda s: s.pop("epoch")),
    "weights a list": lambda p: _rewrite_state(p, lambda s: s.update(weights=[1])),
    "damaged config": lambda p: _rewrite_state(p, lambda s: s.update(config="{")),
}
MODEL_FILE: dict[str, Callable[[Path], object]] = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:300]),
    "wrong shape": lambda p: _rewrite_safetensors(p, lambda t: t.update({_first_weight(t): torch.zeros(3, 3)})),
    "missing tensor": lambda p: _rewrite_safetensors(p, lambda t: t.pop(_first_weight(t))),
}


def _unfinished(run: Path) -> None:
    """Mark the run as interrupted, so that --resume reads its training state."""
    _edit_json(run / "run.json", lambda info: info.update(status="training"))


@pytest.mark.parametrize("name", RUN_JSON)
def test_a_damaged_run_json_is_one_line_naming_it(data: Path, run: Path, name: str) -> None:
    _unfinished(run)
    RUN_JSON[name](run / "run.json")
    for args in (["train", str(data), "-o", str(run), "--resume", "--quiet"], ["eval", str(run), "--quiet"],
                 ["train", str(data), "-o", str(run.parent / "flow-only"), "--autoencoder-from", str(run), "--quiet",
                  *[f"--set={s}" for s in TINY]]):
        code, lines = invoke(*args)
        assert code == 1, (args, lines)
        one_error(lines, str(run / "run.json"))
    code, lines = invoke("status", str(run))
    assert code == 0
    if not name.startswith("no "):  # status shows what a run.json without some keys says; the others are damage
        assert any(line.startswith(f"run: {run / 'run.json'}:") for line in lines), lines


@pytest.mark.parametrize("damage", CONFIG_TOML.values(), ids=CONFIG_TOML.keys())
def test_a_damaged_config_toml_is_one_line_naming_it(data: Path, run: Path, damage: Callable[[Path], object]) -> None:
    damage(run / "config.toml")
    for args in (["train", str(data), "-o", str(run), "--resume", "--quiet"], ["eval", str(run), "--quiet"]):
        code, lines = invoke(*args)
        assert code == 1, (args, lines)
        one_error(lines, str(run / "config.toml"))
    code, lines = invoke("status", str(run))
    assert code == 0 and any(line.startswith(f"run: {run / 'config.toml'}:") for line in lines), lines


@pytest.mark.parametrize("damage", STATE_PT.values(), ids=STATE_PT.keys())
def test_a_damaged_training_state_is_one_line_naming_it(data: Path, run: Path,
                                                       damage: Callable[[Path], object]) -> None:
    _unfinished(run)
    damage(run / "checkpoints" / "state.pt")
    code, lines = invoke("train", str(data), "-o", str(run), "--resume", "--quiet")
    assert code == 1
    one_error(lines, str(run / "checkpoints" / "state.pt"))
    # the stage-end state another run starts from is checked the same way
    end = run / "checkpoints" / "end-autoencoder.pt"
    damage(end)
    code, lines = invoke("train", str(data), "-o", str(run.parent / "flow-only"), "--autoencoder-from", str(run),
                         "--quiet", *[f"--set={s}" for s in TINY])
    assert code == 1 and not (run.parent / "flow-only").exists()
    one_error(lines, str(end))


@pytest.mark.parametrize("damage", MODEL_FILE.values(), ids=MODEL_FILE.keys())
def test_a_damaged_model_file_is_one_line_naming_it(run: Path, damage: Callable[[Path], object]) -> None:
    damage(run / "final" / "model.safetensors")
    code, lines = invoke("eval", str(run), "--quiet")
    assert code == 1
    one_error(lines, str(run / "final" / "model.safetensors"))


def test_the_undamaged_copy_resumes_and_evaluates(data: Path, run: Path) -> None:
    """The damage above is what the errors come from: the same run, intact, continues and evaluates."""
    _unfinished(run)
    code, lines = invoke("train", str(data), "-o", str(run), "--resume", "--quiet")
    assert code == 0, lines
    code, lines = invoke("eval", str(run), "--quiet", "--samples", "4", "--k", "2", "--workers", "1",
                         "--metric", "min_ade")
    assert code == 0, lines


def test_experiment_autoencoder_from_a_missing_directory_is_one_usage_line(tmp_path: Path) -> None:
    experiment = tmp_path / "exp.toml"
    experiment.write_text(f"[data]\npath = '{tmp_path / 'data'}'\n[protocol]\nseeds = [0]\n")
    code, lines = invoke("experiment", str(experiment), "-o", str(tmp_path / "exp"), "--autoencoder-from",
                         str(tmp_path / "nowhere"))
    assert code == 2 and not (tmp_path / "exp").exists()
    one_error(lines, "--autoencoder-from", "nowhere", "no such directory")
