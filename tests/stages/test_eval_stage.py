"""`trajflow eval` and `trajflow experiment` end to end on tiny trained runs, plus the report over them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import polars as pl
import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import TrajflowError, UsageError
from trajflow_pipeline.metrics import METRIC_NAMES
from trajflow_pipeline.model.config import load_config
from trajflow_pipeline.stages.evaluate import EvalOptions, aggregate_metrics, evaluate
from trajflow_pipeline.stages.experiment import run_experiment
from trajflow_pipeline.stages.experiment_config import load_experiment
from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal
from trajflow_pipeline.stages.report import report
from trajflow_pipeline.training import train
from trajflow_pipeline.util.claim import claim
from trajflow_pipeline.util.provenance import code_revision

TINY = ["train.ae_max_epochs=2", "train.ae_min_epochs=1", "train.flow_max_epochs=2", "train.flow_min_epochs=1",
        "model.flow_layers=2", "model.flow_hidden=[16, 16]"]
FAST = EvalOptions(samples=12, k=5, workers=1)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return ingest_synthetic_bimodal(tmp_path_factory.mktemp("data") / "bimodal", samples=120, seed=5, quiet=True)


@pytest.fixture(scope="module")
def tiny_run(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("runs") / "trajflow-s0"
    return train(tiny_data, run, model="trajflow", overrides=TINY, seed=0, quiet=True)


def test_eval_writes_predictions_ground_truth_and_every_metric(tiny_run: Path) -> None:
    out = evaluate(tiny_run, options=FAST, quiet=True)
    info = json.loads((out / "eval.json").read_text())
    assert info["model"] == "trajflow" and info["dataset"] == "synthetic_bimodal" and info["problems"] == 120
    assert info["log_lik_label"] == "latent" and info["samples"] == 12 and info["k"] == 5
    assert info["jsd_groups"] == 1 and info["jsd_groups_skipped"] == 0 and info["jsd_groups_identical_futures"] == 0
    assert info["code_revision"] == code_revision()
    assert info["training_code_revisions"] == json.loads((tiny_run / "run.json").read_text())["code_revisions"]
    predictions = pl.read_parquet(out / "predictions.parquet")
    assert predictions.columns == ["sample_id", "draw", "step", "x", "y", "log_lik"]
    assert predictions.height == 120 * 12 * 14
    truth = pl.read_parquet(out / "ground_truth.parquet")
    assert truth.height == 120 * (10 + 14) and truth.get_column("step").min() == -9
    metrics = pl.read_parquet(out / "metrics.parquet")
    aggregates = metrics.filter(pl.col("aggregate"))
    assert sorted(aggregates.get_column("metric")) == sorted(METRIC_NAMES)
    assert set(metrics.get_column("run")) == {"trajflow-s0"} and set(metrics.get_column("seed")) == {0}
    per_agent = metrics.filter((pl.col("metric") == "min_ade") & ~pl.col("aggregate"))
    assert per_agent.height == 120 and per_agent.get_column("sample_id").null_count() == 0
    values = aggregate_metrics(out)
    assert 0 <= values["jsd"] <= 1 and values["min_ade"] > 0


@pytest.mark.usefixtures("rome_pca_fails_twice")
def test_eval_records_rome_fallbacks_even_when_quiet(tiny_run: Path, tmp_path: Path) -> None:
    """Experiment workers evaluate quietly; ROME's PCA fallback must still be on record, in eval.json."""
    run = Path(shutil.copytree(tiny_run, tmp_path / "run"))
    info = json.loads((evaluate(run, options=FAST, quiet=True) / "eval.json").read_text())
    # one pooled density for the single identical-input group (NLL and JSD) and one per JSD ground-truth set
    assert (info["rome_fits"], info["rome_fallback_fits"]) == (2, 1) and "rome_fits_ext" not in info


def test_eval_records_how_rome_densities_were_computed(tiny_run: Path, tmp_path: Path) -> None:
    """The exact KDE by default, scikit-learn's as romepy calls it on request: eval.json says which; an unknown
    name is a usage error before any work."""
    pytest.importorskip("sklearn", reason="the reference KDE needs scikit-learn (the dev or reference extra)")
    from dataclasses import replace

    tables = {}
    for kde in ("exact", "reference"):
        run = Path(shutil.copytree(tiny_run, tmp_path / kde))
        out = evaluate(run, options=replace(FAST, rome_kde=kde), quiet=True)
        assert json.loads((out / "eval.json").read_text())["rome_kde"] == kde
        tables[kde] = pl.read_parquet(out / "metrics.parquet")
    assert tables["exact"]["metric"].to_list() == tables["reference"]["metric"].to_list()
    with pytest.raises(UsageError, match="--rome-kde must be one of exact, reference"):
        evaluate(tmp_path / "exact", options=replace(FAST, rome_kde="sklearn"), quiet=True)


def test_an_interrupted_evaluation_resumes_its_rome_fits(tiny_run: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from trajflow_pipeline.metrics import parallel

    run = Path(shutil.copytree(tiny_run, tmp_path / "run"))
    shutil.rmtree(run / "eval", ignore_errors=True)
    real_fit, calls = parallel._fit_batch, []

    def fit_once(batch):
        if calls:
            raise KeyboardInterrupt
        calls.append(batch)
        return real_fit(batch)

    monkeypatch.setattr(parallel, "BATCH_FITS", 1)
    monkeypatch.setattr(parallel, "_fit_batch", fit_once)
    with pytest.raises(KeyboardInterrupt):
        evaluate(run, options=FAST, quiet=True)
    assert not (run / "eval").exists() and list((run / "eval-cache").glob("*/part-*.npz"))
    monkeypatch.setattr(parallel, "_fit_batch", real_fit)
    with claim(run / ".eval.lock"):  # another process evaluating the run: refused, the cache left alone
        with pytest.raises(UsageError, match="another process is evaluating this run"):
            evaluate(run, options=FAST, quiet=True)
    resumed_dir = evaluate(run, options=FAST, quiet=True)
    resumed = pl.read_parquet(resumed_dir / "metrics.parquet")
    assert json.loads((resumed_dir / "eval.json").read_text())["rome_fits_resumed"] == 1
    assert not (run / "eval-cache").exists()
    fresh = pl.read_parquet(evaluate(tiny_run, options=FAST, quiet=True) / "metrics.parquet")
    assert resumed.drop("run").equals(fresh.drop("run"))


def test_eval_is_deterministic_and_parallel_equals_serial(tiny_run: Path, tmp_path: Path) -> None:
    first = evaluate(tiny_run, options=FAST, quiet=True)
    before = pl.read_parquet(first / "metrics.parquet"), pl.read_parquet(first / "predictions.parquet")
    again = evaluate(tiny_run, options=EvalOptions(samples=12, k=5, workers=2), quiet=True)
    assert pl.read_parquet(again / "predictions.parquet").equals(before[1])
    assert pl.read_parquet(again / "metrics.parquet").equals(before[0])
    other_seed = evaluate(tiny_run, options=EvalOptions(samples=12, k=5, workers=1, seed=1), quiet=True)
    assert not pl.read_parquet(other_seed / "predictions.parquet").equals(before[1])


def test_eval_bad_inputs(tiny_run: Path, tiny_data: Path, tmp_path: Path) -> None:
    with pytest.raises(TrajflowError, match="not a trajflow run"):
        evaluate(tmp_path, options=FAST, quiet=True)
    unfinished = tmp_path / "unfinished"
    shutil.copytree(tiny_run, unfinished, ignore=shutil.ignore_patterns("final", "eval"))
    info = json.loads((unfinished / "run.json").read_text())
    (unfinished / "run.json").write_text(json.dumps({**info, "status": "training"}))
    with pytest.raises(TrajflowError, match="no final model"):
        evaluate(unfinished, options=FAST, quiet=True)
    with pytest.raises(UsageError, match="unknown metric"):
        evaluate(tiny_run, options=EvalOptions(metrics=("min_ade", "accuracy")), quiet=True)
    with pytest.raises(UsageError, match="--k must be between 1 and --samples"):
        evaluate(tiny_run, options=EvalOptions(samples=5, k=20), quiet=True)
    other = ingest_synthetic_bimodal(tmp_path / "other", samples=60, seed=9, quiet=True)
    with pytest.raises(TrajflowError, match="does not match the run's training data"):
        evaluate(tiny_run, data=other, options=FAST, quiet=True)
    forced = evaluate(tiny_run, data=other, options=FAST, force=True, quiet=True)
    assert json.loads((forced / "eval.json").read_text())["problems"] == 60
    folds_run = tmp_path / "folds_run"
    shutil.copytree(tiny_run, folds_run, ignore=shutil.ignore_patterns("eval"))
    info = json.loads((folds_run / "run.json").read_text())
    (folds_run / "run.json").write_text(json.dumps({**info, "fold": "hotel"}))
    with pytest.raises(UsageError, match="the run was trained on fold hotel of 'synthetic_bimodal'"):
        evaluate(folds_run, data=other, options=FAST, force=True, quiet=True)


def test_eval_cli_and_report(tiny_run: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["eval", str(tiny_run), "--samples", "12", "--k", "5", "--workers", "1", "-q"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["eval", str(tiny_run), "--metric", "nope", "-q"])
    assert result.exit_code == 2 and "unknown metric" in result.output
    out = report([tiny_run], tmp_path / "report", quiet=True)
    markdown = (out / "report.md").read_text()
    for column in ("minADE", "minFDE", "NLL", "JSD"):
        assert column in markdown
    pngs = list((out / "figures").glob("*.png"))
    assert pngs and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 1000 for p in pngs)
    assert "data:image/png;base64," in (out / "report.html").read_text()


def write_tiny_experiment(tmp_path: Path, models: list[str], seeds: list[int]) -> Path:
    """An experiment config over a small synthetic dataset (ingested on first use) with tiny budgets."""
    config = tmp_path / "exp.toml"
    config.write_text(f'''
name = "tiny"
[data]
path = "{(tmp_path / 'data').as_posix()}"
ingest = "synthetic-bimodal"
samples = 80
[protocol]
models = {json.dumps(models)}
seeds = {json.dumps(seeds)}
[train]
set = {json.dumps(TINY)}
[eval]
samples = 10
k = 5
workers = 1
''')
    return config


def test_experiment_runs_every_model_and_resumes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = write_tiny_experiment(tmp_path, ["cv", "trajflow-no-ae"], [0, 1])
    assert load_experiment(config).models == ("cv", "trajflow-no-ae")
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    index = json.loads((out / "experiment.json").read_text())
    assert index["runs"] == ["runs/cv-all-s0", "runs/cv-all-s1", "runs/trajflow-no-ae-all-s0",
                             "runs/trajflow-no-ae-all-s1"]
    metrics = pl.read_parquet(out / "metrics.parquet")
    assert set(metrics.get_column("model")) == {"cv", "trajflow-no-ae"}
    # an interrupted experiment: one run lost its evaluation; a re-run redoes only that, training nothing
    shutil.rmtree(out / "runs" / "cv-all-s1" / "eval")
    trained = {path: path.read_bytes() for path in out.glob("runs/*/train_log.parquet")}
    run_experiment(config, tmp_path / "exp", quiet=True)
    assert (out / "runs" / "cv-all-s1" / "eval" / "metrics.parquet").exists()
    assert {path: path.read_bytes() for path in out.glob("runs/*/train_log.parquet")} == trained, \
        "finished runs must not be trained again"
    bad = tmp_path / "bad.toml"
    bad.write_text(config.read_text().replace("[eval]", "[eval]\nbogus = 1"))
    with pytest.raises(UsageError, match="unknown key"):
        load_experiment(bad)
    bad.write_text(config.read_text().replace("samples = 80", "sampels = 80"))
    with pytest.raises(UsageError, match=r"unknown key\(s\) sampels in \[data\]"):
        load_experiment(bad)
    changed = tmp_path / "changed.toml"
    changed.write_text(config.read_text().replace("samples = 10", "samples = 11"))
    with pytest.raises(UsageError, match="made with a different config"):
        run_experiment(changed, out, quiet=True)


def test_raising_an_experiments_budget_continues_and_reevaluates_only_its_stopped_runs(tmp_path: Path) -> None:
    """A config that only raises an epoch budget may resume an experiment: the runs that budget stopped continue
    and are evaluated again, ending as a fresh experiment with the raised budget would; other runs stay."""
    config = write_tiny_experiment(tmp_path, ["cv", "trajflow-no-ae"], [0])
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    cv_eval = (out / "runs" / "cv-all-s0" / "eval" / "eval.json").read_bytes()
    flow_run = out / "runs" / "trajflow-no-ae-all-s0"
    digest_before = json.loads((flow_run / "eval" / "eval.json").read_text())["model_digest"]
    raised = tmp_path / "raised.toml"
    raised.write_text("# four flow epochs instead of two\n" + config.read_text().replace(
        '"train.flow_max_epochs=2"', '"train.flow_max_epochs=4"'))
    run_experiment(raised, out, quiet=True)
    assert (out / "config.toml").read_text() == raised.read_text()
    assert (out / "runs" / "cv-all-s0" / "eval" / "eval.json").read_bytes() == cv_eval
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 4
    evaluated = json.loads((flow_run / "eval" / "eval.json").read_text())
    assert evaluated["model_digest"] != digest_before
    assert evaluated["model_digest"] == json.loads((flow_run / "run.json").read_text())["rank_weight_digests"][0]
    fresh = run_experiment(raised, tmp_path / "fresh", quiet=True)
    columns = ["run", "metric", "value", "agent_index"]
    assert pl.read_parquet(out / "metrics.parquet").select(columns).equals(
        pl.read_parquet(fresh / "metrics.parquet").select(columns))
    # A run that cannot follow a raise (its flow's end state is gone) stops it before anything changes.
    (flow_run / "checkpoints" / "end-flow.pt").unlink()
    again = tmp_path / "again.toml"
    again.write_text(raised.read_text().replace('"train.flow_max_epochs=4"', '"train.flow_max_epochs=6"'))
    with pytest.raises(UsageError, match="cannot raise the budgets.*trajflow-no-ae-all-s0.*stage-end states"):
        run_experiment(again, out, quiet=True)
    assert (out / "config.toml").read_text() == raised.read_text()
    lowered = tmp_path / "lowered.toml"
    lowered.write_text(config.read_text().replace('"train.flow_max_epochs=2"', '"train.flow_max_epochs=1"'))
    with pytest.raises(UsageError,
                       match=r"flow_max_epochs: 4 vs 1\).*only epoch budgets, the settings of the stage after the flow "
                                 r"and the data stages may change"):
        run_experiment(lowered, out, quiet=True)


def test_deleting_a_budget_override_raises_the_budget_to_what_the_config_now_gives(tmp_path: Path) -> None:
    """An override removed from the config no longer applies: the run gets the budget the rest of the config gives
    it (here the paper's default), as a fresh experiment would; the experiment says it raised the budget, so it must
    not count the old run as done. A learning rate too small to move a weight makes every epoch's validation loss
    the first one's, so early stopping (patience 2) ends the raised run after epoch 3."""
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])
    config.write_text(config.read_text().replace(
        '"train.flow_min_epochs=1"', '"train.flow_min_epochs=1", "train.flow_patience=2", "train.flow_lr=1e-30"'))
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    flow_run = out / "runs" / "trajflow-no-ae-all-s0"
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 2
    removed = tmp_path / "removed.toml"
    removed.write_text(config.read_text().replace('"train.flow_max_epochs=2", ', ""))
    assert "flow_max_epochs" not in removed.read_text()
    evaluated_before = json.loads((flow_run / "eval" / "eval.json").read_text())["date"]
    run_experiment(removed, out, quiet=True)
    assert load_config(flow_run / "config.toml").train.flow_max_epochs == 500
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 3
    # evaluated again after the longer training (the kept weights are epoch 1's both times: the digest cannot tell)
    evaluated = json.loads((flow_run / "eval" / "eval.json").read_text())["date"]
    finished = json.loads((flow_run / "run.json").read_text())["finished"]
    assert evaluated != evaluated_before and evaluated >= finished


def test_raising_an_experiments_patience_continues_the_runs_it_stopped_early(tmp_path: Path) -> None:
    """More patience in the config continues a run whose flow stopped early and evaluates it again; a run that
    cannot follow (its flow's end state is gone) stops the raise before anything changes. As above, a learning
    rate too small to move a weight makes every validation loss the first one's: patience P stops after P + 1."""
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])
    config.write_text(config.read_text().replace(
        '"train.flow_max_epochs=2"', '"train.flow_max_epochs=8", "train.flow_patience=2", "train.flow_lr=1e-30"'))
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    flow_run = out / "runs" / "trajflow-no-ae-all-s0"
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 3
    evaluated_before = json.loads((flow_run / "eval" / "eval.json").read_text())["date"]
    raised = tmp_path / "raised.toml"
    raised.write_text(config.read_text().replace('"train.flow_patience=2"', '"train.flow_patience=4"'))
    run_experiment(raised, out, quiet=True)
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 5
    assert json.loads((flow_run / "eval" / "eval.json").read_text())["date"] != evaluated_before
    (flow_run / "checkpoints" / "end-flow.pt").unlink()
    again = tmp_path / "again.toml"
    again.write_text(raised.read_text().replace('"train.flow_patience=4"', '"train.flow_patience=6"'))
    with pytest.raises(UsageError, match="cannot raise the budgets.*trajflow-no-ae-all-s0.*stage-end states"):
        run_experiment(again, out, quiet=True)
    assert (out / "config.toml").read_text() == raised.read_text()


def test_no_early_stopping_set_for_one_run_by_hand_is_kept_by_the_experiment(tmp_path: Path) -> None:
    """A patience of 0 (no early stopping) is larger than the experiment's patience: the experiment keeps the run as
    it is, rather than asking it for a lower patience (and refusing)."""
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])
    config.write_text(config.read_text().replace(
        '"train.flow_max_epochs=2"', '"train.flow_max_epochs=5", "train.flow_patience=2", "train.flow_lr=1e-30"'))
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    flow_run = out / "runs" / "trajflow-no-ae-all-s0"
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 3
    train(tmp_path / "data", flow_run, resume=True, overrides=["train.flow_patience=0"], quiet=True)
    evaluate(flow_run, data=tmp_path / "data", options=EvalOptions(samples=10, k=5, workers=1), quiet=True)
    log = (flow_run / "train_log.parquet").read_bytes()
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 5
    run_experiment(config, out, quiet=True)
    assert (flow_run / "train_log.parquet").read_bytes() == log
    assert load_config(flow_run / "config.toml").train.flow_patience == 0


def test_a_budget_raised_for_one_run_by_hand_is_kept_by_the_experiment(tmp_path: Path) -> None:
    """`trajflow train --resume --set train.flow_max_epochs=N` beyond the experiment's budget, then eval: the
    experiment counts the run as done (it never lowers a budget), status shows the run's own budget, and a later
    raise of the experiment's budget above it continues the run."""
    from trajflow_pipeline.stages.status import experiment_status

    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])
    out = run_experiment(config, tmp_path / "exp", quiet=True)
    flow_run = out / "runs" / "trajflow-no-ae-all-s0"
    train(tmp_path / "data", flow_run, resume=True, overrides=["train.flow_max_epochs=3"], quiet=True)
    evaluate(flow_run, data=tmp_path / "data", options=EvalOptions(samples=10, k=5, workers=1), quiet=True)
    log = (flow_run / "train_log.parquet").read_bytes()
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 3
    run_experiment(config, out, quiet=True)
    assert (flow_run / "train_log.parquet").read_bytes() == log
    (status,) = experiment_status(out).runs
    assert status.state == "done" and status.progress is not None and status.progress.max_epochs == 3
    raised = tmp_path / "raised.toml"
    raised.write_text(config.read_text().replace('"train.flow_max_epochs=2"', '"train.flow_max_epochs=4"'))
    run_experiment(raised, out, quiet=True)
    assert pl.read_parquet(flow_run / "train_log.parquet").height == 4


def test_an_evaluation_counts_only_for_the_model_it_evaluated(tmp_path: Path) -> None:
    """By the weights' digest; for evaluations from before digests were recorded, by the dates."""
    from trajflow_pipeline.rundir import is_evaluated as run_evaluated

    run = tmp_path / "run"
    (run / "eval").mkdir(parents=True)
    pl.DataFrame({"metric": ["min_ade"], "value": [0.1]}).write_parquet(run / "eval" / "metrics.parquet")

    def state(status: str, digest: str | None, evaluated: str | None, date: str) -> bool:
        (run / "run.json").write_text(json.dumps({"status": status, "finished": "2026-11-30T10:00:00+00:00",
                                                  "rank_weight_digests": [digest] if digest else None}))
        (run / "eval" / "eval.json").write_text(json.dumps({"model_digest": evaluated, "date": date}))
        return run_evaluated(run)

    later, earlier = "2026-11-30T10:05:00.5+00:00", "2026-11-30T09:55:00.5+00:00"
    assert state("finished", "a", "a", earlier)          # the digest decides when both are known
    assert not state("finished", "b", "a", later)
    assert not state("training", "a", "a", later)        # a raised budget is being trained
    assert state("finished", "b", None, later)           # an old evaluation made after the model was finished
    assert not state("finished", "b", None, earlier)     # ... or before it: stale


def test_eval_refuses_weights_that_are_not_the_runs_and_records_what_it_evaluated(tiny_run: Path,
                                                                                  tmp_path: Path) -> None:
    """A final model replaced after training is not scored as the run's: eval checks the weights it loads against
    run.json's digest, and eval.json records the digest of the weights it evaluated."""
    import torch

    from trajflow_pipeline.model.checkpoint import load_model, model_digest, save_model

    run = Path(shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("eval")))
    weights = run / "final" / "model.safetensors"
    model = load_model(weights)
    recorded = json.loads((run / "run.json").read_text())["rank_weight_digests"][0]
    assert model_digest(model) == recorded
    with torch.no_grad():
        next(model.parameters()).add_(1e-3)
    save_model(model, weights)
    result = CliRunner().invoke(app, ["eval", str(run), "--samples", "12", "--k", "5", "--workers", "1", "--quiet"])
    assert result.exit_code == 1, result.output
    assert result.output.strip().startswith(f"error: {weights}: the weights are not the ones this run trained")
    assert len(result.output.strip().splitlines()) == 1 and not (run / "eval").exists()
    out = evaluate(run, options=FAST, quiet=True, force=True)
    assert json.loads((out / "eval.json").read_text())["model_digest"] == model_digest(model) != recorded
