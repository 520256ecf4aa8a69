"""An experiment survives a change of machine: docs/results/publish.py publishes what continues it (finished runs'
evaluation records without draws, unfinished runs' last training state) and restores an experiment directory from
that, which `trajflow experiment` then continues without training or evaluating anything twice."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import polars as pl
import pytest
import torch

from results_scripts import load_results_script
from test_eval_stage import write_tiny_experiment

from trajflow_pipeline.errors import TrajflowError, UsageError
from trajflow_pipeline.model import load_training_state
from trajflow_pipeline.model.config import DataSpec, load_config
from trajflow_pipeline.model.models import build_model
from trajflow_pipeline.rundir import continuation_files, is_evaluated
from trajflow_pipeline.stages.experiment import run_experiment
from trajflow_pipeline.stages.report import report
from trajflow_pipeline.training import check_state
from trajflow_pipeline.training import loop as train_loop

def load_publish():
    """docs/results/publish.py as a module (it is a script, not part of the package)."""
    return load_results_script("publish.py")


class Killed(Exception):
    """The machine went away."""


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """An experiment (its config, its directory; the tests leave both as they are) whose cv run is finished and
    whose trajflow-no-ae run was killed after its first flow epoch (of two)."""
    tmp_path = tmp_path_factory.mktemp("machine")
    config = write_tiny_experiment(tmp_path, ["cv", "trajflow-no-ae"], [0])

    def hook(stage: str, epoch: int) -> None:
        if (stage, epoch) == ("flow", 1):
            raise Killed()

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(train_loop, "_epoch_hook", hook)
        with pytest.raises(Killed):
            run_experiment(config, tmp_path / "exp", quiet=True)
    return config, tmp_path / "exp"


def test_a_published_experiment_restored_elsewhere_goes_on_without_repeating_work(
        interrupted: tuple[Path, Path], tmp_path: Path) -> None:
    config, exp = interrupted
    publish = load_publish()
    results = tmp_path / "docs" / "results" / "tiny"
    publish.publish(exp, results)
    done, cut = results / "models" / "cv-all-s0", results / "unfinished" / "trajflow-no-ae-all-s0"
    assert sorted(p.relative_to(done).as_posix() for p in done.rglob("*") if p.is_file()) == [
        "config.toml", "eval/eval.json", "eval/metrics.parquet", "final/model.json", "final/model.safetensors",
        "run.json", "train_log.parquet"]
    assert sorted(p.relative_to(cut).as_posix() for p in cut.rglob("*") if p.is_file()) == [
        "checkpoints/state.pt", "config.toml", "run.json", "train_log.parquet"]
    rows = pl.read_parquet(done / "eval" / "metrics.parquet")
    full = pl.read_parquet(exp / "runs" / "cv-all-s0" / "eval" / "metrics.parquet")
    assert rows.height < full.height and rows.filter(pl.col("aggregate")).equals(full.filter(pl.col("aggregate")))
    assert set(rows.filter(~pl.col("aggregate")).get_column("metric")) == {"nll", "nll_joint"}

    fresh = tmp_path / "elsewhere" / "exp"  # another machine: nothing but the published folder
    publish.restore(results, fresh)
    assert is_evaluated(fresh / "runs" / "cv-all-s0")
    before = {name: (fresh / "runs" / "cv-all-s0" / name).read_bytes()
              for name in ("run.json", "eval/eval.json", "train_log.parquet")}
    report([fresh], tmp_path / "report-restored", quiet=True, figures=False)  # the index is there at once
    run_experiment(fresh / "config.toml", fresh, quiet=True)

    after = {name: (fresh / "runs" / "cv-all-s0" / name).read_bytes() for name in before}
    assert after == before, "the finished run was trained or evaluated again"
    resumed = fresh / "runs" / "trajflow-no-ae-all-s0"
    log = pl.read_parquet(resumed / "train_log.parquet")
    assert log.get_column("epoch").to_list() == [1, 2]
    assert log.row(0) == pl.read_parquet(cut / "train_log.parquet").row(0), "epoch 1 was trained again"
    info = json.loads((resumed / "run.json").read_text())
    assert info["status"] == "finished" and is_evaluated(resumed)
    index = json.loads((fresh / "experiment.json").read_text())
    assert index["runs"] == index["planned"] == ["runs/cv-all-s0", "runs/trajflow-no-ae-all-s0"]

    out = report([fresh], tmp_path / "report", quiet=True)
    text = (out / "report.md").read_text()
    assert "No draws (eval/predictions.parquet" in text and "1 run (cv-all-s0)" in text
    assert (out / "figures").is_dir() and any((out / "figures").glob("*min-ade-vs-k.png"))


def test_publishing_every_few_minutes_follows_the_experiment_to_its_end(
        interrupted: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """--every: a round that fails says why and the next tries again; the round after the last run finished
    publishes it and ends the loop."""
    _, exp = interrupted
    copy = tmp_path / "exp"
    shutil.copytree(exp, copy)
    publish = load_publish()
    real, rounds, sleeps = publish.publish, [], []

    def flaky(experiment: Path, out: Path, limit: int) -> str:
        rounds.append(out)
        if len(rounds) == 1:
            raise OSError(f"{experiment}: disk full")
        return real(experiment, out, limit)

    def sleep(seconds: float) -> None:      # the experiment goes on meanwhile, and finishes
        sleeps.append(seconds)
        run_experiment(copy / "config.toml", copy, quiet=True)

    monkeypatch.setattr(publish, "publish", flaky)
    results = tmp_path / "results"
    publish.publish_every(copy, results, 15, sleep=sleep)
    assert sleeps == [900] and len(rounds) == 2
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and "not published this round" in lines[0] and "disk full" in lines[0]
    assert "2 finished runs" in lines[1] and "0 unfinished runs" in lines[1]
    assert not (results / "unfinished").exists() and is_evaluated(results / "models" / "trajflow-no-ae-all-s0")


def test_restore_refuses_a_target_that_holds_anything(interrupted: tuple[Path, Path], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    config, exp = interrupted
    publish = load_publish()
    monkeypatch.setattr(publish, "report", lambda *args, **kwargs: None)  # the report is not what is tested here
    results = tmp_path / "results"
    publish.publish(exp, results)
    with pytest.raises(ValueError, match="exists and is not empty"):
        publish.restore(results, exp)
    with pytest.raises(ValueError, match="no config.toml"):
        publish.restore(tmp_path / "nothing", tmp_path / "new")
    assert not (tmp_path / "new").exists()
    # a restored finished run keeps no training state: a larger budget is refused before anything changes
    publish.restore(results, tmp_path / "restored")
    raised = tmp_path / "raised.toml"
    raised.write_text(config.read_text().replace("train.flow_max_epochs=2", "train.flow_max_epochs=3"))
    with pytest.raises(UsageError, match=r"cv-all-s0: its training state \(checkpoints/state.pt\) is not kept"):
        run_experiment(raised, tmp_path / "restored", quiet=True)
    assert (tmp_path / "restored" / "config.toml").read_text() == config.read_text()


def test_an_experiment_with_no_finished_run_is_published_and_later_reported_over(
        interrupted: tuple[Path, Path], tmp_path: Path) -> None:
    _, exp = interrupted
    publish = load_publish()
    early = tmp_path / "early"
    shutil.copytree(exp, early)
    index = json.loads((early / "experiment.json").read_text())
    (early / "experiment.json").write_text(json.dumps({**index, "runs": []}))  # as before cv finished
    results = tmp_path / "results"
    publish.publish(early, results)
    assert "No run of this experiment is finished yet" in (results / "report.md").read_text()
    assert sorted(p.name for p in (results / "unfinished").iterdir()) == ["cv-all-s0", "trajflow-no-ae-all-s0"]
    assert not any(p.is_dir() for p in (results / "models").iterdir())
    publish.publish(exp, results)  # the same folder, once a run is finished
    assert "cv-all-s0" in (results / "report.md").read_text()
    assert sorted(p.name for p in (results / "unfinished").iterdir()) == ["trajflow-no-ae-all-s0"]
    assert (results / "models" / "cv-all-s0" / "eval" / "eval.json").is_file()


def test_a_run_without_a_checkpoint_has_nothing_to_continue(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.toml").write_text("")
    assert continuation_files(run) == ()


def test_a_twin_experiment_takes_the_published_autoencoders_and_trains_only_its_flows(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--autoencoder-from a published folder: the twin's TrajFlow run trains its flow alone (other flow settings)
    and ends where training that config from scratch ends; the runs without an autoencoder train as always."""
    from safetensors.torch import load_file

    base = write_tiny_experiment(tmp_path, ["cv", "trajflow"], [0])
    text = base.read_text()
    run_experiment(base, tmp_path / "base", quiet=True)
    results = tmp_path / "docs" / "results" / "base"
    load_publish().publish(tmp_path / "base", results)
    twin = tmp_path / "twin.toml"
    twin.write_text(text.replace('name = "tiny"', 'name = "twin"')
                    .replace("set = [", 'set = ["model.flow_standardize=true", "model.flow_tail_bound=5", ', 1))
    stages: list[str] = []
    monkeypatch.setattr(train_loop, "_epoch_hook", lambda stage, epoch: stages.append(stage))
    run_experiment(twin, tmp_path / "twin", quiet=True, autoencoder_from=results)
    assert stages == ["flow", "flow"]
    run = tmp_path / "twin" / "runs" / "trajflow-all-s0"
    info = json.loads((run / "run.json").read_text())
    assert info["autoencoder_from"]["run"] == str((results / "models" / "trajflow-all-s0").resolve())
    assert (tmp_path / "twin" / "runs" / "cv-all-s0" / "eval").is_dir()
    run_experiment(twin, tmp_path / "twin", quiet=True, autoencoder_from=results)  # finished: nothing again
    assert stages == ["flow", "flow"]

    monkeypatch.setattr(train_loop, "_epoch_hook", None)
    run_experiment(twin, tmp_path / "scratch", quiet=True)
    scratch = load_file(tmp_path / "scratch" / "runs" / "trajflow-all-s0" / "final" / "model.safetensors")
    reused = load_file(run / "final" / "model.safetensors")
    assert scratch.keys() == reused.keys() and all(torch.equal(scratch[k], reused[k]) for k in scratch)
    with pytest.raises(UsageError, match="no such directory"):
        run_experiment(twin, tmp_path / "other", quiet=True, autoencoder_from=tmp_path / "nowhere")


def test_an_experiment_killed_in_its_first_run_can_be_published(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The index is written before any work: a kill before the first run finishes leaves what publish.py reads,
    and the run's resume state is published."""
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])

    def hook(stage: str, epoch: int) -> None:
        if (stage, epoch) == ("flow", 1):
            raise Killed()

    monkeypatch.setattr(train_loop, "_epoch_hook", hook)
    with pytest.raises(Killed):
        run_experiment(config, tmp_path / "exp", quiet=True)
    assert json.loads((tmp_path / "exp" / "experiment.json").read_text())["runs"] == []
    results = tmp_path / "results"
    load_publish().publish(tmp_path / "exp", results)
    assert sorted(p.name for p in (results / "unfinished").iterdir()) == ["trajflow-no-ae-all-s0"]


def test_a_resume_state_over_the_file_limit_is_published_in_two_files_or_as_its_last_stage_end_state(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run killed in its flow stage whose state is over the limit: published in two files (the state without the
    optimizer's, and that) where both fit, which the restore joins and the copy resumes after its last epoch;
    else with its end-of-autoencoder state and the log of those epochs, from which the copy trains its flow again
    as the run did (the same losses); a limit that no state fits publishes the last state and says so."""
    config = write_tiny_experiment(tmp_path, ["trajflow"], [0])

    def hook(stage: str, epoch: int) -> None:
        if (stage, epoch) == ("flow", 1):
            raise Killed()

    with monkeypatch.context() as patch:
        patch.setattr(train_loop, "_epoch_hook", hook)
        with pytest.raises(Killed):
            run_experiment(config, tmp_path / "exp", quiet=True)
    run = tmp_path / "exp" / "runs" / "trajflow-all-s0"
    state, end = run / "checkpoints" / "state.pt", run / "checkpoints" / "end-autoencoder.pt"
    original = pl.read_parquet(run / "train_log.parquet")
    assert original.get_column("stage").to_list()[-1] == "flow"
    publish = load_publish()
    assert publish.write_state_apart(state, tmp_path / "parts", 10**9)
    parts = [tmp_path / "parts" / "checkpoints" / name for name in ("state.pt", "state-optimizer.pt")]
    apart = max(path.stat().st_size for path in parts)
    assert apart < state.stat().st_size and end.stat().st_size < state.stat().st_size, "the premise of this test"
    losses = ["epoch", "stage", "train_loss", "val_loss", "lr"]

    results = tmp_path / "results-apart"
    line = publish.publish(tmp_path / "exp", results, limit=apart)
    assert "trajflow-all-s0" in line and "its state in two files" in line and "left out" not in line
    copy = results / "unfinished" / "trajflow-all-s0"
    assert sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*") if p.is_file()) == [
        "checkpoints/state-optimizer.pt", "checkpoints/state.pt", "config.toml", "run.json", "train_log.parquet"]
    with pytest.raises(TrajflowError, match="optimizer state is damaged"):  # the first part alone resumes nothing
        check_state(parts[0], load_training_state(parts[0]), build_model(
            load_config(run / "config.toml").model, DataSpec(n_past=8, n_future=12)))
    fresh = tmp_path / "elsewhere-apart"
    publish.restore(results, fresh)
    assert not (fresh / "runs" / "trajflow-all-s0" / "checkpoints" / "state-optimizer.pt").exists()
    run_experiment(fresh / "config.toml", fresh, quiet=True)
    resumed = pl.read_parquet(fresh / "runs" / "trajflow-all-s0" / "train_log.parquet")
    assert resumed.head(original.height).equals(original), "an epoch before the kill was trained again"

    results = tmp_path / "results"  # (here the autoencoder outweighs the flow: parts that do not fit are feigned)
    monkeypatch.setattr(publish, "write_state_apart", lambda *args: False)
    line = publish.publish(tmp_path / "exp", results, limit=end.stat().st_size)
    assert "resumes from end-autoencoder.pt, 1 later epochs left out" in line
    cut = results / "unfinished" / "trajflow-all-s0"
    assert (cut / "checkpoints" / "state.pt").read_bytes() == end.read_bytes()
    published_log = pl.read_parquet(cut / "train_log.parquet")
    assert published_log.equals(original.filter(pl.col("stage") == "autoencoder"))
    fresh = tmp_path / "elsewhere"
    publish.restore(results, fresh)
    run_experiment(fresh / "config.toml", fresh, quiet=True)
    resumed = pl.read_parquet(fresh / "runs" / "trajflow-all-s0" / "train_log.parquet")
    assert resumed.head(original.height).select(losses).equals(original.select(losses)), \
        "the flow epoch trained again differs from the run's own"
    assert is_evaluated(fresh / "runs" / "trajflow-all-s0")

    line = publish.publish(tmp_path / "exp", tmp_path / "tight", limit=1000)
    assert f"its state is {state.stat().st_size:,} bytes, over the 1,000-byte limit" in line
    assert (tmp_path / "tight" / "unfinished" / "trajflow-all-s0" / "checkpoints" / "state.pt").read_bytes() == \
        state.read_bytes()


def test_a_new_temperature_grid_refits_finished_runs_published_or_not_and_evaluates_them_again(
        tmp_path: Path) -> None:
    """An experiment config that adds model.flow_temperature_grid: each finished flow run (here one kept whole and
    one restored from a published folder, without training states) fits the stage after the flow on its final flow
    and is evaluated again, the baseline is left as it was, and the two end with the same model and numbers."""
    config = write_tiny_experiment(tmp_path, ["cv", "trajflow-no-ae"], [0])
    exp = run_experiment(config, tmp_path / "exp", quiet=True)
    publish = load_publish()
    publish.publish(exp, tmp_path / "results")
    restored = tmp_path / "restored"
    publish.restore(tmp_path / "results", restored)
    flow_run, cv_run = "runs/trajflow-no-ae-all-s0", "runs/cv-all-s0"
    cv_before = (exp / cv_run / "eval" / "eval.json").read_bytes()
    text = config.read_text().replace('set = ["', 'set = ["model.flow_temperature_grid=[0.8, 1.0, 1.5]", '
                                      '"model.flow_temperature_problems=10", "')
    assert text != config.read_text()
    grid = tmp_path / "grid.toml"
    grid.write_text(text)
    for target in (exp, restored):
        run_experiment(grid, target, quiet=True)
        info = json.loads((target / flow_run / "run.json").read_text())
        assert set(info["best"]["temperature"]["val_nll_by_temperature"]) == {"0.8", "1", "1.5"}
        assert is_evaluated(target / flow_run)
        assert json.loads((target / "experiment.json").read_text())["runs"] == [cv_run, flow_run]
    assert (exp / cv_run / "eval" / "eval.json").read_bytes() == cv_before, "the baseline was evaluated again"
    ours, theirs = (pl.read_parquet(t / flow_run / "eval" / "metrics.parquet").filter(pl.col("aggregate"))
                    for t in (exp, restored))
    assert ours.equals(theirs)
    assert json.loads((exp / flow_run / "run.json").read_text())["best"] == \
        json.loads((restored / flow_run / "run.json").read_text())["best"]


def test_publishing_again_keeps_the_report_until_the_finished_runs_change(interrupted: tuple[Path, Path],
                                                                          tmp_path: Path) -> None:
    """A restored experiment published back into its folder keeps the report as it was, figures drawn from the
    draws it no longer has included; once another run is finished, the report is made again."""
    _, exp = interrupted
    publish = load_publish()
    results = tmp_path / "results"
    publish.publish(exp, results)
    before = {p.relative_to(results).as_posix(): p.read_bytes()
              for p in [*results.glob("report.*"), *(results / "figures").iterdir()]}
    assert any("min-ade-vs-k" in name for name in before)
    fresh = tmp_path / "fresh"
    publish.restore(results, fresh)
    assert "report (as it was: the same finished runs)" in publish.publish(fresh, results)
    assert {name: (results / name).read_bytes() for name in before} == before
    run_experiment(fresh / "config.toml", fresh, quiet=True)  # the run in training finishes
    line = publish.publish(fresh, results)
    assert "report (as it was" not in line and "trajflow-no-ae-all-s0" in (results / "report.md").read_text()
