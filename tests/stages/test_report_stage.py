"""`trajflow report` on fake run directories written in the eval contract: tables, figures, provenance, errors.

`write_run` / `write_experiment` build runs exactly as `trajflow train` + `trajflow eval` lay them out
(eval/eval.json, eval/metrics.parquet, eval/predictions.parquet, eval/ground_truth.parquet, train_log.csv), so
these tests pin the contract the report reads.
"""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.errors import DataError, TrajflowError, UsageError
from trajflow_pipeline.stages.report import FIGURE_DIR, report

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
METRICS = ("min_ade", "min_fde", "min_ade_joint", "min_fde_joint", "nll", "nll_joint", "jsd")
BASE = {"min_ade": 0.3, "min_fde": 0.6, "min_ade_joint": 0.4, "min_fde_joint": 0.8, "nll": -20.0,
        "nll_joint": -70.0, "jsd": 0.5}
MODEL_FACTOR = {"trajflow": 1.0, "flomo": 1.5, "cv": 2.0, "trajflow-no-ae": 1.2}


def default_value(model: str, fold: str | None, seed: int, metric: str) -> float:
    """A deterministic metric value: model-dependent level plus small fold / seed offsets."""
    fold_offset = 0.0 if fold is None else 0.02 * (sum(map(ord, fold)) % 5)
    return BASE[metric] * MODEL_FACTOR.get(model, 1.0) + 0.01 * seed + fold_offset


def _trajectories(dataset: str, samples: int, n_past: int, n_future: int, draws: int,
                  rng: np.random.Generator) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Ground truth and predictions: one shared group with two modes for bimodal data, else one group per sample."""
    bimodal = dataset == "synthetic_bimodal"
    sample_id = np.arange(samples, dtype=np.int64)
    past_t = np.arange(1 - n_past, 1)
    future_t = np.arange(1, n_future + 1)
    origin = np.zeros((samples, 2)) if bimodal else np.stack([sample_id * 3.0, np.zeros(samples)], axis=1)
    direction = np.where((sample_id % 2 == 0)[:, None], [[1.0, 0.6]], [[1.0, -0.6]]) if bimodal else \
        np.tile([[1.0, 0.1]], (samples, 1))
    past = origin[:, None, :] + past_t[None, :, None] * np.array([1.0, 0.0]) * 0.5
    future = origin[:, None, :] + future_t[None, :, None] * direction[:, None, :] * 0.5
    xy = np.concatenate([past, future], axis=1)
    steps = np.concatenate([past_t, future_t])
    gt = pl.DataFrame({
        "sample_id": np.repeat(sample_id, steps.size),
        "group_id": np.repeat(np.zeros(samples, np.int64) if bimodal else sample_id, steps.size),
        "joint_id": np.repeat(sample_id, steps.size),
        "step": np.tile(steps.astype(np.int64), samples),
        "x": xy[..., 0].ravel(), "y": xy[..., 1].ravel(),
    })
    mode = rng.integers(0, 2, size=(samples, draws)) if bimodal else np.zeros((samples, draws), int)
    heading = np.where(mode[..., None] == 0, [1.0, 0.6], [1.0, -0.6]) if bimodal else \
        np.broadcast_to([1.0, 0.1], (samples, draws, 2))
    drawn = (origin[:, None, None, :] + future_t[None, None, :, None] * heading[:, :, None, :] * 0.5
             + rng.normal(0, 0.1, size=(samples, draws, n_future, 2)))
    log_lik = rng.normal(-5, 2, size=(samples, draws))
    predictions = pl.DataFrame({
        "sample_id": np.repeat(sample_id, draws * n_future),
        "draw": np.tile(np.repeat(np.arange(draws, dtype=np.int64), n_future), samples),
        "step": np.tile(future_t.astype(np.int64), samples * draws),
        "x": drawn[..., 0].ravel(), "y": drawn[..., 1].ravel(),
        "log_lik": np.repeat(log_lik.ravel(), n_future),
    })
    return gt, predictions


def write_run(root: Path, *, model: str, dataset: str, fold: str | None, seed: int,
              values: dict[str, float] | None = None, samples: int = 6, draws: int = 8, n_past: int = 4,
              n_future: int = 5, k: int = 5, train_log: bool = True, name: str | None = None) -> Path:
    """One evaluated run directory in the contract format; `values` overrides aggregate metric values."""
    name = name or f"{model}-{fold or 'all'}-s{seed}"
    run = root / name
    (run / "eval").mkdir(parents=True)
    values = {m: default_value(model, fold, seed, m) for m in METRICS} | (values or {})
    rng = np.random.default_rng(seed + 17 * len(model))
    gt, predictions = _trajectories(dataset, samples, n_past, n_future, draws, rng)
    gt.write_parquet(run / "eval" / "ground_truth.parquet")
    predictions.write_parquet(run / "eval" / "predictions.parquet")
    metric_names = list(values)
    per_sample = pl.DataFrame({
        "metric": np.repeat(metric_names, samples), "value": rng.uniform(0, 1, samples * len(metric_names)),
        "agent_index": np.tile(np.arange(samples, dtype=np.int64), len(metric_names)),
        "group_key": pl.Series([None] * samples * len(metric_names), dtype=pl.Int64),
        "sample_id": np.tile(np.arange(samples, dtype=np.int64), len(metric_names)),
        "aggregate": [False] * samples * len(metric_names)})
    aggregate = pl.DataFrame({
        "metric": metric_names, "value": [float(values[m]) for m in metric_names],
        "agent_index": pl.Series([None] * len(metric_names), dtype=pl.Int64),
        "group_key": pl.Series([None] * len(metric_names), dtype=pl.Int64),
        "sample_id": pl.Series([None] * len(metric_names), dtype=pl.Int64),
        "aggregate": [True] * len(metric_names)})
    identity = [pl.lit(name).alias("run"), pl.lit(model).alias("model"), pl.lit(dataset).alias("dataset"),
                pl.lit(fold, pl.String).alias("fold"), pl.lit(seed, pl.Int64).alias("seed")]
    pl.concat([per_sample, aggregate]).select(*identity, pl.all()).write_parquet(run / "eval" / "metrics.parquet")
    info = {"run": name, "model": model, "dataset": dataset, "fold": fold, "seed": seed, "samples": draws, "k": k,
            "metrics": metric_names, "workers": 1, "seconds": 1.5, "date": "2025-01-02T03:04:05+00:00",
            "trajflow_version": "0.1.0",
            "data_fingerprint": {"dataset": dataset, "manifest_sha256": "ab" * 32, "path": "/data/x"},
            "config": {"model": {"name": model, "latent": 20}, "train": {"seed": seed, "flow_lr": 0.001}},
            "log_lik_label": "flow latent density (scaled displacements)"}
    (run / "eval" / "eval.json").write_text(json.dumps(info, indent=2))
    if train_log and model != "cv":
        epochs = np.arange(1, 6)
        stages = ["autoencoder"] * 5 + ["flow"] * 5 if model == "trajflow" else ["flow"] * 5
        loss = np.concatenate([1.0 / epochs] * (len(stages) // 5))
        pl.DataFrame({"epoch": np.tile(epochs, len(stages) // 5), "stage": stages, "train_loss": loss,
                      "val_loss": loss * 1.1, "lr": 1e-3, "seconds": 0.1}).write_csv(run / "train_log.csv")
    return run


def write_experiment(root: Path, dataset: str, models=("trajflow", "flomo"), folds=("eth", "hotel"), seeds=(0, 1),
                     **kwargs) -> Path:
    """An experiment directory: runs/<model>-<fold>-s<seed> and experiment.json listing them."""
    runs = [write_run(root / "runs", model=m, dataset=dataset, fold=f, seed=s, **kwargs)
            for m in models for f in folds for s in seeds]
    relative = [str(r.relative_to(root)) for r in runs]
    (root / "experiment.json").write_text(json.dumps({"name": root.name, "runs": relative, "planned": relative}))
    return root


@pytest.fixture(scope="module")
def eth_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One report over an ETH/UCY-like experiment (2 models × 2 folds × 2 seeds) plus a synthetic run set."""
    root = tmp_path_factory.mktemp("report")
    experiment = write_experiment(root / "exp_eth", "eth_ucy")
    bimodal = [write_run(root / "bimodal", model=m, dataset="synthetic_bimodal", fold=None, seed=s, samples=40,
                         draws=10) for m in ("trajflow", "cv") for s in (0, 1)]
    return report([experiment, *bimodal], root / "REPORT", quiet=True, max_examples=2)


def _section(markdown: str, heading: str) -> str:
    """The Markdown of one `## heading` section."""
    match = re.search(rf"^## {re.escape(heading)}.*?(?=^## |\Z)", markdown, flags=re.M | re.S)
    assert match, heading
    return match.group(0)


def _table_row(section: str, label: str) -> list[str]:
    """The cells of the first table row whose first cell is `label`."""
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == label:
            return cells
    raise AssertionError(f"no row {label!r}")


def test_report_files_and_every_metric_column(eth_report: Path) -> None:
    for name in ("report.md", "report.html", "report.json"):
        assert (eth_report / name).stat().st_size > 0
    markdown = (eth_report / "report.md").read_text()
    for column in ("minADE (K=5)", "minFDE (K=5)", "minADE joint (K=5)", "minFDE joint (K=5)", "NLL indep",
                   "NLL joint", "JSD"):
        assert column in markdown
    eth = _section(markdown, "ETH/UCY")
    paper = _table_row(eth, "TrajFlow (paper)")
    assert paper[2:4] == ["0.330", "0.550"] and paper[6:8] == ["-21.05", "-75.79"] and paper[8] == "—"
    assert "minADE: MET" in eth or "minADE: NOT MET" in eth
    assert "NLL joint: NOT MET — our TrajFlow -69.98 > paper -75.79." in eth
    assert not list(eth_report.parent.glob(".REPORT.tmp-*"))


def test_mean_std_over_folds_and_seeds_and_best_in_bold(tmp_path: Path) -> None:
    crafted = {("trajflow", "a", 0): 0.1, ("trajflow", "a", 1): 0.2, ("trajflow", "b", 0): 0.3,
               ("trajflow", "b", 1): 0.4, ("flomo", "a", 0): 0.5, ("flomo", "a", 1): 0.5,
               ("flomo", "b", 0): 0.7, ("flomo", "b", 1): 0.7}
    runs = [write_run(tmp_path / "runs", model=m, dataset="round", fold=f, seed=s, values={"min_ade": v})
            for (m, f, s), v in crafted.items()]
    out = report(runs, tmp_path / "rep", quiet=True, figures=False)
    section = _section((out / "report.md").read_text(), "rounD")
    trajflow, flomo = _table_row(section, "TrajFlow"), _table_row(section, "FloMo")
    values = np.array([0.1, 0.2, 0.3, 0.4])
    assert trajflow[1] == "4" and trajflow[2] == f"**{values.mean():.3f} ± {values.std():.3f}**"
    assert trajflow[2] == "**0.250 ± 0.112**" and flomo[2] == "0.600 ± 0.100"
    assert _table_row(section, "TrajFlow (paper)")[2] == "0.670"
    assert "minADE: MET — our TrajFlow 0.25 ≤ paper 0.67." in section
    # per-fold breakdown: mean over the two seeds, best per fold in bold
    assert _table_row(section, "a")[1:3] == ["**0.150**", "0.500"]
    assert _table_row(section, "b")[1:3] == ["**0.350**", "0.700"]
    assert "minADE: mean over seeds (2 per cell); bold: best per fold" in section
    summary = json.loads((out / "report.json").read_text())["summary"]
    row = next(r for r in summary if r["model"] == "trajflow" and r["metric"] == "min_ade")
    assert row["mean"] == pytest.approx(0.25) and row["std"] == pytest.approx(values.std()) and row["runs"] == 4


def test_missing_metric_is_a_dash_and_single_run_has_no_std(tmp_path: Path) -> None:
    run = write_run(tmp_path, model="trajflow", dataset="mine", fold=None, seed=0, train_log=False)
    metrics = pl.read_parquet(run / "eval" / "metrics.parquet").filter(pl.col("metric") != "jsd")
    metrics.write_parquet(run / "eval" / "metrics.parquet")
    out = report([run], tmp_path / "rep", quiet=True, figures=False)
    markdown = (out / "report.md").read_text()
    row = _table_row(_section(markdown, "mine"), "TrajFlow")
    assert row[2] == "**0.300**" and row[-1] == "—"
    assert "no TrajFlow results for `mine`" in markdown and "TrajFlow (paper)" not in markdown


def test_datasets_get_separate_sections(eth_report: Path) -> None:
    markdown = (eth_report / "report.md").read_text()
    eth, bimodal = _section(markdown, "ETH/UCY"), _section(markdown, "Synthetic bimodal")
    assert markdown.index("## Synthetic bimodal") < markdown.index("## ETH/UCY")  # the paper's order
    assert "Constant velocity" in bimodal and "Constant velocity" not in eth
    assert "FloMo" in eth and "FloMo" not in bimodal
    assert "### Per fold" in eth and "### Per fold" not in bimodal
    assert _table_row(bimodal, "TrajFlow (paper)")[-1] == "0.683"


def test_figures_are_png_files_and_embedded_in_html(eth_report: Path) -> None:
    names = sorted(p.name for p in (eth_report / "figures").iterdir())
    assert names == sorted([
        "eth_ucy-examples.png", "eth_ucy-training-trajflow.png", "eth_ucy-training-flomo.png",
        "eth_ucy-min-ade-vs-k.png", "synthetic_bimodal-examples.png", "synthetic_bimodal-density.png",
        "synthetic_bimodal-training-trajflow.png", "synthetic_bimodal-min-ade-vs-k.png"])
    markdown = (eth_report / "report.md").read_text()
    html = (eth_report / "report.html").read_text()
    embedded = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert len(embedded) == len(names)
    for name in names:
        data = (eth_report / "figures" / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 5000, name
        assert f"](figures/{name})" in markdown
        assert base64.b64encode(data).decode() in embedded
    assert 'src="figures/' not in html
    assert "No training log (train_log.csv / .parquet) for: Constant velocity." in markdown


def test_provenance_lists_every_run_with_config(eth_report: Path) -> None:
    markdown = (eth_report / "report.md").read_text()
    html = (eth_report / "report.html").read_text()
    provenance = _section(markdown, "Provenance")
    for name in ("trajflow-eth-s0", "flomo-hotel-s1", "cv-all-s1"):
        row = _table_row(provenance, name)
        assert "2025-01-02T03:04:05+00:00" in row and "0.1.0" in row
        assert any("manifest_sha256=abababababab…" in cell for cell in row)
    assert provenance.count("```json") == 12
    assert '"flow_lr": 0.001' in provenance
    assert html.count("<details><summary>Config and data fingerprint of") == 12


def test_no_figures_and_replacing_an_older_report(tmp_path: Path) -> None:
    run = write_run(tmp_path, model="trajflow", dataset="eth_ucy", fold="eth", seed=0)
    out = report([run], tmp_path / "rep", quiet=True)
    assert list((out / "figures").iterdir())
    out = report([run], out, quiet=True, figures=False)
    assert not list((out / "figures").iterdir()) and "<img" not in (out / "report.html").read_text()


def test_bad_inputs_are_one_line_errors(tmp_path: Path) -> None:
    good = write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold="eth", seed=0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(TrajflowError, match=r"empty: neither an evaluated run .* nor an experiment"):
        report([tmp_path / "empty"], tmp_path / "out", quiet=True)
    with pytest.raises(TrajflowError, match=r"nowhere: not found"):
        report([tmp_path / "nowhere"], tmp_path / "out", quiet=True)
    trained = tmp_path / "trained"
    (trained / "final").mkdir(parents=True)
    with pytest.raises(TrajflowError, match=r"trained: no eval/metrics.parquet; run `trajflow eval .*trained` first"):
        report([good, trained], tmp_path / "out", quiet=True)
    corrupt = write_run(tmp_path / "runs", model="flomo", dataset="eth_ucy", fold="eth", seed=0)
    (corrupt / "eval" / "metrics.parquet").write_bytes(b"PAR1 this is not parquet")
    with pytest.raises(DataError, match=r"flomo-eth-s0/eval/metrics.parquet: unreadable metrics table"):
        report([good, corrupt], tmp_path / "out", quiet=True)
    pl.DataFrame({"a": [1]}).write_parquet(corrupt / "eval" / "metrics.parquet")
    with pytest.raises(DataError, match=r"metrics.parquet: not a trajflow metrics table: missing column\(s\) "
                                       r"metric, value, aggregate"):
        report([corrupt], tmp_path / "out", quiet=True)
    (good / "eval" / "predictions.parquet").write_bytes(b"garbage")
    with pytest.raises(DataError, match=r"trajflow-eth-s0/eval/predictions.parquet: unreadable predictions table"):
        report([good], tmp_path / "out", quiet=True)
    (good / "eval" / "eval.json").write_text("{not json")
    with pytest.raises(DataError, match=r"eval.json: not valid JSON"):
        report([good], tmp_path / "out", quiet=True)
    assert not (tmp_path / "out").exists()


def test_output_guards(tmp_path: Path) -> None:
    run = write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold="eth", seed=0)
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(TrajflowError, match="precious: exists and is not a trajflow report"):
        report([run], precious, quiet=True, figures=False)
    assert (precious / "notes.txt").read_text() == "keep me"
    with pytest.raises(TrajflowError, match="would replace the input run"):
        report([run], run, quiet=True, figures=False)
    with pytest.raises(UsageError, match="--examples"):
        report([run], tmp_path / "rep", quiet=True, max_examples=-1)


def test_a_regenerated_report_keeps_the_files_beside_it(tmp_path: Path) -> None:
    run = write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold="eth", seed=0)
    out = report([run], tmp_path / "rep", quiet=True)
    (out / "config.toml").write_text("name = 'x'\n")
    (out / "models" / "trajflow-eth-s0" / "final").mkdir(parents=True)
    (out / "models" / "trajflow-eth-s0" / "final" / "model.safetensors").write_bytes(b"weights")
    (out / FIGURE_DIR / "stale.png").write_bytes(b"old figure")
    report([run], out, quiet=True)
    assert (out / "config.toml").read_text() == "name = 'x'\n"
    assert (out / "models" / "trajflow-eth-s0" / "final" / "model.safetensors").read_bytes() == b"weights"
    assert not (out / FIGURE_DIR / "stale.png").exists()           # the figures are the report's own
    assert (out / "report.md").is_file() and not list(tmp_path.glob(".rep.*"))


def test_experiment_with_unfinished_runs_and_duplicates(tmp_path: Path) -> None:
    experiment = write_experiment(tmp_path / "exp", "forking_paths", models=("trajflow",), folds=("0",),
                                  seeds=(0,))
    manifest = json.loads((experiment / "experiment.json").read_text())
    manifest["planned"] = [*manifest["runs"], "runs/trajflow-1-s0"]
    (experiment / "experiment.json").write_text(json.dumps(manifest))
    copy = write_run(tmp_path / "elsewhere", model="trajflow", dataset="forking_paths", fold="0", seed=0)
    out = report([experiment, experiment / "runs" / "trajflow-0-s0", copy], tmp_path / "rep", quiet=True,
                 figures=False)
    markdown = (out / "report.md").read_text()
    assert "1 of 2 planned runs are finished" in markdown
    assert "TrajFlow fold 0 seed 0 appears in 2 runs" in markdown
    assert _table_row(_section(markdown, "Forking Paths"), "TrajFlow")[1] == "2"


def _with_plan(experiment: Path, models: tuple[str, ...], folds: tuple[str | None, ...], *,
               unfinished: tuple[str, ...] = (), name: str | None = None) -> None:
    """Give an experiment's manifest a plan (seed 0) and drop the runs `unfinished` from its finished ones."""
    manifest = json.loads((experiment / "experiment.json").read_text())
    manifest["runs"] = [r for r in manifest["runs"] if r not in unfinished]
    manifest["plan"] = [{"run": f"runs/{m}-{f or 'all'}-s0", "model": m, "fold": f, "seed": 0}
                        for m in models for f in folds]
    manifest["planned"] = [row["run"] for row in manifest["plan"]]
    manifest["name"] = name or manifest["name"]
    (experiment / "experiment.json").write_text(json.dumps(manifest))


def test_a_report_of_unfinished_work_names_the_missing_folds_and_judges_no_target(tmp_path: Path) -> None:
    experiment = write_experiment(tmp_path / "exp", "eth_ucy", models=("cv", "trajflow"), folds=("eth", "hotel"),
                                  seeds=(0,))
    _with_plan(experiment, ("cv", "trajflow"), ("eth", "hotel", "zara1"), unfinished=("runs/trajflow-hotel-s0",))
    markdown = (report([experiment], tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    section = _section(markdown, "ETH/UCY")
    assert ("Not every model has runs on every fold yet: TrajFlow has none on folds hotel, zara1; Constant "
            "velocity has none on fold zara1.") in section
    assert "The paper targets are not judged until TrajFlow has every fold" in section
    assert "minADE: NOT CHECKED — no TrajFlow run on folds hotel, zara1 yet; our TrajFlow" in section
    assert "MET" not in section.replace("NOT CHECKED", "")
    assert "(on fold eth, the only one both have runs on)" in section
    assert ("3 of 6 planned runs are finished; the report shows the finished ones (not yet: TrajFlow, 2 runs; "
            "Constant velocity, 1 run)") in markdown
    # an older manifest without the plan: the folds are those of the runs (hotel, from cv), not the planned zara1
    manifest = json.loads((experiment / "experiment.json").read_text())
    del manifest["plan"]
    (experiment / "experiment.json").write_text(json.dumps(manifest))
    section = _section((report([experiment], tmp_path / "rep1", quiet=True, figures=False) / "report.md").read_text(),
                       "ETH/UCY")
    assert "Not every model has runs on every fold yet: TrajFlow has none on fold hotel." in section
    for plan in ([{"run": "runs/x", "model": "cv", "fold": 3, "seed": 0}],
                 [{"run": "runs/x", "model": "cv", "fold": "eth", "seed": True}], {"runs/x": "cv"}):
        manifest["plan"] = plan
        (experiment / "experiment.json").write_text(json.dumps(manifest))
        with pytest.raises(DataError, match=r"experiment\.json.*`plan`"):
            report([experiment], tmp_path / "rep2", quiet=True, figures=False)


def test_the_plans_of_experiments_that_share_a_name_stay_apart(tmp_path: Path) -> None:
    eth = write_experiment(tmp_path / "a", "eth_ucy", models=("trajflow",), folds=("eth", "hotel"), seeds=(0,))
    synthetic = write_experiment(tmp_path / "b", "synthetic_bimodal", models=("trajflow",), folds=(None,),
                                 seeds=(0,))
    _with_plan(eth, ("trajflow",), ("eth", "hotel"), name="paper")
    _with_plan(synthetic, ("trajflow",), (None,), name="paper")
    markdown = (report([eth, synthetic], tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    assert "Not every model" not in markdown and "NOT CHECKED" not in markdown


def test_parquet_training_log_without_validation(tmp_path: Path) -> None:
    run = write_run(tmp_path, model="flomo", dataset="eth_ucy", fold="eth", seed=0, train_log=False)
    pl.DataFrame({"epoch": [1, 2, 3], "stage": ["flow"] * 3, "train_loss": [3.0, 2.0, 1.5],
                  "val_loss": pl.Series([None] * 3, dtype=pl.Float64)}).write_parquet(run / "train_log.parquet")
    out = report([run], tmp_path / "rep", quiet=True, max_examples=1)
    png = (out / "figures" / "eth_ucy-training-flomo.png").read_bytes()
    assert png.startswith(PNG_SIGNATURE) and len(png) > 5000
    (run / "train_log.parquet").write_bytes(b"nope")
    with pytest.raises(DataError, match="train_log.parquet: unreadable training log"):
        report([run], tmp_path / "rep", quiet=True)


def test_groups_skipped_by_jsd_are_counted(tmp_path: Path) -> None:
    runs = [write_run(tmp_path / "runs", model="trajflow", dataset="forking_paths", fold=str(f), seed=0)
            for f in range(2)]
    for run, (evaluated, skipped, identical) in zip(runs, [(5, 2, 0), (4, 1, 3)]):
        info = json.loads((run / "eval" / "eval.json").read_text())
        (run / "eval" / "eval.json").write_text(json.dumps({**info, "jsd_groups": evaluated,
                                                            "jsd_groups_skipped": skipped,
                                                            "jsd_groups_identical_futures": identical}))
    out = report(runs, tmp_path / "rep", quiet=True, figures=False)
    assert ("JSD skipped 3 with a single ground-truth future and 3 whose ground-truth futures are all the same "
            "(identical-input groups; evaluated on 9 group(s) with different futures)"
            in (out / "report.md").read_text())


def test_evaluation_warnings_and_rome_fallbacks_are_reported(tmp_path: Path) -> None:
    """eval.json warnings (a truncated horizon) reach the report once with their runs; ROME's PCA fallbacks are
    summed, per metric set, and runs evaluated before they were counted are said to be missing from the sum."""
    runs = [write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold=f, seed=0)
            for f in ("eth", "hotel", "univ")]
    short = "evaluated over 8 of the data's 12 future steps (--steps 8)"
    for run, counts in zip(runs, [(100, 2, 10, 1), (50, 1, 4, 0)]):
        info = json.loads((run / "eval" / "eval.json").read_text())
        (run / "eval" / "eval.json").write_text(json.dumps({**info, "warnings": [short], **dict(zip(
            ("rome_fits", "rome_fallback_fits", "rome_fits_ext", "rome_fallback_fits_ext"), counts))}))
    markdown = (report(runs, tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    assert ("3 of 150 ROME density fits for the metrics, summed over runs, re-ran a failed PCA with added jitter "
            "(ROME's own fallback for a singular cluster); 1 run evaluated before such fits were counted." in markdown)
    assert "1 of 14 ROME density fits for the extended-horizon (_ext) metrics" in markdown
    assert f"Evaluation warning (trajflow-eth-s0, trajflow-hotel-s0): {short}" in markdown


def test_compute_time_and_machines_per_model(tmp_path: Path) -> None:
    """Training time from the logs' epoch times and evaluation time from eval.json, summed per model, with the
    machines that trained and evaluated the runs where they were recorded."""
    runs = [write_run(tmp_path / "runs", model=m, dataset="eth_ucy", fold=f, seed=0)
            for m in ("trajflow", "cv") for f in ("eth", "hotel")]
    for run in runs[:2]:
        info = json.loads((run / "eval" / "eval.json").read_text())
        (run / "eval" / "eval.json").write_text(json.dumps({
            **info, "seconds": 5400.0, "machine": "CPU: X, 2 cores",
            "training_machines": ["unrecorded", "CPU: X, 2 cores"] if run.name.endswith("eth-s0") else ["GPU: Y"]}))
    markdown = (report(runs, tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    section = markdown[markdown.index("### Compute"):]
    # trajflow: 10 logged epochs of 0.1 s per run; cv runs have no training log
    assert _table_row(section, "TrajFlow") == ["TrajFlow", "2", "2 s", "3.0 h", "unrecorded; CPU: X, 2 cores; GPU: Y",
                                               "CPU: X, 2 cores"]
    assert _table_row(section, "Constant velocity") == ["Constant velocity", "2", "—", "3 s", "not recorded",
                                                        "not recorded"]


def test_settings_that_differ_from_the_paper_are_named(tmp_path: Path) -> None:
    """A reduced budget or a change of ours shows next to the numbers; keys that only identify a run do not."""
    runs = [write_run(tmp_path / "runs", model=m, dataset="eth_ucy", fold=f, seed=0)
            for m in ("trajflow", "flomo") for f in ("eth", "hotel")]
    for run in runs:
        info = json.loads((run / "eval" / "eval.json").read_text())
        info["config"]["train"] |= {"flow_max_epochs": 25, "device": "cuda", "seed": 7}
        if info["model"] == "flomo":
            info["config"]["model"] |= {"flow_standardize": True}
        (run / "eval" / "eval.json").write_text(json.dumps(info))
    markdown = (report(runs, tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    assert ("Settings that differ from the paper's: model.flow_standardize = true (paper: false) in 2 runs (FloMo); "
            "train.flow_max_epochs = 25 (paper: 500) in all runs." in markdown)
    assert "train.device" not in markdown and "train.seed" not in markdown
    plain = [write_run(tmp_path / "plain", model="trajflow", dataset="eth_ucy", fold="eth", seed=0)]
    assert "differ from the paper" not in (report(plain, tmp_path / "rep2", quiet=True, figures=False)
                                           / "report.md").read_text()


def test_nll_medians_beside_the_means(tmp_path: Path) -> None:
    """Each run's median over its per-agent NLL rows (and per-group joint rows), averaged over runs per model and
    per fold, in a table of their own without the paper's row; the means above are untouched."""
    runs = [write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold=f, seed=0, samples=5)
            for f in ("eth", "hotel")]
    for run, nll in zip(runs, ([1.0, 2.0, 3.0, 4.0, 900.0], [-5.0, -4.0, -3.0, 50.0, 60.0])):
        path = run / "eval" / "metrics.parquet"
        table = pl.read_parquet(path)
        values = table["value"].to_numpy().copy()
        values[((table["metric"] == "nll") & ~table["aggregate"]).to_numpy()] = nll
        table.with_columns(value=pl.Series(values)).write_parquet(path)
    out = report(runs, tmp_path / "rep", quiet=True, figures=False)
    markdown = (out / "report.md").read_text()
    medians = markdown[markdown.index("### NLL medians"):markdown.index("### Compute")]
    row = _table_row(medians, "TrajFlow")
    assert row[1] == "2" and row[2] == "**0.00 ± 3.00**"  # medians 3 and -3
    assert "TrajFlow (paper)" not in medians and "per run the median over agents" in medians
    assert _table_row(medians[medians.index("#### NLL indep median, per fold"):], "eth")[1] == "**3.00**"
    assert _table_row(medians[medians.index("#### NLL indep median, per fold"):], "hotel")[1] == "**-3.00**"
    assert "#### NLL joint median, per fold" in medians and "#### minADE median" not in medians
    assert _table_row(_section(markdown, "ETH/UCY"), "TrajFlow")[6] == "**-19.99 ± 0.01**"  # the aggregates
    medians_json = json.loads((out / "report.json").read_text())["nll_medians"]
    assert {(r["metric"], r["mean"]) for r in medians_json["summary"]} >= {("nll", 0.0)}


def test_nll_medians_name_runs_without_per_agent_rows_and_keep_nan(tmp_path: Path) -> None:
    """A run whose table holds only aggregates is named in a note, not silently averaged out; a NaN among a run's
    per-agent values makes its median NaN, as its mean would be, rather than the median of the rest."""
    runs = [write_run(tmp_path / "runs", model="trajflow", dataset="eth_ucy", fold=f, seed=0, samples=5)
            for f in ("eth", "hotel", "univ")]
    path = runs[1] / "eval" / "metrics.parquet"
    pl.read_parquet(path).filter(pl.col("aggregate")).write_parquet(path)
    path = runs[2] / "eval" / "metrics.parquet"
    table = pl.read_parquet(path)
    values = table["value"].to_numpy().copy()
    values[((table["metric"] == "nll") & ~table["aggregate"]).to_numpy()] = [1.0, 2.0, np.nan, 4.0, 5.0]
    table.with_columns(value=pl.Series(values)).write_parquet(path)
    markdown = (report(runs, tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    medians = markdown[markdown.index("### NLL medians"):markdown.index("### Compute")]
    assert "Note: no per-agent NLL rows to take medians of in 1 run (trajflow-hotel-s0); the medians below leave " \
           "it out." in medians
    assert _table_row(medians, "TrajFlow")[1] == "2"
    per_fold = medians[medians.index("#### NLL indep median, per fold"):]
    assert _table_row(per_fold, "univ")[1] == "nan" and "hotel" not in per_fold.split("####")[1]


def test_uneven_seeds_are_noted(tmp_path: Path) -> None:
    experiment = write_experiment(tmp_path / "exp", "eth_ucy", models=("trajflow", "cv"), folds=("eth", "hotel"),
                                  seeds=(0, 1))
    manifest = json.loads((experiment / "experiment.json").read_text())
    manifest["runs"] = [r for r in manifest["runs"] if r != "runs/trajflow-hotel-s1"]
    (experiment / "experiment.json").write_text(json.dumps(manifest))
    markdown = (report([experiment], tmp_path / "rep", quiet=True, figures=False) / "report.md").read_text()
    assert "Folds have different numbers of seeds (TrajFlow: fold eth 2, fold hotel 1)." in markdown
