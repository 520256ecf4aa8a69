"""`trajflow status EXP` on experiment directories laid out as `trajflow experiment` leaves them."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import polars as pl
import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.model.config import load_config
from trajflow_pipeline.stages.status import (ExperimentStatus, RunStatus, StageProgress, experiment_status,
                                             parse_lock_table)
from trajflow_pipeline.util.claim import claim

BUDGET = ["train.ae_max_epochs=30", "train.ae_min_epochs=5", "train.ae_patience=4", "train.flow_max_epochs=8",
          "train.flow_min_epochs=2", "train.flow_patience=3"]


def write_experiment(out: Path, budget: list[str] = BUDGET) -> Path:
    """An experiment directory's config: TrajFlow and cv on folds eth and hotel, one seed (no dataset needed)."""
    out.mkdir(parents=True)
    (out / "config.toml").write_text(f'''name = "status_test"
[data]
path = "{(out / 'no-data').as_posix()}"
[protocol]
models = ["trajflow", "cv"]
folds = ["eth", "hotel"]
seeds = [0]
[train]
set = {json.dumps(budget)}
''')
    return out


def named(status: ExperimentStatus, *names: str) -> list[RunStatus]:
    """The experiment's runs called `names`, in that order (KeyError for a run it does not plan)."""
    runs = {run.name: run for run in status.runs}
    return [runs[name] for name in names]


def write_run(out: Path, name: str, *, status: str, log: list[tuple[str, int, float | None]],
              model: str = "trajflow", budget: list[str] = BUDGET, evaluated: bool = False) -> Path:
    """A run directory: run.json, its config, a training log of (stage, epoch, val_loss) and, when `evaluated`, an
    evaluation of its final weights."""
    run = out / "runs" / name
    run.mkdir(parents=True)
    (run / "config.toml").write_text(load_config(overrides=[*budget, f"model.name={model}"]).to_toml())
    info = {"model": model, "status": status, "rank_weight_digests": ["w1"] if status == "finished" else None,
            "finished": "2026-11-30T10:00:00+00:00" if status == "finished" else None}
    (run / "run.json").write_text(json.dumps(info))
    pl.DataFrame({"stage": [s for s, _, _ in log], "epoch": [e for _, e, _ in log],
                  "val_loss": [v for _, _, v in log], "seconds": [2.0] * len(log)},
                 schema={"stage": pl.String, "epoch": pl.Int64, "val_loss": pl.Float64, "seconds": pl.Float64},
                 ).write_parquet(run / "train_log.parquet")
    if evaluated:
        (run / "eval").mkdir()
        pl.DataFrame({"metric": ["min_ade", "min_fde", "min_ade"], "value": [0.25, 0.5, 9.0],
                      "aggregate": [True, True, False]}).write_parquet(run / "eval" / "metrics.parquet")
        (run / "eval" / "eval.json").write_text(json.dumps({"model_digest": "w1", "seconds": 30.0,
                                                            "date": "2026-11-30T10:01:00+00:00"}))
    return run


def autoencoder_then_flow(flow_losses: list[float]) -> list[tuple[str, int, float | None]]:
    """Ten autoencoder epochs (best at 7), then flow epochs with the given validation losses."""
    ae = [("autoencoder", e, 1.0 / e if e <= 7 else 0.5) for e in range(1, 11)]
    return ae + [("flow", e, v) for e, v in enumerate(flow_losses, start=1)]


def test_each_state_with_its_progress_and_the_time_its_stage_may_take(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1, -2, -3, -2, -2, -2]),
              evaluated=True)
    write_run(out, "trajflow-hotel-s0", status="training", log=autoencoder_then_flow([-1.0, -3.0, -2.0]))
    write_run(out, "cv-eth-s0", status="finished", model="cv", log=[("fit", 1, None)])
    status = experiment_status(out)
    # the closed-form baseline first (minutes, not hours), as the experiment works on them
    assert [r.name for r in status.runs] == ["cv-eth-s0", "cv-hotel-s0", "trajflow-eth-s0", "trajflow-hotel-s0"]
    trained, planned, done, interrupted = status.runs
    assert (done.state, done.metrics, done.eval_seconds, done.train_seconds) == (
        "done", {"min_ade": 0.25, "min_fde": 0.5}, 30.0, 32.0)
    assert done.progress == StageProgress(stage="flow", epoch=6, min_epochs=2, max_epochs=8, best_epoch=3,
                                          patience=3, seconds_per_epoch=2.0)
    if sys.platform == "linux":
        assert interrupted.state == "interrupted" and interrupted.busy is False
    # flow epoch 3 of at most 8; best at 2 with patience 3: early stopping can end it after epoch 5
    assert interrupted.progress is not None and interrupted.progress.epochs_left == (2, 5)
    assert (trained.state, planned.state, planned.progress, planned.train_seconds) == ("trained", "planned", None, 0)
    assert status.to_dict()["runs"][3]["progress"]["epochs_left"] == (2, 5)


def test_a_closed_form_last_stage_shows_no_time_per_epoch(tmp_path: Path) -> None:
    """A baseline's fit and TrajFlow's temperature stage have no epochs: their seconds are not an epoch's time."""
    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="finished",
              log=[*autoencoder_then_flow([-1, -2, -3, -2, -2, -2]), ("temperature", 1, None)], evaluated=True)
    write_run(out, "cv-eth-s0", status="finished", model="cv", log=[("fit", 1, None)])
    flow, cv = named(experiment_status(out), "trajflow-eth-s0", "cv-eth-s0")
    assert flow.progress is not None and flow.progress.stage == "temperature"
    assert cv.progress is not None and cv.progress.stage == "fit"
    assert flow.progress.seconds_per_epoch is None and cv.progress.seconds_per_epoch is None


def test_the_epoch_range_follows_train_early_stopping() -> None:
    """train.py: a stage ends at its maximum, or once it is past its minimum and `patience` epochs have brought no
    lower validation loss than the best (counted from epoch 0 while no loss was finite)."""
    early = StageProgress(stage="autoencoder", epoch=3, min_epochs=100, max_epochs=5000, best_epoch=1, patience=10)
    assert (early.epochs_left, early.patience_left, early.stopped) == ((97, 4997), 8, False)
    stopped = StageProgress(stage="flow", epoch=20, min_epochs=10, max_epochs=500, best_epoch=10, patience=10)
    assert (stopped.stopped, stopped.epochs_left, stopped.patience_left) == (True, (0, 0), 0)
    at_max = StageProgress(stage="flow", epoch=25, min_epochs=10, max_epochs=25, best_epoch=25, patience=10)
    assert at_max.stopped and at_max.epochs_left == (0, 0)
    no_patience = StageProgress(stage="flow", epoch=20, min_epochs=10, max_epochs=25, best_epoch=10, patience=0)
    assert no_patience.epochs_left == (5, 5) and no_patience.patience_left is None
    never_finite = StageProgress(stage="flow", epoch=2, min_epochs=2, max_epochs=8, best_epoch=None, patience=3)
    assert never_finite.epochs_left == (1, 6)
    assert StageProgress(stage="flow", epoch=3, min_epochs=2, max_epochs=8, patience=3).stopped
    closed_form = StageProgress(stage="fit", epoch=1)
    assert closed_form.epochs_left is None and closed_form.stopped


def test_an_unfinished_run_whose_stage_ended_shows_the_next_stage(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    # autoencoder best at 7, patience 4, min 5: it stopped after epoch 11; the flow had not logged an epoch
    write_run(out, "trajflow-eth-s0", status="training",
              log=[("autoencoder", e, 1.0 / e if e <= 7 else 0.5) for e in range(1, 12)])
    progress = named(experiment_status(out), "trajflow-eth-s0")[0].progress
    assert progress == StageProgress(stage="flow", epoch=0, min_epochs=2, max_epochs=8, patience=3)
    assert progress.epochs_left == (3, 8)  # patience 3 counted from epoch 0


def test_the_budget_is_the_one_the_experiment_now_sets(tmp_path: Path) -> None:
    """Per-model overrides and raised budgets count for runs that will train again; a live run keeps its own."""
    out = write_experiment(tmp_path / "exp")
    (out / "config.toml").write_text((out / "config.toml").read_text()
                                     + '[models.trajflow]\nset = ["train.flow_max_epochs=40"]\n')
    write_run(out, "trajflow-eth-s0", status="training", log=autoencoder_then_flow([-1.0, -2.0, -3.0]))
    write_run(out, "trajflow-hotel-s0", status="training", log=autoencoder_then_flow([-1.0, -2.0, -3.0]))
    with claim(out / "runs" / ".trajflow-hotel-s0.lock"):
        interrupted, live = named(experiment_status(out), "trajflow-eth-s0", "trajflow-hotel-s0")
    assert interrupted.progress is not None and interrupted.progress.max_epochs == 40
    if sys.platform == "linux":
        assert live.state == "training" and live.progress is not None and live.progress.max_epochs == 8


def test_lock_table_lines_held_and_waiting() -> None:
    table = ("1: FLOCK  ADVISORY  WRITE 28836 fe:00:5309521 0 EOF\n"
             "1: -> FLOCK  ADVISORY  WRITE 28900 fe:00:5309521 0 EOF\n"
             "2: POSIX  ADVISORY  READ 1234 00:2f:77 0 EOF\n"
             "3: OFDLCK ADVISORY  WRITE -1 08:01:4242 0 EOF\n"
             "4: FLOCK  ADVISORY  WRITE 99 <none>:0 0 EOF\n"
             "5: -> POSIX ADVISORY WRITE 5 08:01:99 0 EOF\n")
    assert parse_lock_table(table) == {5309521, 77, 4242}


def test_on_a_network_file_system_an_unclaimed_run_may_be_another_machines(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import trajflow_pipeline.stages.status as status_module

    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="training", log=autoencoder_then_flow([-1.0]))
    monkeypatch.setattr(status_module, "_file_system_type", lambda path: "nfs4")
    monkeypatch.setattr(status_module, "_locked_inodes", lambda: set())
    started, planned = named(experiment_status(out), "trajflow-eth-s0", "trajflow-hotel-s0")
    assert (started.state, started.busy) == ("training or interrupted", None)
    assert (planned.state, planned.busy) == ("planned", None)


def test_evaluating_runs_show_no_patience_and_unreadable_runs_do_not_hide_the_others(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1.0, -2.0, -2.0, -2.0, -2.0]))
    write_run(out, "trajflow-hotel-s0", status="training", log=autoencoder_then_flow([-1.0]))
    (out / "runs" / "trajflow-hotel-s0" / "run.json").write_text("[1, 2]")
    with claim(out / "runs" / ".trajflow-eth-s0.lock"):
        status = experiment_status(out)
        output = _cli_output(out)
    evaluating, unreadable = named(status, "trajflow-eth-s0", "trajflow-hotel-s0")
    assert evaluating.fits_saved is None                                        # no evaluation cache yet
    if sys.platform == "linux":
        assert evaluating.state == "evaluating"
        row = next(line for line in output.splitlines() if "trajflow-eth-s0" in line)
        assert "flow: 5/8" in row and "(0/3)" not in row and " s-" not in row
    assert unreadable.state == "unreadable" and "expected a JSON object" in (unreadable.problem or "")
    assert "trajflow-hotel-s0:" in output and "run.json" in output


def _cli_output(out: Path) -> str:
    result = CliRunner().invoke(app, ["status", str(out)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.skipif(sys.platform != "linux", reason="claims are read from /proc/locks, which only Linux has")
def test_a_claimed_run_is_training_and_asking_never_takes_its_claim(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="training", log=autoencoder_then_flow([]))
    with claim(out / "runs" / ".trajflow-eth-s0.lock") as mine, claim(out / "runs" / ".cv-hotel-s0.lock"):
        assert mine
        training, claimed, unclaimed = named(experiment_status(out), "trajflow-eth-s0", "cv-hotel-s0",
                                             "trajflow-hotel-s0")
        assert (training.state, training.busy) == ("training", True)
        assert (claimed.state, claimed.busy) == ("training", True)   # claimed, before its run.json exists
        assert unclaimed.busy is False
        with claim(out / "runs" / ".trajflow-eth-s0.lock") as again:  # held by us still: status did not touch it
            assert not again


def test_a_raised_budget_shows_until_the_run_follows_it(tmp_path: Path) -> None:
    raised = [b.replace("flow_max_epochs=8", "flow_max_epochs=12") for b in BUDGET]
    out = write_experiment(tmp_path / "exp", budget=raised)
    write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1.0] * 8), evaluated=True)
    assert named(experiment_status(out), "trajflow-eth-s0")[0].state == "budget raised"


def test_a_new_temperature_grid_shows_on_the_flow_runs_it_changes(tmp_path: Path) -> None:
    """The experiment's config adds model.flow_temperature_grid: the finished TrajFlow run shows it until it fits
    the stage; the constant-velocity run, which has no such stage, stays done."""
    grid = [*BUDGET, "model.flow_temperature_grid=[1.0, 1.2]"]
    out = write_experiment(tmp_path / "exp", budget=grid)
    write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1.0] * 8), evaluated=True)
    write_run(out, "cv-eth-s0", status="finished", log=[("fit", 1, 0.5)], model="cv", evaluated=True)
    flow, cv = named(experiment_status(out), "trajflow-eth-s0", "cv-eth-s0")
    assert (flow.state, cv.state) == ("temperature changed", "done")
    assert "temperature changed" in _cli_output(out)


def test_cli_table_json_and_errors(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1, -2]), evaluated=True)
    runner = CliRunner()
    result = runner.invoke(app, ["status", str(out)])  # not a terminal: the table keeps its width, whatever COLUMNS
    assert result.exit_code == 0, result.output
    assert "trajflow-eth-s0" in result.output and "0.250/0.500" in result.output and "flow: 2/8" in result.output
    assert "s/epoch" in result.output and "…" not in result.output
    assert "4 runs: 3 planned, 1 done" in result.output
    as_json = json.loads(runner.invoke(app, ["status", str(out), "--json"]).stdout)
    assert [r["state"] for r in as_json["runs"]] == ["planned", "planned", "done", "planned"]
    missing = runner.invoke(app, ["status", str(tmp_path / "nothing")])
    assert missing.exit_code != 0 and "not an experiment directory" in missing.output
    with pytest.raises(UsageError, match="not an experiment directory"):
        experiment_status(tmp_path)
    (out / "runs" / "trajflow-eth-s0" / "run.json").write_text("{broken")
    broken, = named(experiment_status(out), "trajflow-eth-s0")
    assert broken.state == "unreadable" and re.search(r"run\.json.*unreadable", broken.problem or "")


def test_folds_come_from_the_run_directories_when_the_dataset_is_not_here(tmp_path: Path) -> None:
    out = write_experiment(tmp_path / "exp")
    text = (out / "config.toml").read_text().replace('folds = ["eth", "hotel"]\n', 'folds = "all"\n')
    (out / "config.toml").write_text(text)
    write_run(out, "trajflow-zara1-s0", status="training", log=autoencoder_then_flow([]))
    status = experiment_status(out)
    assert [r.name for r in status.runs] == ["cv-zara1-s0", "trajflow-zara1-s0"]
    assert status.note is not None and "was not found from here" in status.note


def test_an_evaluation_in_progress_shows_its_saved_fits(tmp_path: Path) -> None:
    import numpy as np

    from trajflow_pipeline.metrics.parallel import RomeTask
    from trajflow_pipeline.metrics.rome_cache import RomeCache

    out = write_experiment(tmp_path / "exp")
    run = write_run(out, "trajflow-eth-s0", status="finished", log=autoencoder_then_flow([-1.0, -2.0]))
    tasks = [RomeTask(fit=np.zeros((3, 2)), queries=(np.zeros((1, 2)),)) for _ in range(5)]
    cache = RomeCache(run / "eval-cache", tasks, base_seed=0)
    cache.save([(i, ((np.full(1, -1.0),), 0)) for i in range(3)])
    cache.save([(1, ((np.full(1, -1.0),), 0))])                                # saved twice counts once
    evaluating, = named(experiment_status(out), "trajflow-eth-s0")
    assert (evaluating.state, evaluating.fits_saved) == ("trained", (3, 5))
    assert "eval: 3/5 fits saved" in _cli_output(out)


def test_one_run_of_trajflow_train(tmp_path: Path) -> None:
    """`trajflow status RUN` on a run directory of its own: its state and progress under its saved config."""
    out = tmp_path / "alone"
    run = write_run(out, "r", status="training", log=autoencoder_then_flow([-1.0, -3.0, -2.0]))
    status = experiment_status(run)
    assert (status.kind, status.name, len(status.runs)) == ("run", "r", 1)
    only = status.runs[0]
    assert (only.state, only.busy, only.model) == ("training or interrupted", None, "trajflow")
    assert only.progress is not None and only.progress.epochs_left == (2, 5)
    output = _cli_output(run)
    assert "run r" in output and "flow: 3/8" in output and "1 run: 1 training or interrupted" in output
    done = write_run(out, "done", status="finished", log=autoencoder_then_flow([-1, -2]), evaluated=True)
    assert experiment_status(done).runs[0].state == "done" and "0.250/0.500" in _cli_output(done)
    (done / "run.json").write_text("{broken")
    broken, = experiment_status(done).runs
    assert broken.state == "unreadable" and "run.json" in (broken.problem or "")
