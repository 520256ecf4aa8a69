"""Run independent ROME density fits in same-shape batches, across processes, with identical numbers for any worker count.

A ROME fit (OPTICS clustering, silhouette choice among 199 candidate clusterings, per-cluster PCA whitening,
Gaussian KDE) is the slow part of evaluation. Fits of one shape (n points of dimension D) are fitted together by
:mod:`trajflow_pipeline.metrics.rome`, one batched array program; batches are spread over processes.

Determinism: every batch runs with BLAS / OpenMP limited to one thread (also faster for these small problems), and
the estimator uses no random numbers, so a fit's result depends only on its task: serial and parallel runs, and any
batching, give bit-identical arrays.

ROME re-runs a cluster's PCA with added jitter when it fails (a singular covariance); those fits are counted, and
:func:`run_rome_tasks` says once how many needed the fallback (and adds them to a :class:`RomeTally` when given
one, which is how `trajflow eval` records them in eval.json even when quiet).

Batches run in a pool of :mod:`trajflow_pipeline.util.scheduler` (the one the experiment runner uses for its
runs): local worker processes, never forked from the calling process (the eval stage has used torch's thread pools
before the metrics run, and forking a process with live OpenMP threads can deadlock the child), from a
'forkserver' that has imported the estimator once (it lives as long as the calling process, so later pools start
at once), or 'spawn' where forkserver does not exist (Windows); or, with `ray`, tasks on a Ray cluster, one batch
each, spread over the cluster's CPUs. The numbers are the same either way. Worker functions are top level, so
every backend can import them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics import rome
from trajflow_pipeline.metrics.rome import DEFAULT_MIN_STD, KDE_CHOICES, KDE_EXACT
from trajflow_pipeline.metrics.rome_cache import Finished, RomeCache
from trajflow_pipeline.util.progress import make_progress, say
from trajflow_pipeline.util.scheduler import LocalPool, RayPool, Resources

#: most points x points x fits clustered in one batch (bounds a batch's working memory to a few hundred MB)
BATCH_BUDGET = 1 << 21
#: most dimensions x min(points, dimensions) x fits in one batch (a layer of the densities' principal axes)
BATCH_AXES_BUDGET = 1 << 23
#: most fits in one batch (also how often, at most, finished fits are saved to a cache)
BATCH_FITS = 256


@dataclass(frozen=True)
class RomeTask:
    """One ROME density: fitted on `fit` (n, D) and evaluated (log-density) at each array in `queries`.

    `label` names the task in error messages (e.g. "agent 17", "group 3 predictions, chunk 2"); `kde` is how the
    density is computed (`rome.KDE_CHOICES`: exact, or romepy's arithmetic through scikit-learn).
    """

    fit: np.ndarray
    queries: tuple[np.ndarray, ...]
    label: str = "ROME task"
    min_std: float = DEFAULT_MIN_STD
    kde: str = KDE_EXACT


@dataclass
class RomeTally:
    """A running tally, over any number of :func:`run_rome_tasks` calls, of the ROME fits: how many there were, how
    many re-ran a failed PCA with added jitter (ROME's own fallback for a singular cluster; the fit goes on,
    slightly perturbed) and with how many retries, and how many were resumed from a cache rather than made."""

    fits: int = 0
    fallback_fits: int = 0
    retries: int = 0
    resumed: int = 0

    def note(self) -> str:
        """One sentence for a log or a warnings list ('' when no fit fell back)."""
        if not self.fallback_fits:
            return ""
        return (f"{self.fallback_fits} of {self.fits} ROME fits re-ran a failed PCA with added jitter "
                f"({self.retries} retries; ROME's own fallback for a singular cluster)")


def resolve_workers(workers: int | None) -> int:
    """The number of worker processes: `None` means all cores (os.cpu_count()); must be >= 1."""
    if workers is None:
        return max(1, os.cpu_count() or 1)
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise UsageError(f"workers must be a positive integer (got {workers!r})")
    return int(workers)


def fit_and_score(task: RomeTask) -> tuple[np.ndarray, ...]:
    """Fit ROME on `task.fit` and return the log-density at each query array (float64); see `_fit_batch`."""
    return _fit_batch([task])[0][0]


def _check_task(task: RomeTask) -> None:
    """DataError unless the task's points and queries are finite and their distances fit in double precision;
    UsageError for an unknown KDE."""
    if task.kde not in KDE_CHOICES:
        raise UsageError(f"unknown ROME KDE {task.kde!r}; valid: {', '.join(KDE_CHOICES)}")
    if np.ndim(task.fit) != 2 or np.shape(task.fit)[0] < 2:
        raise DataError(f"cannot estimate a density for {task.label}: it needs at least 2 samples of one "
                        f"dimension each, got an array of shape {np.shape(task.fit)}")
    if not (np.isfinite(task.fit).all() and all(np.isfinite(q).all() for q in task.queries)):
        raise DataError(f"non-finite values in the points of {task.label}")
    with np.errstate(over="ignore"):
        extent = float(np.square(np.ptp(np.asarray(task.fit, dtype=np.float64), axis=0)).sum())
    if not np.isfinite(extent):
        raise DataError(f"the points of {task.label} are too far apart for a density estimate (their distances "
                        "overflow double precision): are they in the right units?")
    dimension = task.fit.shape[1]
    for query in task.queries:
        if np.ndim(query) != 2 or np.shape(query)[1] != dimension:
            raise DataError(f"the queries of {task.label} have shape {np.shape(query)}; the density is over "
                            f"{dimension} dimensions")


def _fit_batch(tasks: Sequence[RomeTask]) -> list[tuple[tuple[np.ndarray, ...], int]]:
    """Fit ROME on each task's points (all of one shape) and return, per task, the log-density at each of its query
    arrays and how many times a cluster's PCA was re-run with jitter (ROME's fallback; 0 for most fits).

    The clusterings and the exact densities of all fits are one batched computation
    (`trajflow_pipeline.metrics.rome`); tasks asking for the reference KDE get theirs per fit through scikit-learn.
    BLAS and OpenMP run on one thread (faster for these small problems, and reproducible), so a result is a
    function of its task alone. ROME's log-density is a log-sum-exp over clusters of KDE log-densities computed in
    log space: far from every sample it is very negative but finite, never -inf, so no floor is applied. A
    non-finite result can only come from a degenerate fit and is reported as a DataError.
    """
    from threadpoolctl import threadpool_limits

    for task in tasks:
        _check_task(task)
    points = np.stack([np.ascontiguousarray(task.fit, dtype=np.float64) for task in tasks])
    with threadpool_limits(limits=1):
        labels = rome.cluster(points)
        exact = np.array([task.kde == KDE_EXACT for task in tasks])
        results = _exact_densities(tasks, points, labels, exact) if exact.any() else {}
        results.update({i: _reference_density(tasks[i], points[i], labels[i]) for i in np.flatnonzero(~exact)})
    out = [results[i] for i in range(len(tasks))]
    for task, (values, _) in zip(tasks, out):
        for value in values:
            if not np.all(np.isfinite(value)):
                raise DataError(f"ROME returned a non-finite log-density for {task.label} "
                                f"({task.fit.shape[0]} points of dimension {task.fit.shape[1]}): "
                                "the sample set is degenerate")
    return out


def _exact_densities(tasks: Sequence[RomeTask], points: np.ndarray, labels: np.ndarray,
                     wanted: np.ndarray) -> dict[int, tuple[tuple[np.ndarray, ...], int]]:
    """The exact densities of the `wanted` tasks (index -> result as `_fit_batch`), fitted as one batch and
    evaluated in groups of tasks with equally many query points."""
    chosen = np.flatnonzero(wanted)
    mixture = rome.fit_mixture(points[chosen], labels[chosen], np.array([tasks[i].min_std for i in chosen]))
    lengths = {i: [len(q) for q in tasks[i].queries] for i in chosen}
    by_count: dict[int, list[int]] = {}
    for position, i in enumerate(chosen):
        by_count.setdefault(sum(lengths[i]), []).append(position)
    results: dict[int, tuple[tuple[np.ndarray, ...], int]] = {}
    for count, positions in by_count.items():
        members = [int(chosen[p]) for p in positions]
        if count:
            queries = np.stack([np.concatenate([np.asarray(q, dtype=np.float64).reshape(-1, points.shape[2])
                                                for q in tasks[i].queries]) for i in members])
            values = mixture.log_density(queries, np.array(positions))
        else:
            values = np.zeros((len(members), 0))
        for row, (position, i) in enumerate(zip(positions, members)):
            parts = np.split(values[row], np.cumsum(lengths[i])[:-1]) if lengths[i] else []
            results[i] = (tuple(parts), int(mixture.pca_retries[position]))
    return results


def _reference_density(task: RomeTask, points: np.ndarray, labels: np.ndarray) -> tuple[tuple[np.ndarray, ...], int]:
    """One task's density through scikit-learn as romepy computes it (`rome.KDE_REFERENCE`)."""
    try:
        import sklearn
    except ImportError as error:
        raise UsageError("the reference KDE needs scikit-learn (the reference extra: pip install -e '.[reference]'); "
                         "the exact KDE, the default, does not") from error
    from trajflow_pipeline.metrics.rome.reference import ReferenceDensity

    # inputs are checked finite float64, so scikit-learn's repeated validation is skipped (public settings)
    with sklearn.config_context(assume_finite=True, skip_parameter_validation=True):
        density = ReferenceDensity(points, labels, task.min_std)
        values = tuple(np.asarray(density.log_density(np.ascontiguousarray(q, dtype=np.float64)), dtype=np.float64)
                       for q in task.queries)
    return values, density.pca_retries


def _run_batch(batch: list[tuple[int, RomeTask]]) -> list[tuple[int, tuple[tuple[np.ndarray, ...], int]]]:
    """Worker entry point (top level, so 'spawn' can import it): fit a batch of (index, task) pairs of one shape."""
    return [(index, result) for (index, _), result in zip(batch, _fit_batch([task for _, task in batch]))]


#: Modules the forkserver imports once, so that forked workers start with the estimator ready.
_PRELOAD = ("trajflow_pipeline.metrics.parallel", "threadpoolctl")
#: times Ray runs a batch again whose worker died (a batch is pure: running it again gives the same numbers)
RAY_RETRIES = 3


def _saved(store: RomeCache | None, finished: list[Finished], quiet: bool) -> RomeCache | None:
    """Save finished fits in `store`; the cache only saves time, so when it cannot be written the fits go on without
    it (said once) rather than the evaluation ending. Returns the store to use from now on."""
    if store is None or not finished:
        return store
    try:
        store.save(finished)
    except OSError as error:
        if not quiet:
            say(("warning:", "yellow"), f" cannot save ROME fits in {store.directory} ({error}); going on without a "
                "cache, so an interruption would start the fits again")
        return None
    return store


def _batches(tasks: Sequence[RomeTask], todo: list[int], workers: int) -> list[list[int]]:
    """Task indices in batches of one fit shape, in task order within each: at most BATCH_FITS fits, BATCH_BUDGET
    points squared and BATCH_AXES_BUDGET principal-axis elements per batch, and at least ~4 batches per worker when there are enough fits."""
    by_shape: dict[tuple[int, int], list[int]] = {}
    for index in todo:
        by_shape.setdefault(tuple(np.shape(tasks[index].fit)), []).append(index)
    spread = max(1, -(-len(todo) // (4 * workers))) if workers > 1 else BATCH_FITS
    batches = []
    for (n_points, dimension), indices in by_shape.items():
        axes = dimension * min(n_points, dimension)
        size = max(1, min(BATCH_FITS, spread, BATCH_BUDGET // max(1, n_points * n_points),
                          BATCH_AXES_BUDGET // max(1, axes)))
        batches += [indices[i:i + size] for i in range(0, len(indices), size)]
    return sorted(batches)


def run_rome_tasks(tasks: Sequence[RomeTask], *, workers: int | None = None, quiet: bool = False,
                   description: str = "ROME density fits", base_seed: int = 0,
                   fallbacks: RomeTally | None = None, cache: Path | None = None,
                   ray: str | None = None) -> list[tuple[np.ndarray, ...]]:
    """Run independent ROME tasks and return, in task order, each task's tuple of log-density arrays.

    `workers` processes (default: all cores; 1 runs in this process, as does a single task) share the
    tasks in batches of one fit shape; the numbers are identical for any `workers` and any batching. With `ray`
    (a Ray address, `util.scheduler.connect_ray`), the batches are Ray tasks of one CPU each instead, as many
    as the cluster has CPUs at once (`workers` is then not used).
    `base_seed` names the task list in a cache (the estimator itself draws no random numbers).
    A rich progress bar counts finished fits unless `quiet`, and a note says how many fits needed ROME's PCA
    fallback (see the module docstring) when any did; `fallbacks`, when given, adds this call's counts to it.
    With `cache` (a directory), finished fits are saved as they come and a rerun over the same tasks fits only
    those not saved yet (see :mod:`trajflow_pipeline.metrics.rome_cache`); the numbers are the same either way.
    """
    n_workers = resolve_workers(workers)
    ray_pool = RayPool(ray, Resources(cpus=1), retries=RAY_RETRIES) if ray is not None and tasks else None
    if ray_pool is not None:
        n_workers = ray_pool.capacity
    n_tasks = len(tasks)
    results: list[tuple[np.ndarray, ...] | None] = [None] * n_tasks
    retries = np.zeros(n_tasks, dtype=np.int64)
    if n_tasks == 0:
        return []
    store = RomeCache(cache, tasks, base_seed) if cache is not None else None
    for index, (values, retried) in (store.load() if store is not None else {}).items():
        results[index], retries[index] = values, retried
    todo = [index for index, result in enumerate(results) if result is None]
    resumed = n_tasks - len(todo)
    if resumed and not quiet:
        say((f"{description}: {resumed} of {n_tasks} fits resumed from {store.directory}", "dim"))
    batches = _batches(tasks, todo, n_workers)
    progress = make_progress(quiet)
    with progress:
        bar = progress.add_task(description, total=n_tasks, completed=resumed)
        if ray_pool is None and (n_workers == 1 or len(batches) <= 1):
            for batch in batches:
                done = _run_batch([(i, tasks[i]) for i in batch])
                for index, (values, retried) in done:
                    results[index], retries[index] = values, retried
                store = _saved(store, done, quiet)
                progress.advance(bar, len(done))
        else:
            with ray_pool or LocalPool(min(n_workers, len(batches)), preload=_PRELOAD) as pool:
                futures = [pool.submit(_run_batch, [(i, tasks[i]) for i in batch]) for batch in batches]
                unsaved = set(futures)
                try:
                    for future in as_completed(futures):
                        done = future.result()
                        for index, (values, retried) in done:
                            results[index], retries[index] = values, retried
                        store = _saved(store, done, quiet)
                        unsaved.discard(future)
                        progress.advance(bar, len(done))
                except BaseException:
                    for future in futures:
                        future.cancel()
                    for future in unsaved:  # batches that finished before the interruption are kept too
                        if future.done() and not future.cancelled() and future.exception() is None:
                            store = _saved(store, future.result(), quiet)
                    raise
    missing = [i for i, r in enumerate(results) if r is None]
    if missing:  # cannot happen unless the pool misbehaves; never hand back a silently short list
        raise RuntimeError(f"ROME tasks {missing[:10]} produced no result")
    this_call = RomeTally(fits=n_tasks, fallback_fits=int((retries > 0).sum()), retries=int(retries.sum()),
                          resumed=resumed)
    if fallbacks is not None:
        fallbacks.fits += this_call.fits
        fallbacks.fallback_fits += this_call.fallback_fits
        fallbacks.retries += this_call.retries
        fallbacks.resumed += this_call.resumed
    if this_call.fallback_fits and not quiet:
        say((f"note: {this_call.note()}", "dim"))
    return results  # type: ignore[return-value]
