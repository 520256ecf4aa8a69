"""`trajflow eval`: draw samples for every test problem of a run's fold and compute the paper's metrics.

Writes, atomically, ``RUN/eval/``:

* ``predictions.parquet``  — sample_id, draw, step (1..H), x, y (metres, world), log_lik (per draw; the model's
                              density in its `log_lik_space`, e.g. the flow latent for TrajFlow — see eval.json);
* ``ground_truth.parquet`` — sample_id, group_id, joint_id, step (-(n_past-1)..0 observed, 1..n_future future), x, y;
* ``metrics.parquet``      — long format: run, model, dataset, fold, seed, metric, value, agent_index, group_key,
                              sample_id, aggregate (True on the one mean row per metric, as the paper averages;
                              the other rows are per agent, or per joint group / identical-input group);
* ``eval.json``            — what produced the numbers: run, model, dataset, fold, seed, draws, K, metrics, workers,
                              seconds, date, trajflow version, data fingerprint, the run's resolved config.
"""

from __future__ import annotations

import datetime as dt
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch

from .. import __version__
from ..data import Problems, build_problems, select_samples
from ..errors import TrajflowError, UsageError
from ..metrics import METRIC_NAMES, check_metric_names, compute_metrics
from ..model.models import TrajectoryModel
from ..schemas import open_dataset
from ..util.atomic import atomic_directory
from ..util.progress import make_progress
from .runs import RunInfo, open_run

EVAL_DIR = "eval"


@dataclass(frozen=True)
class EvalOptions:
    """How a run is evaluated; the defaults are the paper's (100 draws, minADE/minFDE on 20 of them)."""

    samples: int = 100
    k: int = 20
    metrics: tuple[str, ...] = METRIC_NAMES
    workers: int | None = None
    seed: int = 0
    batch_size: int = 512
    steps: int | None = None
    #: cap on the pooled predictions of an identical-input group fed to ROME (None: all, as the reference
    #: framework); the synthetic set pools 3000 x draws points, which costs minutes per fit without a cap
    max_pooled: int | None = None

    def validate(self) -> None:
        if self.samples < 1:
            raise UsageError(f"--samples must be at least 1, got {self.samples}")
        if not 1 <= self.k <= self.samples:
            raise UsageError(f"--k must be between 1 and --samples ({self.samples}), got {self.k}")
        if self.workers is not None and self.workers < 1:
            raise UsageError(f"--workers must be at least 1, got {self.workers}")
        if self.steps is not None and self.steps < 1:
            raise UsageError(f"--steps must be at least 1, got {self.steps}")
        if self.max_pooled is not None and self.max_pooled < 2:
            raise UsageError(f"--max-pooled must be at least 2, got {self.max_pooled}")
        check_metric_names(self.metrics)


def draw_predictions(model: TrajectoryModel, problems: Problems, options: EvalOptions, *, device: torch.device,
                     quiet: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Sample `options.samples` futures per problem in batches: (A, S, H, 2) world positions and (A, S) log-liks.

    One torch generator seeded with `options.seed` drives every draw, so the result is reproducible.
    """
    generator = torch.Generator(device=device).manual_seed(options.seed)
    trajectories, log_liks = [], []
    model.eval()
    with make_progress(quiet) as progress:
        task = progress.add_task(f"sampling {options.samples} futures", total=len(problems))
        for start in range(0, len(problems), options.batch_size):
            index = slice(start, min(start + options.batch_size, len(problems)))
            batch = problems.batch.index(index).without_future().to(device)
            drawn = model.sample(batch, options.samples, steps=options.steps, generator=generator)
            trajectories.append(drawn.trajectories.double().cpu().numpy())
            log_liks.append(drawn.log_lik.double().cpu().numpy())
            progress.advance(task, index.stop - index.start)
    return np.concatenate(trajectories), np.concatenate(log_liks)


def predictions_table(sample_id: np.ndarray, trajectories: np.ndarray, log_lik: np.ndarray) -> pl.DataFrame:
    """Long table of the draws: one row per (sample, draw, step)."""
    agents, draws, steps, _ = trajectories.shape
    return pl.DataFrame({
        "sample_id": np.repeat(sample_id.astype(np.int64), draws * steps),
        "draw": np.tile(np.repeat(np.arange(draws, dtype=np.int64), steps), agents),
        "step": np.tile(np.arange(1, steps + 1, dtype=np.int64), agents * draws),
        "x": trajectories[..., 0].ravel(),
        "y": trajectories[..., 1].ravel(),
        "log_lik": np.repeat(log_lik.ravel(), steps),
    })


def ground_truth_table(problems: Problems) -> pl.DataFrame:
    """Observed past and ground-truth future of every problem, steps relative to t0."""
    batch = problems.batch
    assert batch.future is not None
    positions = torch.cat([batch.past, batch.future], dim=1).double().numpy()
    agents, steps, _ = positions.shape
    return pl.DataFrame({
        "sample_id": np.repeat(problems.sample_id.astype(np.int64), steps),
        "group_id": np.repeat(problems.group_id.astype(np.int64), steps),
        "joint_id": np.repeat(problems.joint_id.astype(np.int64), steps),
        "step": np.tile(np.arange(1 - problems.n_past, problems.n_future + 1, dtype=np.int64), agents),
        "x": positions[..., 0].ravel(),
        "y": positions[..., 1].ravel(),
    })


def metrics_table(run: RunInfo, problems: Problems, trajectories: np.ndarray, options: EvalOptions, *,
                  quiet: bool) -> pl.DataFrame:
    """The long metrics table of one run, ground truth compared over the trained horizon."""
    assert problems.batch.future is not None
    gt = problems.batch.future.double().numpy()
    horizon = min(gt.shape[1], trajectories.shape[2])
    table = compute_metrics(trajectories[:, :, :horizon], gt[:, :horizon], joint_key=problems.joint_id,
                            group_id=problems.group_id, k=options.k, metrics=options.metrics,
                            workers=options.workers, quiet=quiet, seed=options.seed, max_pooled=options.max_pooled)
    sample_ids = pl.Series(problems.sample_id.astype(np.int64))
    return table.with_columns(
        sample_id=pl.col("agent_index").map_batches(
            lambda idx: sample_ids.gather(idx.fill_null(0)).set(idx.is_null(), None), return_dtype=pl.Int64),
    ).select(
        pl.lit(run.name).alias("run"), pl.lit(run.model).alias("model"), pl.lit(problems.dataset).alias("dataset"),
        pl.lit(run.fold, dtype=pl.String).alias("fold"), pl.lit(run.seed, dtype=pl.Int64).alias("seed"),
        "metric", "value", "agent_index", "group_key", "sample_id", "aggregate",
    )


def _check_fingerprint(run: RunInfo, given: dict[str, str], force: bool) -> None:
    """Refuse data other than the run was trained on (other dataset or other manifest) unless forced."""
    trained = run.fingerprint
    if force or not trained:
        return
    for key in ("dataset", "manifest_sha256"):
        if trained.get(key) != given.get(key):
            raise TrajflowError(
                f"{given.get('path')}: data does not match the run's training data ({key}: run has "
                f"{trained.get(key)!r}, data has {given.get(key)!r}); pass --force to evaluate anyway")


def evaluate(run_dir: str | Path, *, data: str | Path | None = None, options: EvalOptions | None = None,
             device: str = "auto", force: bool = False, quiet: bool = False) -> Path:
    """Evaluate the run in `run_dir` on the test split of its fold; returns the eval directory."""
    options = options or EvalOptions()
    options.validate()
    started = time.perf_counter()
    run = open_run(run_dir)
    ds = open_dataset(data or run.data_path)
    _check_fingerprint(run, ds.fingerprint(), force)
    try:
        selection = select_samples(ds, run.fold, "test")
    except UsageError:
        raise UsageError(f"{ds.path}: the run was trained on fold {run.fold or '(none)'} of '{run.dataset}', "
                         f"which dataset '{ds.meta.dataset}' does not have") from None
    problems = build_problems(ds, selection)
    torch_device = _device(device)
    model = run.load_model(torch_device)
    trajectories, log_lik = draw_predictions(model, problems, options, device=torch_device, quiet=quiet)
    metrics = metrics_table(run, problems, trajectories, options, quiet=quiet)
    info: dict[str, Any] = {
        "run": run.name, "run_dir": str(run.path.resolve()), "model": run.model, "dataset": problems.dataset,
        "fold": run.fold, "seed": run.seed, "samples": options.samples, "k": options.k,
        "metrics": list(check_metric_names(options.metrics)), "workers": options.workers, "eval_seed": options.seed,
        "max_pooled": options.max_pooled,
        "problems": len(problems), "steps": int(trajectories.shape[2]), "device": str(torch_device),
        "seconds": round(time.perf_counter() - started, 3), "date": dt.datetime.now(dt.timezone.utc).isoformat(),
        "trajflow_version": __version__, "data_fingerprint": problems.fingerprint, "config": run.config,
        "log_lik_label": model.log_lik_space,
        **_group_counts(problems.group_id, options.metrics),
    }
    with atomic_directory(run.path / EVAL_DIR) as tmp:
        predictions_table(problems.sample_id, trajectories, log_lik).write_parquet(tmp / "predictions.parquet")
        ground_truth_table(problems).write_parquet(tmp / "ground_truth.parquet")
        metrics.write_parquet(tmp / "metrics.parquet")
        (tmp / "eval.json").write_text(json.dumps(info, indent=2, default=str) + "\n")
    return run.path / EVAL_DIR


def _group_counts(group_id: np.ndarray, metrics: tuple[str, ...]) -> dict[str, int]:
    """How many identical-input groups JSD evaluates (two or more futures) and skips (a single future)."""
    if "jsd" not in metrics:
        return {}
    _, sizes = np.unique(group_id, return_counts=True)
    return {"jsd_groups": int((sizes >= 2).sum()), "jsd_groups_skipped": int((sizes < 2).sum())}


def aggregate_metrics(eval_dir: str | Path) -> dict[str, float]:
    """metric -> value of the aggregate rows of an eval directory's metrics table."""
    table = pl.read_parquet(Path(eval_dir) / "metrics.parquet").filter(pl.col("aggregate"))
    return dict(table.select("metric", "value").iter_rows())


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as error:
        raise UsageError(f"--device: {error}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError("--device cuda requested but no CUDA device is available")
    return device
