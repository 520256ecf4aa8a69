"""`training.train`: learning on a bimodal toy, run directory contents, resume == uninterrupted, bad input.

Most tests feed generated SceneBatches through a stand-in for `trajflow_pipeline.data.load_problems` (fast and
independent of the dataset readers); the last ones train on a real synthetic-bimodal dataset directory.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch

import trajflow_pipeline
from trajflow_pipeline import data as data_module
from trajflow_pipeline.errors import DataError, TrajflowError, UsageError
from trajflow_pipeline.model import compiled as compiled_module
from trajflow_pipeline.model import load_model, load_training_state, save_training_state
from trajflow_pipeline.model.config import load_config
from trajflow_pipeline.model.normalize import scene_speed, target_frame, to_local
from trajflow_pipeline.model.toy import bimodal_batch
from train_fakes import FakeProblems
from trajflow_pipeline import rundir
from trajflow_pipeline.rundir import open_run
from trajflow_pipeline.training import loop as train_loop
from trajflow_pipeline.training import train
from trajflow_pipeline.util import provenance

FAST = ["train.ae_min_epochs=0", "train.flow_min_epochs=0"]
TINY_MODEL = ["model.flow_layers=4", "model.flow_hidden=[16, 16]", "model.gnn_layers=2"]


def install_fake_data(monkeypatch: pytest.MonkeyPatch, n_train: int, n_val: int, *, neighbours: int = 2,
                      folds: tuple[str, ...] = (), nan_train: bool = False) -> None:
    """Serve bimodal toy problems for every dataset path; folds other than `folds` are a UsageError."""

    def load_problems(dataset_dir: object, fold: str | None = None, split: str = "train") -> FakeProblems:
        if fold is not None and fold not in folds:
            raise UsageError(f"fold '{fold}' does not exist in dataset 'toy'")
        n = {"train": n_train, "val": n_val, "test": n_val}[split]
        if n == 0:
            raise DataError("the selected split has no samples", path=Path(str(dataset_dir)) / "samples.parquet")
        batch, _ = bimodal_batch(n, seed={"train": 0, "val": 1, "test": 2}[split], neighbours=neighbours)
        if nan_train and split == "train":
            future = batch.future.clone()
            future[3, 5] = float("nan")
            batch = replace(batch, future=future)
        return FakeProblems(batch=batch, n_past=batch.n_past, n_future=batch.n_future)

    monkeypatch.setattr(data_module, "load_problems", load_problems)


def train_killed_and_resumed(monkeypatch: pytest.MonkeyPatch, run: Path, kill_after: tuple[str, int],
                             **options: object) -> Path:
    """Train into `run` until the epoch `kill_after` (stage, epoch) is checkpointed, die there, then resume."""

    class Killed(Exception):
        pass

    def hook(stage: str, epoch: int) -> None:
        if (stage, epoch) == kill_after:
            raise Killed()

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(Killed):
        train(run.parent / "data", run, resume=run.exists(), **options)
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    return train(run.parent / "data", run, resume=True, **options)


def interrupted_after_first_epoch(monkeypatch: pytest.MonkeyPatch, data: Path, run: Path, **options: object) -> None:
    """Start training `run` and stop it (KeyboardInterrupt) once its first epoch is checkpointed."""

    def hook(stage: str, epoch: int) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(KeyboardInterrupt):
        train(data, run, **options)
    monkeypatch.setattr(train_loop, "_epoch_hook", None)


def log_of(run: Path) -> pl.DataFrame:
    return pl.read_parquet(run / "train_log.parquet")


def final_weights(run: Path) -> dict[str, torch.Tensor]:
    return load_model(run / "final").state_dict()


def test_training_lowers_validation_nll_and_samples_both_modes(monkeypatch: pytest.MonkeyPatch,
                                                               tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 512, 128)
    run = train(tmp_path / "data", tmp_path / "run", model="trajflow", quiet=True,
                overrides=[*FAST, "train.ae_max_epochs=15", "train.flow_max_epochs=15", "train.ae_lr=5e-3",
                           "train.ae_batch_size=64"])
    log = log_of(run)
    for stage in ("autoencoder", "flow"):
        val = log.filter(pl.col("stage") == stage).get_column("val_loss")
        assert val.min() < val[0] - 0.1, f"{stage} validation loss did not improve: {val.to_list()}"
    flow_val = log.filter(pl.col("stage") == "flow").get_column("val_loss")
    assert flow_val.min() < 0
    model = load_model(run / "final", expected_model="trajflow")
    batch, _ = bimodal_batch(20, seed=7)
    trajectories, log_lik = model.sample(batch, 50, generator=torch.Generator().manual_seed(0))
    local = to_local(trajectories.reshape(20, -1, 2), target_frame(batch.past)).reshape(20, 50, 14, 2)
    final_y = local[:, :, -1, 1]
    left = float((final_y > 0).float().mean())
    assert 0.2 < left < 0.8, f"samples collapsed onto one mode (left fraction {left:.2f})"
    assert float(final_y.abs().median()) > 0.4, "samples do not reach the modes"
    assert torch.isfinite(log_lik).all()


def test_run_directory_contents(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 96, 32)
    run = train(tmp_path / "data", tmp_path / "run", model="flomo", seed=4, quiet=True,
                overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=2"])
    config = load_config(run / "config.toml")
    assert config.model.name == "flomo" and config.train.seed == 4 and config.train.flow_max_epochs == 2
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "finished" and info["trajflow_version"] == trajflow_pipeline.__version__
    assert info["fingerprint"]["dataset"] == "toy" and info["n_train"] == 96 and info["n_val"] == 32
    assert info["log_lik_space"] == "scaled_displacements" and info["best"]["flow"]["epoch"] >= 1
    log = log_of(run)
    assert log.columns[:7] == ["epoch", "stage", "train_loss", "val_loss", "lr", "seconds", "skipped_steps"]
    assert log.get_column("stage").to_list() == ["flow", "flow"]
    lr = log.get_column("lr").to_list()
    assert lr[1] == pytest.approx(lr[0] * 0.98)
    assert (run / "checkpoints" / "state.pt").is_file() and (run / "checkpoints" / "best-flow.safetensors").is_file()
    assert load_model(run / "final").name == "flomo"
    leftovers = [p.name for p in run.rglob("*") if ".tmp" in p.name]
    assert not leftovers


def test_a_compiled_flow_stage_trains_as_eager_and_is_recorded(monkeypatch: pytest.MonkeyPatch,
                                                                tmp_path: Path) -> None:
    monkeypatch.setattr(compiled_module, "COMPILE_BACKEND", "aot_eager")   # the traced graphs, without code generation
    install_fake_data(monkeypatch, 96, 32)
    options = [*FAST, *TINY_MODEL, "train.flow_max_epochs=2", "train.flow_batch_size=32"]
    compiled = train(tmp_path / "data", tmp_path / "compiled", model="flomo", quiet=True,
                     overrides=[*options, "train.compile_flow=on"])
    eager = train(tmp_path / "data", tmp_path / "eager", model="flomo", quiet=True,
                  overrides=[*options, "train.compile_flow=off"])
    assert json.loads((compiled / "run.json").read_text())["compiled"]["flow"].startswith("compiled in ")
    assert "compiled" not in json.loads((eager / "run.json").read_text())
    for name, value in final_weights(eager).items():
        assert torch.allclose(final_weights(compiled)[name], value, atol=1e-5), name
    # where and how a run computes may change when it goes on: a raised budget, now eager
    train(tmp_path / "data", compiled, model="flomo", quiet=True, resume=True,
          overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=3", "train.flow_batch_size=32",
                     "train.compile_flow=off"])
    assert log_of(compiled).height == 3


def test_a_run_keeps_its_compiled_kernels_and_a_resume_loads_them(monkeypatch: pytest.MonkeyPatch,
                                                                    tmp_path: Path) -> None:
    """What the compile made is kept in the run (stamped, checked) and handed to torch before a resume compiles;
    a damaged file is named in one line, ignored and replaced. (The backend here generates no kernels, so torch's
    artifacts are stood in for by known bytes; tests/model/test_model_compiled.py checks torch's side.)"""
    monkeypatch.setattr(compiled_module, "COMPILE_BACKEND", "aot_eager")
    made: list[bytes] = [b"kernels of the first process"]
    loaded: list[bytes] = []
    monkeypatch.setattr(train_loop, "compiled_kernels", lambda: made[-1])
    monkeypatch.setattr(train_loop, "preload_kernels", loaded.append)
    install_fake_data(monkeypatch, 96, 32)
    options = [*FAST, *TINY_MODEL, "train.flow_batch_size=32", "train.compile_flow=on"]
    run = train(tmp_path / "data", tmp_path / "run", model="flomo", quiet=True,
                overrides=[*options, "train.flow_max_epochs=1"])
    assert loaded == [] and rundir.read_compiled_kernels(run) == (made[0], None)

    made.append(b"kernels of the second process")
    train(tmp_path / "data", run, model="flomo", quiet=True, resume=True, overrides=[*options, "train.flow_max_epochs=2"])
    assert loaded == [made[0]]
    assert json.loads((run / "run.json").read_text())["compiled"]["flow"].endswith(" with the kernels the run had kept")
    assert rundir.read_compiled_kernels(run) == (made[1], None)

    kernels_file = run / rundir.COMPILED_KERNELS_FILE
    kernels_file.write_bytes(kernels_file.read_bytes()[:-3])                           # cut short, as a full disk does
    assert rundir.read_compiled_kernels(run)[1] == f"{kernels_file}: damaged (not the kernels trajflow wrote); " \
                                                   f"compiling from scratch"
    train(tmp_path / "data", run, model="flomo", quiet=True, resume=True, overrides=[*options, "train.flow_max_epochs=3"])
    assert loaded == [made[0]] and log_of(run).height == 3
    assert rundir.read_compiled_kernels(run) == (made[1], None)                           # replaced by a sound copy
    stamped = kernels_file.read_bytes().replace(torch.__version__.encode(), b"0.0.1", 1)
    kernels_file.write_bytes(stamped)
    assert rundir.read_compiled_kernels(run)[1] == (f"{kernels_file}: compiled by torch 0.0.1, this is "
                                                    f"{torch.__version__}; compiling anew")


def test_resume_gives_the_uninterrupted_result(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 80, 24)
    options = dict(model="trajflow", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.ae_max_epochs=3",
                                                             "train.flow_max_epochs=3", "train.ae_batch_size=32",
                                                             "train.flow_batch_size=32"])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)
    whole_info = json.loads((whole / "run.json").read_text())
    assert whole_info["code_revisions"] == [provenance.code_revision() or "unknown"]
    assert whole_info["machines"] == [provenance.machine_description("cpu")]

    class Killed(Exception):
        pass

    for stop_at in [("autoencoder", 2), ("flow", 1), ("flow", 3)]:
        def hook(stage: str, epoch: int, stop_at: tuple[str, int] = stop_at) -> None:
            if (stage, epoch) == stop_at:
                raise Killed(stop_at)

        monkeypatch.setattr(train_loop, "_epoch_hook", hook)
        # newer code continues the run after the first interruption: run.json keeps both revisions
        monkeypatch.setattr(provenance, "code_revision", lambda first=stop_at[0] == "autoencoder": (
            "rev-a" if first else "rev-b"))
        with pytest.raises(Killed):  # the first call starts the run: --resume needs one to continue
            train(tmp_path / "data", tmp_path / "parts", resume=(tmp_path / "parts").exists(), **options)
        assert not (tmp_path / "parts" / "final").exists()
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    train(tmp_path / "data", tmp_path / "parts", resume=True, **options)
    a, b = final_weights(whole), final_weights(tmp_path / "parts")
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name
    curve = ["stage", "epoch", "train_loss", "val_loss", "lr", "skipped_steps"]
    assert log_of(whole).select(curve).equals(log_of(tmp_path / "parts").select(curve))
    # A finished run resumes to itself.
    assert train(tmp_path / "data", tmp_path / "parts", resume=True, **options) == tmp_path / "parts"
    assert json.loads((tmp_path / "parts" / "run.json").read_text())["code_revisions"] == ["rev-a", "rev-b"]


def test_training_from_before_revisions_were_kept_is_marked_unrecorded(monkeypatch: pytest.MonkeyPatch,
                                                                       tmp_path: Path) -> None:
    """A state written by a release that kept no revisions resumes as ["unrecorded", <the code now>]."""
    install_fake_data(monkeypatch, 64, 16)
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=3"])

    class Killed(Exception):
        pass

    def hook(stage: str, epoch: int) -> None:
        if epoch == 1:
            raise Killed()

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(Killed):
        train(tmp_path / "data", tmp_path / "run", **options)
    state_path = tmp_path / "run" / "checkpoints" / "state.pt"
    state = load_training_state(state_path)
    del state["code_revisions"], state["format"], state["format_version"]
    save_training_state(state_path, state)
    monkeypatch.setattr(provenance, "code_revision", lambda: "rev-b")
    monkeypatch.setattr(train_loop, "_epoch_hook", lambda stage, epoch: hook(stage, epoch - 1))
    with pytest.raises(Killed):  # run.json names the continuing code while it trains, not only once it is done
        train(tmp_path / "data", tmp_path / "run", resume=True, **options)
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert (info["status"], info["code_revisions"]) == ("training", ["unrecorded", "rev-b"])
    assert info["machines"] == [provenance.machine_description("cpu")]  # the state still had its machines
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    train(tmp_path / "data", tmp_path / "run", resume=True, **options)
    assert json.loads((tmp_path / "run" / "run.json").read_text())["code_revisions"] == ["unrecorded", "rev-b"]
    assert provenance.revisions_after(["rev-a", "rev-b"]) == ["rev-a", "rev-b"]
    monkeypatch.setattr(provenance, "code_revision", lambda: None)          # not a git checkout
    assert provenance.revisions_after([]) == ["unknown"]


def test_resume_restores_flomo_randomness(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 64, 16)
    options = dict(model="flomo", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=3",
                                                          "train.flow_batch_size=32"])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)

    def hook(stage: str, epoch: int) -> None:
        if epoch == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "data", tmp_path / "parts", **options)
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    train(tmp_path / "data", tmp_path / "parts", resume=True, **options)
    a, b = final_weights(whole), final_weights(tmp_path / "parts")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_same_seed_same_curve_other_seed_other_curve(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 64, 16)
    overrides = [*FAST, *TINY_MODEL, "train.flow_max_epochs=2"]
    runs = [train(tmp_path / "d", tmp_path / f"r{i}", model="trajflow-no-ae", seed=seed, quiet=True,
                  overrides=overrides) for i, seed in enumerate((1, 1, 2))]
    losses = [log_of(run).get_column("train_loss").to_list() for run in runs]
    assert losses[0] == losses[1] and losses[0] != losses[2]


def test_constant_velocity_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 64, 16)
    run = train(tmp_path / "d", tmp_path / "run", model="cv", quiet=True)
    log = log_of(run)
    assert log.get_column("stage").to_list() == ["fit"]
    model = load_model(run / "final", expected_model="cv")
    assert 0 < float(model.sigma) < 1
    trajectories, _ = model.sample(bimodal_batch(3)[0], 5, steps=20)
    assert trajectories.shape == (3, 5, 20, 2)


def test_non_finite_steps_are_skipped_and_counted(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 64, 16, nan_train=True)
    run = train(tmp_path / "d", tmp_path / "run", model="trajflow-no-ae", quiet=True,
                overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=2", "train.flow_batch_size=16"])
    log = log_of(run)
    assert log.get_column("skipped_steps").to_list() == [1, 1]
    assert log.get_column("train_loss").is_finite().all()
    assert json.loads((run / "run.json").read_text())["skipped_steps"] == 2
    assert all(torch.isfinite(v).all() for v in final_weights(run).values())


def test_without_val_split_part_of_train_is_held_out(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 50, 0)
    run = train(tmp_path / "d", tmp_path / "run", model="cv", quiet=True)
    info = json.loads((run / "run.json").read_text())
    assert (info["n_train"], info["n_val"]) == (45, 5) and "held out" in info["validation"]


def test_bad_input_is_one_clear_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 32, 8, folds=("a",))
    data = tmp_path / "d"
    with pytest.raises(UsageError, match="unknown config key 'train.nope'"):
        train(data, tmp_path / "r1", overrides=["train.nope=1"], quiet=True)
    with pytest.raises(UsageError, match="unknown model 'flowmo'"):
        train(data, tmp_path / "r2", model="flowmo", quiet=True)
    with pytest.raises(UsageError, match="fold 'b' does not exist"):
        train(data, tmp_path / "r3", fold="b", model="cv", quiet=True)
    config = tmp_path / "cfg.toml"
    config.write_text("[train]\nflow_lr = 'fast'\n")
    with pytest.raises(UsageError, match="train.flow_lr"):
        train(data, tmp_path / "r4", config_path=config, quiet=True)
    run = train(data, tmp_path / "r5", fold="a", model="cv", quiet=True)
    with pytest.raises(UsageError, match="already holds a run"):
        train(data, run, model="cv", quiet=True)
    with pytest.raises(UsageError, match="different configuration"):
        train(data, run, model="flomo", resume=True, quiet=True)
    install_fake_data(monkeypatch, 0, 8)
    with pytest.raises(DataError, match="no samples"):
        train(data, tmp_path / "r6", model="cv", quiet=True)


def test_corrupt_checkpoint_on_resume_names_the_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 32, 8)
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=2"])
    interrupted_after_first_epoch(monkeypatch, tmp_path / "d", tmp_path / "run", **options)
    state = tmp_path / "run" / "checkpoints" / "state.pt"
    assert load_training_state(state)["epoch"] == 1
    state.write_bytes(b"not a checkpoint")
    with pytest.raises(TrajflowError, match="state.pt"):
        train(tmp_path / "d", tmp_path / "run", resume=True, **options)


def test_resume_continues_on_the_runs_own_fold(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 32, 8, folds=("a", "b"))
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.flow_max_epochs=2"])
    interrupted_after_first_epoch(monkeypatch, tmp_path / "d", tmp_path / "run", fold="a", **options)
    with pytest.raises(UsageError, match="started for fold 'a', not 'b'"):
        train(tmp_path / "d", tmp_path / "run", fold="b", resume=True, **options)
    requested: list[str | None] = []
    serve = data_module.load_problems
    monkeypatch.setattr(data_module, "load_problems", lambda path, fold=None, split="train": (
        requested.append(fold), serve(path, fold=fold, split=split))[1])
    train(tmp_path / "d", tmp_path / "run", resume=True, **options)  # no --fold: the run's own
    assert requested and set(requested) == {"a"}
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["fold"] == "a" and info["status"] == "finished"


def test_trains_on_a_real_dataset_directory(synthetic_dataset: Path, tmp_path: Path) -> None:
    run = train(synthetic_dataset, tmp_path / "run", model="trajflow", quiet=True,
                overrides=[*FAST, *TINY_MODEL, "train.ae_max_epochs=2", "train.flow_max_epochs=2"])
    info = json.loads((run / "run.json").read_text())
    assert info["dataset"] == "synthetic_bimodal" and info["n_past"] == 10 and info["n_future"] == 14
    assert info["fingerprint"]["manifest_sha256"]
    model = load_model(run / "final")
    problems = data_module.load_problems(synthetic_dataset, split="test")
    trajectories, log_lik = model.sample(problems.batch.index(slice(0, 4)).without_future(), 3, steps=20)
    assert trajectories.shape == (4, 3, 20, 2) and np.isfinite(log_lik.numpy()).all()
    with pytest.raises(UsageError, match="no folds"):
        train(synthetic_dataset, tmp_path / "run2", fold="0", model="cv", quiet=True)


def test_flow_standardize_is_fitted_logged_saved_and_resumed(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 80, 24)
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[
        *FAST, *TINY_MODEL, "model.flow_standardize=true", "model.flow_tail_bound=5", "train.flow_max_epochs=2",
        "train.flow_batch_size=32"])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)
    log = log_of(whole)
    assert log.get_column("stage").unique(maintain_order=True).to_list() == ["standardize", "flow"]
    model = load_model(whole / "final")
    assert model.stages == ("standardize", "flow") and bool((model.flow.scale != 1).all())

    parts = train_killed_and_resumed(monkeypatch, tmp_path / "parts", ("flow", 1), **options)
    a, b = final_weights(whole), final_weights(parts)
    assert a.keys() == b.keys() and {"flow.shift", "flow.scale"} <= a.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_flow_temperature_grid_fits_the_sampling_temperature_after_the_flow(monkeypatch: pytest.MonkeyPatch,
                                                                           tmp_path: Path) -> None:
    """model.flow_temperature_grid: a stage "temperature" after the flow keeps the grid value of the lowest
    sample-based validation NLL, logs and records the whole curve, saves the choice with the weights (the model
    then draws with it), leaves the flow as it was, and a resumed run ends as the uninterrupted one."""
    install_fake_data(monkeypatch, 80, 24)
    overrides = [*FAST, *TINY_MODEL, "train.flow_max_epochs=2", "train.flow_batch_size=32",
                 "train.flow_select_samples=20"]
    grid = ["model.flow_temperature_grid=[0.5, 1.0, 2.0]", "model.flow_temperature_problems=12"]
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[*overrides, *grid])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)
    log = log_of(whole)
    assert log.get_column("stage").unique(maintain_order=True).to_list() == ["flow", "temperature"]
    best = json.loads((whole / "run.json").read_text())["best"]["temperature"]
    curve = best["val_nll_by_temperature"]
    assert set(curve) == {"0.5", "1", "2"} and len(set(curve.values())) == 3 and best["problems"] == 12
    assert best["val_nll"] == min(curve.values()) == curve[f"{best['temperature']:g}"]
    assert log.filter(pl.col("stage") == "temperature").get_column("val_nll").to_list() == [best["val_nll"]]
    model = load_model(whole / "final")
    assert model.stages == ("flow", "temperature") and model.sampling_temperature() == best["temperature"]

    fitted = final_weights(whole)
    plain = final_weights(train(tmp_path / "data", tmp_path / "plain", model="trajflow-no-ae", quiet=True,
                                overrides=overrides))
    assert set(fitted) - set(plain) == {"fitted_temperature"}
    for name, tensor in plain.items():  # the stage changes the draws' temperature, not the flow
        assert torch.equal(fitted[name], tensor), name

    parts = final_weights(train_killed_and_resumed(monkeypatch, tmp_path / "parts", ("flow", 1), **options))
    assert parts.keys() == fitted.keys()
    for name in fitted:
        assert torch.equal(fitted[name], parts[name]), name


def test_the_temperature_stage_is_added_changed_and_dropped_when_a_run_resumes(monkeypatch: pytest.MonkeyPatch,
                                                                               tmp_path: Path) -> None:
    """`train --resume --set model.flow_temperature_grid=...`: a finished run fits the stage after the flow on its
    final flow and ends as a run trained with that grid from the start (weights, log, record), whether it kept its
    training state or is a published copy without it; a run in training takes the grid when it gets there; a new
    grid fits the stage again on the same draws, and an emptied one drops it, back to the flow as it was."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    base = [*FAST, *TINY_MODEL, "train.flow_max_epochs=2", "train.flow_batch_size=32", "train.flow_select_samples=20"]
    grid = ["model.flow_temperature_grid=[0.5, 1.0, 2.0]", "model.flow_temperature_problems=12"]
    options = dict(model="trajflow-no-ae", quiet=True)
    whole = train(data, tmp_path / "whole", overrides=[*base, *grid], **options)
    whole_best = json.loads((whole / "run.json").read_text())["best"]
    run = train(data, tmp_path / "run", overrides=base, **options)
    plain = final_weights(run)
    published = tmp_path / "published"
    shutil.copytree(run, published)
    shutil.rmtree(published / "checkpoints")
    interrupted_after_first_epoch(monkeypatch, data, tmp_path / "training", overrides=base, **options)
    for target in (run, published, tmp_path / "training"):
        train(data, target, resume=True, overrides=[*base, *grid], **options)
        same_run(target, whole)
        info = json.loads((target / "run.json").read_text())
        assert info["status"] == "finished" and info["best"] == whole_best, target
        assert load_config(target / "config.toml") == load_config(whole / "config.toml")

    train(data, run, resume=True, overrides=["model.flow_temperature_grid=[1.0, 2.0]"], **options)
    curve = json.loads((run / "run.json").read_text())["best"]["temperature"]["val_nll_by_temperature"]
    assert curve == {t: whole_best["temperature"]["val_nll_by_temperature"][t] for t in ("1", "2")}
    assert log_of(run).filter(pl.col("stage") == "temperature").height == 1

    train(data, run, resume=True, overrides=["model.flow_temperature_grid=[]"], **options)
    dropped = final_weights(run)
    assert dropped.keys() == plain.keys() and all(torch.equal(dropped[k], plain[k]) for k in plain)
    assert log_of(run).get_column("stage").unique().to_list() == ["flow"]
    assert "temperature" not in json.loads((run / "run.json").read_text())["best"]
    assert load_model(run / "final").stages == ("flow",)
    with pytest.raises(UsageError, match="model.flow_temperature_problems / model.speed_normalize_sample_threshold "
                                         "changed"):
        train(data, run, resume=True, overrides=["model.flow_bins=4"], **options)


@pytest.mark.parametrize("grid", [[], ["model.flow_temperature_grid=[0.5, 1.0, 2.0]",
                                       "model.flow_temperature_problems=12"]], ids=["no-grid", "grid"])
def test_a_new_sample_threshold_finishes_a_run_anew_with_the_same_flow(monkeypatch: pytest.MonkeyPatch,
                                                                      tmp_path: Path, grid: list[str]) -> None:
    """`train --resume --set model.speed_normalize_sample_threshold=...` on a finished run with speed_normalize,
    kept whole or published without its training state: no gradient stage runs again; the final model carries the
    setting (the temperature fitted again where the run has that stage) and is the run trained with it from the
    start."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    base = [*FAST, *TINY_MODEL, "train.flow_max_epochs=2", "train.flow_batch_size=32", "model.speed_normalize=true",
            "model.speed_normalize_max=1.0", *grid]
    threshold = ["model.speed_normalize_sample_threshold=1.05"]
    options = dict(model="trajflow-no-ae", quiet=True)
    whole = train(data, tmp_path / "whole", overrides=[*base, *threshold], **options)
    run = train(data, tmp_path / "run", overrides=base, **options)
    flow_rows = log_of(run).filter(pl.col("stage") == "flow").height
    published = tmp_path / "published"
    shutil.copytree(run, published)
    shutil.rmtree(published / "checkpoints")
    for target in (run, published):
        train(data, target, resume=True, overrides=[*base, *threshold], **options)
        same_run(target, whole)
        assert load_model(target / "final").config.speed_normalize_sample_threshold == 1.05
        assert log_of(target).filter(pl.col("stage") == "flow").height == flow_rows
        assert load_config(target / "config.toml") == load_config(whole / "config.toml")


def test_a_sample_threshold_matters_to_finished_runs_only_where_scenes_are_scaled() -> None:
    """What an experiment asks of its finished runs when the threshold changes (`refit_matters`): with
    model.speed_normalize their draws change, with or without the temperature stage; without it nothing does."""
    from trajflow_pipeline.training import refit_matters

    for model in ("trajflow", "cv"):
        for scaled in (True, False):
            old = load_config(overrides=[f"model.name={model}", f"model.speed_normalize={str(scaled).lower()}"])
            new = replace(old, model=replace(old.model, speed_normalize_sample_threshold=2.0))
            assert refit_matters(old, new) is scaled, (model, scaled)


def test_flow_temperature_and_its_grid_exclude_each_other() -> None:
    with pytest.raises(UsageError, match="flow_temperature_grid"):
        load_config(overrides=["model.flow_temperature=1.2", "model.flow_temperature_grid=[1.0, 1.2]"])
    with pytest.raises(UsageError, match="flow_temperature_grid"):
        load_config(overrides=["model.flow_temperature_grid=[0.0, 1.2]"])


def test_speed_normalize_fits_its_reference_once_saves_it_and_resumes(monkeypatch: pytest.MonkeyPatch,
                                                                     tmp_path: Path) -> None:
    """model.speed_normalize: the reference pace is the training split's median scene speed, fitted before the
    first stage, saved with the final weights, and a resumed run is the uninterrupted one."""
    install_fake_data(monkeypatch, 80, 24)
    options = dict(model="trajflow", quiet=True, overrides=[
        *FAST, *TINY_MODEL, "model.speed_normalize=true", "train.ae_max_epochs=2", "train.flow_max_epochs=2",
        "train.ae_batch_size=32", "train.flow_batch_size=32"])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)
    train_batch = data_module.load_problems(tmp_path / "data").batch
    speeds = scene_speed(train_batch.past, train_batch.neighbours, train_batch.neighbours_valid,
                         train_batch.neighbours_mask)
    assert float(load_model(whole / "final").speed_reference) == pytest.approx(float(speeds.median()))
    parts = train_killed_and_resumed(monkeypatch, tmp_path / "parts", ("autoencoder", 1), **options)
    a, b = final_weights(whole), final_weights(parts)
    assert a.keys() == b.keys() and "speed_reference" in a
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_flow_weights_selected_by_the_sample_based_validation_nll(monkeypatch: pytest.MonkeyPatch,
                                                                   tmp_path: Path) -> None:
    from safetensors.torch import load_file

    install_fake_data(monkeypatch, 80, 24)
    options = dict(model="trajflow-no-ae", quiet=True, overrides=[
        *FAST, *TINY_MODEL, "train.flow_max_epochs=5", "train.flow_batch_size=32", "train.flow_select=val_nll",
        "train.flow_select_every=2", "train.flow_select_problems=10", "train.flow_select_samples=20"])
    whole = train(tmp_path / "data", tmp_path / "whole", **options)
    flow = log_of(whole).filter(pl.col("stage") == "flow")
    checked = flow.filter(pl.col("val_nll").is_not_null())
    assert checked.get_column("epoch").to_list() == [2, 4, 5]  # every 2 epochs, and the last one
    assert checked.get_column("val_nll").is_finite().all()
    best = checked.sort("val_nll").row(0, named=True)
    info = json.loads((whole / "run.json").read_text())["best"]["flow"]
    assert info["selected_by"] == "val_nll" and info["epoch"] == best["epoch"]
    assert info["val_nll"] == pytest.approx(best["val_nll"])
    assert info["lowest_val_loss"] == pytest.approx(flow.get_column("val_loss").min())
    kept, final = load_file(str(whole / "checkpoints" / "best-flow.safetensors")), final_weights(whole)
    assert kept.keys() == final.keys() and all(torch.equal(kept[k], final[k]) for k in kept)
    by_loss = load_model(whole / "checkpoints" / "lowest-val-loss-flow.safetensors")  # kept for comparisons
    assert by_loss.state_dict().keys() == final.keys()

    parts = train_killed_and_resumed(monkeypatch, tmp_path / "parts", ("flow", 3), **options)
    # resumed == uninterrupted: the same checks, values and kept weights
    assert log_of(parts).drop("seconds", "samples_per_s").equals(log_of(whole).drop("seconds", "samples_per_s"))
    a, b = final_weights(whole), final_weights(parts)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_draws_rome_cannot_fit_do_not_end_a_val_nll_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import trajflow_pipeline.metrics as metrics_module

    def unfittable(*args: object, **kwargs: object) -> None:
        raise DataError("all 20 draws of agent 3 are identical")

    install_fake_data(monkeypatch, 80, 24)
    monkeypatch.setattr(metrics_module, "compute_metrics", unfittable)
    run = train(tmp_path / "data", tmp_path / "run", model="trajflow-no-ae", quiet=True, overrides=[
        *FAST, *TINY_MODEL, "train.flow_max_epochs=3", "train.flow_batch_size=32", "train.flow_select=val_nll",
        "train.flow_select_every=1", "train.flow_select_problems=10", "train.flow_select_samples=20"])
    assert log_of(run).filter(pl.col("stage") == "flow").get_column("val_nll").null_count() == 3
    best = json.loads((run / "run.json").read_text())["best"]["flow"]
    assert best["epoch"] == 3 and best["selected_by"].startswith("last epoch")


def budget_options(ae: int, flow: int, *extra: str) -> dict[str, object]:
    """Train options of a tiny TrajFlow run with the given epoch budgets."""
    return dict(model="trajflow", quiet=True, overrides=[*FAST, *TINY_MODEL, "train.ae_batch_size=32",
                                                         "train.flow_batch_size=32", f"train.ae_max_epochs={ae}",
                                                         f"train.flow_max_epochs={flow}", *extra])


def same_run(a: Path, b: Path) -> None:
    """The two runs trained the same: identical final weights and loss curves."""
    wa, wb = final_weights(a), final_weights(b)
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    curve = ["stage", "epoch", "train_loss", "val_loss", "lr", "skipped_steps"]
    assert log_of(a).select(curve).equals(log_of(b).select(curve))


def test_raised_budgets_give_the_run_the_larger_budget_would_have(monkeypatch: pytest.MonkeyPatch,
                                                                  tmp_path: Path) -> None:
    """Resuming a finished run with a larger flow budget continues the flow from its last epoch; a larger
    autoencoder budget continues the autoencoder and trains the flow anew. Either way the run ends as a run with
    those budgets from the start would have, and an extension interrupted half-way resumes to the same."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    run = train(data, tmp_path / "run", **budget_options(2, 2))
    assert (run / "checkpoints" / "end-autoencoder.pt").is_file() and (run / "checkpoints" / "end-flow.pt").is_file()

    train(data, run, resume=True, **budget_options(2, 4))
    same_run(run, train(data, tmp_path / "ae2-flow4", **budget_options(2, 4)))
    assert load_config(run / "config.toml").train.flow_max_epochs == 4
    assert json.loads((run / "run.json").read_text())["status"] == "finished"

    def hook(stage: str, epoch: int) -> None:
        if (stage, epoch) == ("flow", 2):
            raise KeyboardInterrupt

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(KeyboardInterrupt):
        train(data, run, resume=True, **budget_options(4, 4))
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    # Half-way: the old final model is still there, but the run is not finished, so nothing evaluates it.
    assert json.loads((run / "run.json").read_text())["status"] == "training"
    assert (run / "final" / "model.safetensors").is_file()
    with pytest.raises(TrajflowError, match="did not finish"):
        open_run(run)
    train(data, run, resume=True, quiet=True)      # the saved config already holds the new budgets
    same_run(run, train(data, tmp_path / "ae4-flow4", **budget_options(4, 4)))
    assert json.loads((run / "run.json").read_text())["best"]["autoencoder"]["epoch"] == 4


def test_a_stage_that_stopped_early_is_not_retrained(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 80, 24)
    early = ("train.flow_patience=1", "train.flow_lr=0.5")
    run = train(tmp_path / "data", tmp_path / "run", **budget_options(1, 8, *early))
    flow_epochs = log_of(run).filter(pl.col("stage") == "flow").height
    assert flow_epochs < 8, "the settings should make the flow stop early"
    before = (run / "final" / "model.safetensors").read_bytes()
    info = json.loads((run / "run.json").read_text())
    (run / "checkpoints" / "end-flow.pt").unlink()  # not needed: the log shows the stage stopped early
    train(tmp_path / "data", run, resume=True, **budget_options(1, 20, *early))
    assert (run / "final" / "model.safetensors").read_bytes() == before
    assert json.loads((run / "run.json").read_text()) == info
    assert log_of(run).filter(pl.col("stage") == "flow").height == flow_epochs
    assert load_config(run / "config.toml").train.flow_max_epochs == 20


def test_raised_patience_continues_a_stage_that_stopped_early(monkeypatch: pytest.MonkeyPatch,
                                                              tmp_path: Path) -> None:
    """More patience on a run whose flow stopped early continues the flow from its last epoch and ends as a run
    with that patience from the start; once the stage would have stopped there anyway, more is a no-op."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"

    def options(patience: int, flow: int = 12) -> dict[str, object]:
        return budget_options(1, flow, f"train.flow_patience={patience}", "train.flow_lr=0.5")

    run = train(data, tmp_path / "run", **options(1))
    stopped_at = log_of(run).filter(pl.col("stage") == "flow").height
    assert stopped_at < 12, "the settings should make the flow stop early"
    train(data, run, resume=True, **options(4))
    longer = train(data, tmp_path / "patience4", **options(4))
    same_run(run, longer)
    assert log_of(run).filter(pl.col("stage") == "flow").height > stopped_at
    assert load_config(run / "config.toml").train.flow_patience == 4
    assert json.loads((run / "run.json").read_text())["status"] == "finished"

    # A stage that ran its whole budget: more patience changes nothing, and the run stays as it was.
    full = train(data, tmp_path / "full", **options(1, flow=2))
    assert log_of(full).filter(pl.col("stage") == "flow").height == 2
    before = (full / "final" / "model.safetensors").read_bytes()
    train(data, full, resume=True, **options(5, flow=2))
    assert (full / "final" / "model.safetensors").read_bytes() == before
    assert load_config(full / "config.toml").train.flow_patience == 5
    (full / "checkpoints" / "end-flow.pt").unlink()  # not needed: the log shows the stage ran its whole budget
    train(data, full, resume=True, **options(6, flow=2))
    assert (full / "final" / "model.safetensors").read_bytes() == before

    # Less patience is not a budget raise, and an early-stopped stage without its end state cannot continue.
    with pytest.raises(UsageError, match="flow_patience"):
        train(data, run, resume=True, **options(2))
    (run / "checkpoints" / "end-flow.pt").unlink()
    with pytest.raises(UsageError, match="end-flow.pt is missing.*flow_patience 4 -> 6"):
        train(data, run, resume=True, **options(6))

    # Patience 0 (no early stopping) is the largest: raising to it runs the stage to its limit; leaving it, not.
    unstopped = train(data, tmp_path / "unstopped", **options(1))
    train(data, unstopped, resume=True, **options(0))
    same_run(unstopped, train(data, tmp_path / "patience0", **options(0)))
    assert log_of(unstopped).filter(pl.col("stage") == "flow").height == 12
    with pytest.raises(UsageError, match="flow_patience"):
        train(data, unstopped, resume=True, **options(3))


def test_only_raised_budgets_may_change_on_resume(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 64, 16)
    data = tmp_path / "data"
    run = train(data, tmp_path / "run", **budget_options(2, 2))
    with pytest.raises(UsageError, match="flow_max_epochs.*only train.ae_max_epochs / train.flow_max_epochs / "
                                         "train.ae_patience / train.flow_patience may be raised"):
        train(data, run, resume=True, **budget_options(2, 1))
    with pytest.raises(UsageError, match="flow_lr"):
        train(data, run, resume=True, **budget_options(2, 4, "train.flow_lr=3e-4"))
    # A run whose flow finished before stage-end states were kept cannot be extended exactly: it says so.
    (run / "checkpoints" / "end-flow.pt").unlink()
    with pytest.raises(UsageError, match="end-flow.pt is missing.*new directory"):
        train(data, run, resume=True, **budget_options(2, 4))
    assert load_config(run / "config.toml").train.flow_max_epochs == 2  # a refused change leaves the run as it was
    (run / "checkpoints" / "state.pt").unlink()
    with pytest.raises(UsageError, match="state.pt is missing"):
        train(data, run, resume=True, **budget_options(2, 4))


def test_new_execution_settings_on_a_finished_run_are_recorded_and_train_nothing(monkeypatch: pytest.MonkeyPatch,
                                                                                 tmp_path: Path) -> None:
    """A finished run resumed with another train.compile_flow keeps its final model and its finish time (so
    nothing evaluates it again) and records the setting."""
    install_fake_data(monkeypatch, 64, 16)
    data = tmp_path / "data"
    run = train(data, tmp_path / "run", **budget_options(2, 2))
    model, info = (run / "final" / "model.safetensors").read_bytes(), (run / "run.json").read_bytes()
    options = budget_options(2, 2, "train.compile_flow=off")
    train(data, run, resume=True, **options)
    assert (run / "final" / "model.safetensors").read_bytes() == model and (run / "run.json").read_bytes() == info
    assert load_config(run / "config.toml").train.compile_flow == "off"


def test_a_raise_interrupted_while_saving_is_completed_by_the_next_resume(monkeypatch: pytest.MonkeyPatch,
                                                                          tmp_path: Path) -> None:
    """Killed after the raise saved run.json and the checkpoint but not config.toml: the run must not look
    finished with the old model, and a plain --resume finishes the raise."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    run = train(data, tmp_path / "run", **budget_options(2, 2))
    real_write = train_loop.atomic_write_text

    def killed_at_config(path: Path, text: str) -> None:
        if Path(path).name == "config.toml":
            raise KeyboardInterrupt
        real_write(path, text)

    monkeypatch.setattr(train_loop, "atomic_write_text", killed_at_config)
    with pytest.raises(KeyboardInterrupt):
        train(data, run, resume=True, **budget_options(2, 4))
    monkeypatch.setattr(train_loop, "atomic_write_text", real_write)
    assert json.loads((run / "run.json").read_text())["status"] == "training"
    assert load_config(run / "config.toml").train.flow_max_epochs == 2
    train(data, run, resume=True, quiet=True)
    assert load_config(run / "config.toml").train.flow_max_epochs == 4
    same_run(run, train(data, tmp_path / "ae2-flow4", **budget_options(2, 4)))


def test_a_raised_budget_with_val_nll_selection_keeps_what_a_longer_run_keeps(monkeypatch: pytest.MonkeyPatch,
                                                                             tmp_path: Path) -> None:
    """The check the end of the 3-epoch stage called for (epoch 3 is off the every-2 schedule) must not decide
    what the 5-epoch continuation keeps: a fresh 5-epoch run never made it."""
    install_fake_data(monkeypatch, 80, 24)

    def options(flow: int) -> dict[str, object]:
        return dict(model="trajflow-no-ae", quiet=True, overrides=[
            *FAST, *TINY_MODEL, f"train.flow_max_epochs={flow}", "train.flow_batch_size=32",
            "train.flow_select=val_nll", "train.flow_select_every=2", "train.flow_select_problems=10",
            "train.flow_select_samples=20"])

    # Scripted checks: the unscheduled one at epoch 3 would win if the continuation remembered it.
    scripted = {2: -1.0, 3: -5.0, 4: -2.0, 5: -3.0}
    monkeypatch.setattr(train_loop.Session, "_sample_nll",
                        lambda self, batch, subset, label: scripted[int(label.removeprefix("epoch "))])
    run = train(tmp_path / "data", tmp_path / "run", **options(3))
    assert log_of(run).filter(pl.col("val_nll").is_not_null()).get_column("epoch").to_list() == [2, 3]
    assert json.loads((run / "run.json").read_text())["best"]["flow"]["epoch"] == 3
    train(tmp_path / "data", run, resume=True, **options(5))
    whole = train(tmp_path / "data", tmp_path / "whole", **options(5))
    a, b = final_weights(whole), final_weights(run)
    assert all(torch.equal(a[k], b[k]) for k in a)
    best = [json.loads((r / "run.json").read_text())["best"]["flow"] for r in (whole, run)]
    assert best[0] == best[1] and best[0]["epoch"] == 5


def test_a_flow_only_run_from_another_runs_autoencoder_equals_training_from_scratch(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """--autoencoder-from: a run that takes a finished run's autoencoder and other flow settings trains only the
    flow, and ends exactly as the same config trained from scratch; interrupted, it resumes to the same."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    source = train(data, tmp_path / "source", **budget_options(3, 2, "train.flow_lr=0.002"))
    other_flow = budget_options(3, 3, "train.flow_lr=0.0005", "train.flow_lr_decay=0.9")
    scratch = train(data, tmp_path / "scratch", **other_flow)

    def hook(stage: str, epoch: int) -> None:
        assert stage == "flow", "the autoencoder must not be trained again"
        if epoch == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(KeyboardInterrupt):
        train(data, tmp_path / "reused", autoencoder_from=source, **other_flow)
    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    reused = train(data, tmp_path / "reused", autoencoder_from=source, resume=True, **other_flow)
    same_run(reused, scratch)
    info = json.loads((reused / "run.json").read_text())
    assert info["status"] == "finished"
    assert info["autoencoder_from"] == {"run": str(source.resolve()), "autoencoder_epochs": 3,
                                        "autoencoder_best_epoch": info["best"]["autoencoder"]["epoch"]}
    assert load_config(reused / "config.toml").train.flow_lr == 0.0005
    # a budget raise keeps the record
    train(data, reused, resume=True, **budget_options(3, 4, "train.flow_lr=0.0005", "train.flow_lr_decay=0.9"))
    assert json.loads((reused / "run.json").read_text())["autoencoder_from"] == info["autoencoder_from"]


@pytest.mark.parametrize("kept", ["checkpoints", "published"])
def test_a_run_with_other_flow_model_settings_takes_the_autoencoder_and_equals_training_from_scratch(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, kept: str) -> None:
    """The flow's and the context encoders' model settings may differ from the source's (paired ablations): the run
    trains only its own flow, initialised as its config would, and ends exactly as that config from scratch; the
    source may be a run kept without checkpoints (a published model: final/, log, run.json, config.toml)."""
    install_fake_data(monkeypatch, 80, 24)
    data = tmp_path / "data"
    ours = ("model.speed_normalize=true", "model.use_map=false")  # a data constant fitted before the autoencoder
    source = train(data, tmp_path / "source", **budget_options(3, 2, *ours, "train.flow_lr=0.002"))
    if kept == "published":
        shutil.rmtree(source / "checkpoints")
    other_model = budget_options(3, 2, *ours, "model.flow_standardize=true", "model.flow_tail_bound=5",
                                 "model.flow_bins=4", 'model.gnn_aggregate="mean"', "model.past_out=32")
    scratch = train(data, tmp_path / "scratch", **other_model)

    def hook(stage: str, epoch: int) -> None:
        assert stage == "flow", "the autoencoder must not be trained again"

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    reused = train(data, tmp_path / "reused", autoencoder_from=source, **other_model)
    same_run(reused, scratch)
    info = json.loads((reused / "run.json").read_text())
    assert info["best"] == json.loads((scratch / "run.json").read_text())["best"]
    assert info["autoencoder_from"]["autoencoder_epochs"] == 3


def test_a_published_source_needs_its_training_log(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install_fake_data(monkeypatch, 48, 16)
    data = tmp_path / "data"
    source = train(data, tmp_path / "source", **budget_options(1, 1))
    shutil.rmtree(source / "checkpoints")
    log = pl.read_parquet(source / "train_log.parquet")
    log.drop("stage").write_parquet(source / "train_log.parquet")
    with pytest.raises(DataError, match="train_log.parquet.*no column 'stage'"):
        train(data, tmp_path / "new", autoencoder_from=source, **budget_options(1, 1))
    (source / "train_log.parquet").unlink()
    with pytest.raises(UsageError, match="without its training log"):
        train(data, tmp_path / "new", autoencoder_from=source, **budget_options(1, 1))
    assert not (tmp_path / "new").exists()
    log.drop("val_nll").write_parquet(source / "train_log.parquet")  # an older log: taken
    train(data, tmp_path / "new", autoencoder_from=source, **budget_options(1, 1))


@pytest.mark.parametrize("change, message", [
    (["train.ae_lr=0.01"], "train.ae_lr"),
    (["model.alpha=5"], "model.alpha"),
    (["--seed"], "train.seed"),
    (["--model"], "'trajflow' run; this run trains 'trajflow-no-ae'"),
    (["--fold"], "fold"),
    (["--no-autoencoder"], "end-autoencoder.pt is missing"),
])
def test_an_autoencoder_other_settings_would_not_train_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                                   change: list[str], message: str) -> None:
    install_fake_data(monkeypatch, 48, 16, folds=("a", "b"))
    data = tmp_path / "data"
    source = train(data, tmp_path / "source", fold="a", **budget_options(1, 1))
    options = budget_options(1, 1, *[c for c in change if "=" in c])
    options["fold"] = "b" if change == ["--fold"] else "a"
    if change == ["--seed"]:
        options["seed"] = 5
    if change == ["--model"]:
        options["model"] = "trajflow-no-ae"
    if change == ["--no-autoencoder"]:
        (source / "checkpoints" / "end-autoencoder.pt").unlink()
        shutil.rmtree(source / "final")
    with pytest.raises(UsageError, match=message.replace("(", r"\(")):
        train(data, tmp_path / "new", autoencoder_from=source, **options)
    assert not (tmp_path / "new").exists()
    # a run that did not start from this autoencoder is not resumed as if it had
    with pytest.raises(UsageError, match="did not start from"):
        train(data, source, resume=True, autoencoder_from=tmp_path / "elsewhere", fold="a", **budget_options(1, 1))
