"""`trajflow eval`: draw samples for every test problem of a run's fold and compute the paper's metrics.

Writes, atomically, ``RUN/eval/``:

* ``predictions.parquet``  — sample_id, draw, step (1..H), x, y (metres, world), log_lik (per draw; the model's
                              density in its `log_lik_space`, e.g. the flow latent for TrajFlow — see eval.json);
* ``ground_truth.parquet`` — sample_id, group_id, joint_id, step (-(n_past-1)..0 observed, 1..n_future future), x, y;
* ``metrics.parquet``      — long format: run, model, dataset, fold, seed, metric, value, agent_index, group_key,
                              sample_id, aggregate (True on the one mean row per metric, as the paper averages;
                              the other rows are per agent, or per joint group / identical-input group);
* ``eval.json``            — what produced the numbers: run, model, dataset, fold, seed, draws, K, metrics, workers,
                              ``ray`` (the Ray address the ROME fits ran on, or null), ``rome_kde`` (how ROME's densities were computed; docs/rome.md),
                              seconds, date, trajflow version and code revisions (``code_revision`` of the
                              evaluation, ``training_code_revisions`` from run.json), the machines (``machine``
                              that evaluated, ``training_machines``), data fingerprint, the run's resolved config,
                              the digest of the evaluated weights (``model_digest``: an experiment re-evaluates a
                              run whose final model has changed since), ``horizon`` (below), ``rome_fits`` and
                              ``rome_fallback_fits`` (ROME density fits made for the standard metrics, and how many
                              re-ran a failed PCA with added jitter; ``*_ext`` the same for the extended-horizon
                              metrics), and any ``warnings`` (a truncated horizon).

While it runs, finished ROME fits (most of an evaluation's time) are kept in ``RUN/eval-cache/``: an interrupted
evaluation, run again on the same model, data and setup, fits only what was not finished (the numbers are the
same; ``rome_fits_resumed`` in eval.json counts the fits it found, and ``seconds`` is the last attempt's), and the
folder is removed once ``RUN/eval/`` is written. A run is evaluated by one process at a time (``RUN/.eval.lock``).

Horizons. The metrics compare the predictions with the ground truth over the dataset's ``n_future`` steps.
``--steps S`` below it evaluates only the first S steps: allowed (a shorter-horizon evaluation is a legitimate
question), but printed as a warning and recorded (``horizon.truncated``, ``warnings``), never silent.

``--extended-horizon`` (EvalOptions.extended_horizon) is the paper's rounD protocol (section VI-B): the standard
metrics stay over the trained horizon, and every metric is computed once more with the suffix ``_ext`` over
each sample's own ground-truth horizon (the samples column ``n_future_max``: rounD needs up to 35 steps where
models train on 25). Predictions then run to the longest of those horizons; ADE averages a sample's own valid
steps, FDE takes its last one, ROME densities are fitted per sample on its own draws truncated to its horizon
(see :mod:`trajflow_pipeline.metrics.density`), and joint groups (rounD: a target / ego pair, which share a
horizon) use their shortest member's. ``*_ext`` averages over all samples, most of which (94 % of real rounD
scenes) end at n_future; ``*_ext_long`` (aggregate rows only) averages the same per-sample values over just the
samples (joint groups) that need more than n_future steps, the scenes the extrapolation check is about. The
paper's extrapolation minADE (2.27 m for TrajFlow against 0.67 m over 25 steps) looks like the latter, so both
are reported. Only the samples that need more than n_future steps are scored again, with every sample sharing
a joint group or an identical-input group with them (to a fixed point); all other units keep their standard rows,
which are by definition their extended values, and the means cover both. ROME seeds a fit by its order in a
call, so a recomputed density may differ slightly from one fitted among all samples. TrajFlow's auto-regressive
decoder rolls out the extra steps; models with a fixed output length (FloMo, TrajFlow w/o AE) are extended at
constant velocity from their last two predicted positions, as the paper's reference framework does:
``horizon.extended_by_constant_velocity`` records it.
"""

from __future__ import annotations

import datetime as dt
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch

from .. import __version__
from ..data import Problems, build_problems, select_samples
from ..errors import DataError, TrajflowError, UsageError
from ..metrics import METRIC_NAMES, RomeTally, check_metric_names, compute_metrics, jsd_groups
from ..metrics.extended import EXTENDED_SUFFIX, extended_metrics
from ..metrics.rome import KDE_CHOICES, KDE_EXACT
from ..model.checkpoint import model_digest
from ..model.models import CV_EXTENSION, TrajectoryModel
from ..model.runtime import resolve_device
from ..rundir import (EVAL_DIR, EVAL_FILE, EVAL_LOCK, GROUND_TRUTH_FILE, METRICS_FILE, PREDICTIONS_FILE, ROME_CACHE_DIR,
                      RunInfo, open_run)
from ..schemas import data_mismatch, open_dataset
from ..util import input_files
from ..util.atomic import atomic_directory
from ..util.bounds import check_seed
from ..util.claim import claim
from ..util.progress import make_progress, say
from ..util.provenance import code_revision, machine_description



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
    #: also score each sample over its own ground-truth horizon (samples column n_future_max) as *_ext metrics
    extended_horizon: bool = False
    #: cap on the pooled predictions of an identical-input group fed to ROME (None: all, as the reference
    #: framework); the synthetic set pools 3000 x draws points, which costs minutes per fit without a cap
    max_pooled: int | None = None
    #: how ROME's densities are computed: "exact" (the default) or "reference", romepy's arithmetic through
    #: scikit-learn (its numbers to the bit, rounding residue included; docs/rome.md)
    rome_kde: str = KDE_EXACT

    def validate(self) -> None:
        check_seed(self.seed, "--seed")
        if self.samples < 1:
            raise UsageError(f"--samples must be at least 1, got {self.samples}")
        if not 1 <= self.k <= self.samples:
            raise UsageError(f"--k must be between 1 and --samples ({self.samples}), got {self.k}")
        if self.workers is not None and self.workers < 1:
            raise UsageError(f"--workers must be at least 1, got {self.workers}")
        if self.steps is not None and self.steps < 1:
            raise UsageError(f"--steps must be at least 1, got {self.steps}")
        if not isinstance(self.extended_horizon, bool):
            raise UsageError(f"extended_horizon must be true or false, got {self.extended_horizon!r}")
        if self.max_pooled is not None and self.max_pooled < 2:
            raise UsageError(f"--max-pooled must be at least 2, got {self.max_pooled}")
        if self.rome_kde not in KDE_CHOICES:
            raise UsageError(f"--rome-kde must be one of {', '.join(KDE_CHOICES)}, got {self.rome_kde!r}")
        check_metric_names(self.metrics)


@dataclass(frozen=True)
class Horizon:
    """How many steps an evaluation predicts and scores (eval.json ``horizon``; see the module docstring)."""

    trained: int                 # the model's n_future
    ground_truth: int            # the dataset's n_future
    predicted: int               # steps drawn per future
    evaluated: int               # steps the standard metrics compare: min(ground_truth, predicted)
    beyond_horizon: str          # how the model makes steps past `trained` (models.AUTOREGRESSIVE, ...)
    extended: bool = False       # *_ext metrics over each sample's own horizon
    extended_min: int | None = None
    extended_max: int | None = None
    extended_samples: int | None = None   # samples whose own horizon exceeds ground_truth

    @property
    def truncated(self) -> bool:
        """True when the standard metrics see fewer steps than the ground truth has."""
        return self.evaluated < self.ground_truth

    @property
    def extended_by_cv(self) -> bool:
        """True when steps past the model's trained horizon come from constant-velocity extension."""
        return self.predicted > self.trained and self.beyond_horizon == CV_EXTENSION

    def record(self) -> dict[str, Any]:
        """The eval.json entry."""
        out: dict[str, Any] = {
            "trained": self.trained, "ground_truth": self.ground_truth, "predicted": self.predicted,
            "evaluated": self.evaluated, "truncated": self.truncated, "beyond_trained": self.beyond_horizon,
            "extended_by_constant_velocity": self.extended_by_cv, "extended": self.extended,
        }
        if self.extended:
            out.update(extended_metrics=f"*{EXTENDED_SUFFIX}: each sample over its own n_future_max",
                       extended_min=self.extended_min, extended_max=self.extended_max,
                       extended_samples=self.extended_samples)
        return out


def plan_horizon(options: EvalOptions, problems: Problems, model: TrajectoryModel) -> Horizon:
    """Steps to predict and to score. Default: the dataset's n_future, or with `extended_horizon` the longest
    ground-truth horizon; `--steps` below that longest horizon is a UsageError (it could not be scored)."""
    ground_truth = problems.n_future
    own = problems.horizons
    longest = int(own.max()) if options.extended_horizon else ground_truth
    predicted = options.steps if options.steps is not None else longest
    if options.extended_horizon and predicted < longest:
        raise UsageError(f"--steps {predicted} is shorter than the longest ground-truth horizon ({longest} steps, "
                         "samples column n_future_max) that --extended-horizon scores; drop --steps or raise it")
    extended = {}
    if options.extended_horizon:
        extended = {"extended_min": int(own.min()), "extended_max": longest,
                    "extended_samples": int((own > ground_truth).sum())}
    return Horizon(trained=model.spec.n_future, ground_truth=ground_truth, predicted=predicted,
                   evaluated=min(ground_truth, predicted), beyond_horizon=model.beyond_horizon,
                   extended=options.extended_horizon, **extended)


def horizon_warnings(horizon: Horizon, has_column: bool) -> list[str]:
    """What a user must know about the evaluated horizon: a truncation, or an extension with nothing to extend."""
    notes = []
    if horizon.truncated:
        notes.append(f"--steps {horizon.predicted} is below the dataset's n_future {horizon.ground_truth}: the "
                     f"metrics cover only the first {horizon.predicted} of {horizon.ground_truth} ground-truth "
                     "steps (recorded in eval.json, horizon.truncated)")
    if horizon.extended and not has_column:
        notes.append("--extended-horizon: the samples table has no n_future_max column, so every sample is scored "
                     f"over n_future = {horizon.ground_truth} and the *{EXTENDED_SUFFIX} metrics equal the others")
    return notes


def draw_predictions(model: TrajectoryModel, problems: Problems, options: EvalOptions, *, device: torch.device,
                     quiet: bool = False, steps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample `options.samples` futures per problem in batches: (A, S, H, 2) world positions and (A, S) log-liks.

    H is `steps` (default: `options.steps`, else the model's n_future). One torch generator seeded with
    `options.seed` drives every draw, so the result is reproducible.
    """
    steps = options.steps if steps is None else steps
    generator = torch.Generator(device=device).manual_seed(options.seed)
    trajectories, log_liks = [], []
    model.eval()
    with make_progress(quiet) as progress:
        task = progress.add_task(f"sampling {options.samples} futures", total=len(problems))
        for start in range(0, len(problems), options.batch_size):
            index = slice(start, min(start + options.batch_size, len(problems)))
            batch = problems.batch.index(index).without_future().to(device)
            drawn = model.sample(batch, options.samples, steps=steps, generator=generator)
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
    """Observed past and ground-truth future of every problem, steps relative to t0: up to n_future, or with an
    extended read up to each problem's own horizon (no rows past it: nothing is padded or invented)."""
    batch = problems.batch
    assert batch.future is not None
    future = batch.future if problems.extended_future is None else problems.extended_future
    positions = torch.cat([batch.past, future], dim=1).double().numpy()
    agents, steps, _ = positions.shape
    table = pl.DataFrame({
        "sample_id": np.repeat(problems.sample_id.astype(np.int64), steps),
        "group_id": np.repeat(problems.group_id.astype(np.int64), steps),
        "joint_id": np.repeat(problems.joint_id.astype(np.int64), steps),
        "step": np.tile(np.arange(1 - problems.n_past, steps - problems.n_past + 1, dtype=np.int64), agents),
        "x": positions[..., 0].ravel(),
        "y": positions[..., 1].ravel(),
    })
    return table if problems.extended_future is None else table.filter(pl.col("x").is_not_nan())


def metrics_table(run: RunInfo, problems: Problems, trajectories: np.ndarray, options: EvalOptions, *,
                  quiet: bool, horizon: Horizon | None = None, fallbacks: RomeTally | None = None,
                  fallbacks_ext: RomeTally | None = None, rome_cache: Path | None = None,
                  ray: str | None = None) -> pl.DataFrame:
    """The long metrics table of one run: the standard metrics over `horizon.evaluated` steps (default: the
    ground truth's n_future, or fewer when fewer were predicted) and, for an extended horizon, the same metrics
    with suffix _ext over each problem's own ground-truth horizon. `fallbacks` and `fallbacks_ext` tally the ROME
    fits that needed ROME's PCA fallback for the standard and the _ext metrics; `rome_cache` keeps finished fits
    on disk so that an interrupted evaluation resumes; with `ray` (a Ray address) the ROME fits run on that
    cluster, with the same numbers."""
    assert problems.batch.future is not None
    gt = problems.batch.future.double().numpy()
    steps = min(gt.shape[1], trajectories.shape[2]) if horizon is None else horizon.evaluated
    common = dict(joint_key=problems.joint_id, group_id=problems.group_id, k=options.k, metrics=options.metrics,
                  workers=options.workers, quiet=quiet, seed=options.seed, max_pooled=options.max_pooled,
                  fallbacks=fallbacks, rome_cache=rome_cache, rome_kde=options.rome_kde, ray=ray)
    table = compute_metrics(trajectories[:, :, :steps], gt[:, :steps], **common)
    if horizon is not None and horizon.extended:
        extended = extended_metrics(problems, trajectories, table, dict(common, fallbacks=fallbacks_ext))
        table = pl.concat([table, extended], how="vertical")
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
    mismatch = None if force else data_mismatch(run.fingerprint, given)
    if mismatch:
        raise TrajflowError(f"{given.get('path')}: data does not match the run's training data ({mismatch}); "
                            "pass --force to evaluate anyway")


def _check_weights_digest(run: RunInfo, model: TrajectoryModel, force: bool) -> str:
    """The digest of the weights about to be evaluated, refused (unless forced) when run.json recorded another:
    a final model replaced or changed after training would otherwise be scored, and filed, as this run's."""
    digest = model_digest(model)
    if run.weights_digest is not None and digest != run.weights_digest and not force:
        raise DataError(f"the weights are not the ones this run trained (digest {digest[:12]}, run.json records "
                        f"{run.weights_digest[:12]}): the file was replaced or changed after training; restore it, "
                        "retrain, or pass --force to evaluate them anyway", path=run.model_file)
    return digest


def evaluate(run_dir: str | Path, *, data: str | Path | None = None, options: EvalOptions | None = None,
             device: str = "auto", force: bool = False, quiet: bool = False, ray: str | None = None) -> Path:
    """Evaluate the run in `run_dir` on the test split of its fold; returns the eval directory. With `ray` (a Ray
    address, or 'local') the ROME fits are spread over that cluster in batches; the numbers are the same."""
    options = options or EvalOptions()
    options.validate()
    started = time.perf_counter()
    revision = code_revision()  # read now: a commit or checkout during evaluation must not be credited with it
    run = open_run(run_dir)
    with claim(run.path / EVAL_LOCK) as mine:  # one evaluation of a run at a time: they share RUN/eval-cache
        if not mine:
            raise UsageError(f"{run.path}: another process is evaluating this run (it holds {EVAL_LOCK}); "
                             "wait for it to finish")
        return _evaluate(run, data=data, options=options, device=device, force=force, quiet=quiet,
                         started=started, revision=revision, ray=ray)


def _evaluate(run: RunInfo, *, data: str | Path | None, options: EvalOptions, device: str, force: bool,
              quiet: bool, started: float, revision: str | None, ray: str | None = None) -> Path:
    """The evaluation of an opened run, under its evaluation claim (see `evaluate`)."""
    ds = open_dataset(data or run.data_path)
    _check_fingerprint(run, ds.fingerprint(), force)
    try:
        selection = select_samples(ds, run.fold, "test")
    except UsageError:
        raise UsageError(f"{ds.path}: the run was trained on fold {run.fold or '(none)'} of '{run.dataset}', "
                         f"which dataset '{ds.meta.dataset}' does not have") from None
    problems = build_problems(ds, selection, extended=options.extended_horizon)
    torch_device = resolve_device(device)
    model = run.load_model(torch_device)
    digest = _check_weights_digest(run, model, force)
    horizon = plan_horizon(options, problems, model)
    warnings = horizon_warnings(horizon, "n_future_max" in selection.columns)
    for warning in warnings:
        say(("warning:", "yellow"), f" {warning}")
    trajectories, log_lik = draw_predictions(model, problems, options, device=torch_device, quiet=quiet,
                                             steps=horizon.predicted)
    # ROME's PCA fallbacks are printed unless quiet, and recorded either way (experiment workers are quiet).
    fallbacks, fallbacks_ext = RomeTally(), RomeTally()
    metrics = metrics_table(run, problems, trajectories, options, quiet=quiet, horizon=horizon, fallbacks=fallbacks,
                            fallbacks_ext=fallbacks_ext, rome_cache=run.path / ROME_CACHE_DIR, ray=ray)
    info: dict[str, Any] = {
        "run": run.name, "run_dir": str(run.path.resolve()), "model": run.model, "dataset": problems.dataset,
        "fold": run.fold, "seed": run.seed, "samples": options.samples, "k": options.k,
        "metrics": list(check_metric_names(options.metrics)), "workers": options.workers, "ray": ray,
        "eval_seed": options.seed, "max_pooled": options.max_pooled, "rome_kde": options.rome_kde,
        "problems": len(problems), "steps": int(trajectories.shape[2]), "device": str(torch_device),
        "seconds": round(time.perf_counter() - started, 3), "date": dt.datetime.now(dt.timezone.utc).isoformat(),
        "trajflow_version": __version__, "code_revision": revision,
        "training_code_revisions": run.code_revisions, "machine": machine_description(str(torch_device)),
        "training_machines": run.machines,
        "data_fingerprint": problems.fingerprint, "config": run.config,
        "model_digest": digest,
        "log_lik_label": model.log_lik_space, "horizon": horizon.record(), "warnings": warnings,
        "rome_fits": fallbacks.fits, "rome_fallback_fits": fallbacks.fallback_fits,
        "rome_fits_resumed": fallbacks.resumed + fallbacks_ext.resumed,
        **({"rome_fits_ext": fallbacks_ext.fits, "rome_fallback_fits_ext": fallbacks_ext.fallback_fits}
           if horizon.extended else {}),
        **_group_counts(problems, horizon.evaluated, options.metrics),
    }
    with atomic_directory(run.path / EVAL_DIR) as tmp:
        predictions_table(problems.sample_id, trajectories, log_lik).write_parquet(tmp / PREDICTIONS_FILE)
        ground_truth_table(problems).write_parquet(tmp / GROUND_TRUTH_FILE)
        metrics.write_parquet(tmp / METRICS_FILE)
        (tmp / EVAL_FILE).write_text(json.dumps(info, indent=2, default=str) + "\n")
    shutil.rmtree(run.path / ROME_CACHE_DIR, ignore_errors=True)  # its fits are in the evaluation now
    return run.path / EVAL_DIR


def _group_counts(problems: Problems, steps: int, metrics: tuple[str, ...]) -> dict[str, int]:
    """How many identical-input groups JSD evaluates over `steps` (futures that differ), and how many it skips
    because they have a single future or several identical ones (no ground-truth density)."""
    if "jsd" not in metrics:
        return {}
    assert problems.batch.future is not None
    _, sizes = np.unique(problems.group_id, return_counts=True)
    evaluated, point_mass = jsd_groups(problems.batch.future[:, :steps].double().numpy(), problems.group_id)
    return {"jsd_groups": int(evaluated.size), "jsd_groups_skipped": int((sizes < 2).sum()),
            "jsd_groups_identical_futures": int(point_mass.size)}


def aggregate_metrics(eval_dir: str | Path) -> dict[str, float]:
    """metric -> value of the aggregate rows of an eval directory's metrics table."""
    table = input_files.read_parquet(Path(eval_dir) / METRICS_FILE).filter(pl.col("aggregate"))
    return dict(table.select("metric", "value").iter_rows())
