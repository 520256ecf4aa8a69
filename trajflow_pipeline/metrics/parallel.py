"""Run independent ROME density fits across processes, with identical numbers for any worker count.

A ROME fit (OPTICS clustering, silhouette model selection over 199 candidate clusterings, per-cluster PCA
whitening, Gaussian KDE) is the slow part of evaluation. On 100 x 24 points of real draws it takes about 0.03 s
here, against 0.22 s for the library as it is: scikit-learn's input validation is skipped, and the shortcuts of
:mod:`trajflow_pipeline.metrics.rome_shortcuts` avoid most of its per-call overhead; none of these changes a
number (bench/rome_shortcuts.py checks every log-density). Everything else in `trajflow_pipeline.metrics` is
vectorised numpy; the fits are the only per-task Python work, so this
module spreads them over processes.

Determinism: every task is run with BLAS / OpenMP limited to one thread (which is also ~2.5x faster for
these small problems than letting OpenBLAS use several threads) and with numpy's global RNG seeded from the
task's index in the list (ROME itself is deterministic given its input, but it and scikit-learn may touch
the global RNG). A task's result therefore depends only on its data and index, never on which process or
in which order it ran: serial and parallel runs give bit-identical arrays.

ROME prints "PCA failed, was done again with different random start." to stdout when a cluster's covariance is
singular and it retries with added jitter (its own fallback; the fit goes on). Those lines would land in the
middle of progress bars and tables, so they are counted instead, and :func:`run_rome_tasks` says once how many
fits needed the fallback (and adds them to a :class:`RomeTally` tally when given one, which is how
`trajflow eval` records them in eval.json even when quiet).

Workers are never forked from the calling process: the eval stage has used torch's thread pools before the
metrics run, and forking a process with live OpenMP threads can deadlock the child. They come from a
'forkserver' (a fresh, single-threaded interpreter that has imported ROME / scikit-learn once, ~2-3 s,
and then forks each worker cheaply; it lives as long as the calling process, so later pools start at
once), or from 'spawn' where forkserver does not exist (Windows). Worker functions are top level, so both
start methods can import them.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics.rome_cache import Finished, RomeCache
from trajflow_pipeline.metrics.rome_shortcuts import romepy_audited, shortcuts
from trajflow_pipeline.util.progress import console, make_progress

#: ROME's default minimum standard deviation (metres here); the reference framework uses the default too.
DEFAULT_MIN_STD = 0.1
#: with a cache and one worker, finished fits are saved every this many (about 20-30 s of fitting)
CACHE_EVERY = 256


@dataclass(frozen=True)
class RomeTask:
    """One ROME density: fitted on `fit` (n, D) and evaluated (log-density) at each array in `queries`.

    `label` names the task in error messages (e.g. "agent 17", "group 3 predictions, chunk 2").
    """

    fit: np.ndarray
    queries: tuple[np.ndarray, ...]
    label: str = "ROME task"
    min_std: float = DEFAULT_MIN_STD


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


def fit_and_score(task: RomeTask, seed: int) -> tuple[np.ndarray, ...]:
    """Fit ROME on `task.fit` and return the log-density at each query array (float64); see `_fit_and_score`."""
    return _fit_and_score(task, seed)[0]


def _fit_and_score(task: RomeTask, seed: int) -> tuple[tuple[np.ndarray, ...], int]:
    """Fit ROME on `task.fit`; return the log-density at each query array (float64) and how many times ROME fell
    back to re-running a failed PCA with jitter (0 for most fits).

    Runs in whichever process calls it; BLAS / OpenMP threads are limited to one and numpy's global RNG is
    seeded with `seed` so that the result is a function of (task, seed) only. Those settings and our shortcuts
    are process-wide, so fits from several threads of one process take turns. Finiteness is checked here once
    (of the points, and of their squared extent, which bounds every distance ROME computes), and scikit-learn's
    own (repeated) input validation is switched off for speed. ROME's `score_samples`
    returns a natural-log density (log-sum-exp over clusters of KDE log-densities, each computed in log
    space), so points far from every sample get a very negative but finite value, never -inf: no floor
    is applied. A non-finite result can only come from a degenerate fit and is reported as a DataError.
    """
    if not (np.isfinite(task.fit).all() and all(np.isfinite(q).all() for q in task.queries)):
        raise DataError(f"non-finite values in the points of {task.label}")
    with np.errstate(over="ignore"):
        extent = float(np.square(np.ptp(np.asarray(task.fit, dtype=np.float64), axis=0)).sum())
    if not np.isfinite(extent):
        raise DataError(f"the points of {task.label} are too far apart for a density estimate (their distances "
                        "overflow double precision): are they in the right units?")
    import sklearn
    from rome.ROME import ROME
    from threadpoolctl import threadpool_limits

    # One BLAS / OpenMP thread (faster for these small problems, and reproducible); scikit-learn's input
    # and parameter validation skipped (inputs are checked finite float64 here; ~20 % of a fit's time,
    # numbers unchanged); the shortcuts of rome_shortcuts (numbers unchanged too).
    with _ONE_FIT_AT_A_TIME, threadpool_limits(limits=1), \
            sklearn.config_context(assume_finite=True, skip_parameter_validation=True), shortcuts(), \
            _rome_messages_counted() as messages:
        np.random.seed(seed % (2**32))
        model = ROME(min_std=task.min_std).fit(np.ascontiguousarray(task.fit, dtype=np.float64))
        out = tuple(np.asarray(model.score_samples(np.ascontiguousarray(q, dtype=np.float64)), dtype=np.float64)
                    for q in task.queries)
    for values in out:
        if not np.all(np.isfinite(values)):
            raise DataError(f"ROME returned a non-finite log-density for {task.label} "
                            f"({task.fit.shape[0]} points of dimension {task.fit.shape[1]}): "
                            "the sample set is degenerate")
    return out, sum(PCA_RETRY_MESSAGE in message for message in messages)


#: Held while a fit runs: the RNG seed, thread limits and module patches of a fit are process-wide, and two threads
#: patching and restoring the same attributes could leave them patched.
_ONE_FIT_AT_A_TIME = threading.RLock()

#: What ROME prints (once per failed attempt) when it re-runs a cluster's PCA with jitter.
PCA_RETRY_MESSAGE = "PCA failed"


@contextlib.contextmanager
def _rome_messages_counted() -> Iterator[list[str]]:
    """While active, what ROME's module prints is collected in the yielded list instead of reaching stdout.

    ROME calls the built-in ``print``; a module-level ``print`` shadows it for that module only, so nothing else
    that writes to stdout meanwhile (a progress bar's refresh thread) is affected.
    """
    import rome.ROME as rome_module

    messages: list[str] = []
    def collect(*args: object, **kwargs: object) -> None:
        messages.append(" ".join(str(a) for a in args))

    shadowed = rome_module.__dict__.get("print")  # set only while another capture is active
    rome_module.print = collect  # type: ignore[attr-defined]
    try:
        yield messages
    finally:
        if shadowed is None:
            del rome_module.print  # type: ignore[attr-defined]
        else:
            rome_module.print = shadowed  # type: ignore[attr-defined]


def _run_batch(batch: list[tuple[int, RomeTask]],
               base_seed: int) -> list[tuple[int, tuple[tuple[np.ndarray, ...], int]]]:
    """Worker entry point (top level, so 'spawn' can import it): run a batch of (index, task) pairs."""
    return [(index, _fit_and_score(task, base_seed + index)) for index, task in batch]


#: Modules the forkserver imports once, so that forked workers start with ROME ready.
_PRELOAD = ["trajflow_pipeline.metrics.parallel", "rome.ROME", "threadpoolctl"]


def _pool_context() -> multiprocessing.context.BaseContext:
    """'forkserver' with ROME preloaded where available, else 'spawn' (never plain 'fork'; see module doc)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(_PRELOAD)
        return context
    return multiprocessing.get_context("spawn")


def _saved(store: RomeCache | None, finished: list[Finished], quiet: bool) -> RomeCache | None:
    """Save finished fits in `store`; the cache only saves time, so when it cannot be written the fits go on without
    it (said once) rather than the evaluation ending. Returns the store to use from now on."""
    if store is None or not finished:
        return store
    try:
        store.save(finished)
    except OSError as error:
        if not quiet:
            console.print(f"[yellow]warning:[/] cannot save ROME fits in {store.directory} ({error}); going on "
                          "without a cache, so an interruption would start the fits again")
        return None
    return store


def _batches(n_tasks: int, workers: int) -> list[range]:
    """Split task indices into contiguous batches: ~8 per worker amortises IPC and keeps the bar moving."""
    n_batches = min(n_tasks, workers * 8)
    bounds = np.linspace(0, n_tasks, n_batches + 1).round().astype(int)
    return [range(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]


def run_rome_tasks(tasks: Sequence[RomeTask], *, workers: int | None = None, quiet: bool = False,
                   description: str = "ROME density fits", base_seed: int = 0,
                   fallbacks: RomeTally | None = None, cache: Path | None = None) -> list[tuple[np.ndarray, ...]]:
    """Run independent ROME tasks and return, in task order, each task's tuple of log-density arrays.

    `workers` processes (default: all cores; 1 runs in this process, as does a single task) share the
    tasks; task `i` is seeded with `base_seed + i`, so the numbers are identical for any `workers`.
    A rich progress bar counts finished fits unless `quiet`, and a note says how many fits needed ROME's PCA
    fallback (see the module docstring) when any did; `fallbacks`, when given, adds this call's counts to it.
    With `cache` (a directory), finished fits are saved as they come and a rerun over the same tasks fits only
    those not saved yet (see :mod:`trajflow_pipeline.metrics.rome_cache`); the numbers are the same either way.
    """
    n_workers = resolve_workers(workers)
    n_tasks = len(tasks)
    results: list[tuple[np.ndarray, ...] | None] = [None] * n_tasks
    retries = np.zeros(n_tasks, dtype=np.int64)
    if n_tasks == 0:
        return []
    store = (RomeCache(cache, tasks, base_seed, patched=romepy_audited())
             if cache is not None else None)
    for index, (values, retried) in (store.load() if store is not None else {}).items():
        results[index], retries[index] = values, retried
    todo = [index for index, result in enumerate(results) if result is None]
    resumed = n_tasks - len(todo)
    if resumed and not quiet:
        console.print(f"[dim]{description}: {resumed} of {n_tasks} fits resumed from {store.directory}[/]")
    progress = make_progress(quiet)
    with progress:
        bar = progress.add_task(description, total=n_tasks, completed=resumed)
        if n_workers == 1 or len(todo) <= 1:
            pending: list[Finished] = []
            try:
                for index in todo:
                    finished = _fit_and_score(tasks[index], base_seed + index)
                    results[index], retries[index] = finished
                    pending.append((index, finished))
                    if len(pending) >= CACHE_EVERY:
                        store, pending = _saved(store, pending, quiet), []
                    progress.advance(bar)
            finally:  # what was fitted before an interruption is kept too
                store = _saved(store, pending, quiet)
        else:
            batches = [[todo[i] for i in batch] for batch in _batches(len(todo), n_workers)]
            with ProcessPoolExecutor(max_workers=min(n_workers, len(batches)), mp_context=_pool_context()) as pool:
                futures = [pool.submit(_run_batch, [(i, tasks[i]) for i in batch], base_seed) for batch in batches]
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
        console.print(f"[dim]note: {this_call.note()}[/]")
    return results  # type: ignore[return-value]
