"""Run independent ROME density fits across processes, with identical numbers for any worker count.

A ROME fit (OPTICS clustering, silhouette model selection over 199 candidate clusterings, per-cluster PCA
whitening, Gaussian KDE) is the slow part of evaluation. On 100 x 24 points of real draws it takes about 0.03 s
here, against 0.22 s for the library as it is (bench/rome_shortcuts.py, which checks that every log-density is
the same): scikit-learn's input validation is skipped, and so is its probing of numpy arrays for dataframes;
OPTICS updates reachabilities without a neighbour query per point; each distinct candidate clustering is scored
once, with silhouettes computed directly from ROME's distance matrix (:func:`silhouette_precomputed`). None of
these changes a number. Everything
else in `trajflow_pipeline.metrics` is vectorised numpy; the fits are the only per-task Python work, so this
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
import functools
import importlib.metadata
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
    # numbers unchanged); the shortcuts below (numbers unchanged too).
    with _ONE_FIT_AT_A_TIME, threadpool_limits(limits=1), \
            sklearn.config_context(assume_finite=True, skip_parameter_validation=True), _shortcuts(), \
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


#: romepy versions whose candidate selection (_silhouette_multiple_clusterings) was read and tested here.
_AUDITED_ROMEPY = frozenset({"0.1.4"})


@functools.cache
def _romepy_version() -> str | None:
    try:
        return importlib.metadata.version("romepy")
    except importlib.metadata.PackageNotFoundError:
        return None


@contextlib.contextmanager
def _distinct_candidates_scored_once() -> Iterator[None]:
    """While active, ROME's choice among its candidate clusterings scores each distinct candidate only once.

    A ROME fit extracts 199 candidate clusterings from one OPTICS ordering and scores every usable one by
    silhouette (two scikit-learn calls each), which is most of a fit. The candidates repeat: for 100 draws of
    12 steps, ~45 of ~180 usable ones are distinct. ROME keeps the first candidate with the best score, and a
    repeated candidate scores exactly what its first occurrence did, so passing ROME's own selection function only
    the first occurrence of each distinct candidate, in their order, picks the same clustering bit for bit
    (tested against the unmodified library). The argument rests on that function's body, so only the romepy
    versions it was checked against are changed; with any other the library runs as it is.
    """
    import rome.ROME as rome_module

    select = getattr(rome_module, "_silhouette_multiple_clusterings", None)
    if select is None or _romepy_version() not in _AUDITED_ROMEPY:
        yield
        return

    def select_among_distinct(points: np.ndarray, clusterings: np.ndarray) -> np.ndarray:
        _, first = np.unique(clusterings, axis=1, return_index=True)
        return select(points, clusterings[:, np.sort(first)])

    rome_module._silhouette_multiple_clusterings = select_among_distinct
    try:
        yield
    finally:
        rome_module._silhouette_multiple_clusterings = select


#: scikit-learn versions whose silhouette_score / silhouette_samples were read and mirrored by `silhouette_precomputed`.
_AUDITED_SKLEARN = frozenset({"1.9.1"})


@functools.cache
def _sklearn_version() -> str | None:
    try:
        return importlib.metadata.version("scikit-learn")
    except importlib.metadata.PackageNotFoundError:
        return None


def silhouette_precomputed(distances: np.ndarray, labels: np.ndarray) -> float:
    """The mean silhouette coefficient of 1-D integer `labels` (n,) over a dense float64 distance matrix (n, n)
    of finite, non-negative distances with a zero diagonal: scikit-learn's ``silhouette_score(distances, labels,
    metric="precomputed")``, bit for bit, for such inputs (the only ones ROME passes; other dtypes, shapes or
    invalid matrices are not checked here, and `_rome_silhouette` gives them to the library).

    ROME calls that function twice per candidate clustering (~190 times per fit), and most of its time there goes
    to validating the same 100 x 100 matrix again. This is the library's arithmetic in the library's order (per
    sample, the distances to each cluster summed in ascending sample order, as its per-row ``np.bincount`` does;
    one ``bincount`` over all rows sums each bucket in that same order) without the checks, which ROME's inputs
    pass by construction. Tested equal to the library on random and degenerate labelings.
    """
    labels = np.asarray(labels)
    encoded, n_labels = _encoded_labels(labels)
    n_samples = encoded.size
    if not 1 < n_labels < n_samples:
        raise ValueError(f"Number of labels is {n_labels}. Valid values are 2 to n_samples - 1 (inclusive)")
    freqs = np.bincount(encoded)
    buckets = (np.arange(n_samples)[:, None] * n_labels + encoded[None, :]).ravel()
    cluster_sums = np.bincount(buckets, weights=distances.ravel(), minlength=n_samples * n_labels)
    cluster_sums = cluster_sums.reshape(n_samples, n_labels)
    own = (np.arange(n_samples), encoded)
    intra = cluster_sums[own]
    cluster_sums[own] = np.inf
    cluster_sums /= freqs
    inter = cluster_sums.min(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        intra /= (freqs - 1).take(encoded, mode="clip")
        coefficients = inter - intra
        coefficients /= np.maximum(intra, inter)
    return float(np.mean(np.nan_to_num(coefficients)))


def _encoded_labels(labels: np.ndarray) -> tuple[np.ndarray, int]:
    """1-D labels as 0..k-1 in the order of their values (the codes scikit-learn's LabelEncoder gives, as int64)
    and k. ROME's int64 labels are nearly always every value from their minimum to their maximum, which needs no
    sort."""
    if labels.dtype == np.int64 and labels.ndim == 1 and labels.size:
        low, high = int(labels.min()), int(labels.max())
        if high - low < 2 * labels.size:  # a small range: no overflow, and a short bincount
            shifted = labels - low
            if np.bincount(shifted).all():
                return shifted, high - low + 1
    classes, encoded = np.unique(labels, return_inverse=True)
    return encoded.reshape(-1).astype(np.int64), classes.size


def _rome_silhouette(distances: np.ndarray, labels: np.ndarray, *, metric: str) -> float:
    """What ROME's module calls as ``silhouette_score``: the direct computation for ROME's input (precomputed
    float64 distances, 1-D integer labels), the library's function for anything else."""
    labels = np.asarray(labels)
    if (metric != "precomputed" or type(distances) is not np.ndarray or distances.dtype != np.float64
            or distances.ndim != 2 or labels.ndim != 1 or labels.dtype.kind not in "iu"):
        from sklearn.metrics import silhouette_score
        return silhouette_score(distances, labels, metric=metric)
    return silhouette_precomputed(distances, labels)


@contextlib.contextmanager
def _silhouettes_computed_directly() -> Iterator[None]:
    """While active, ROME's candidate scoring uses :func:`silhouette_precomputed` (same numbers, ~20x less time
    per call) instead of scikit-learn's ``silhouette_score``; only for the romepy and scikit-learn versions it was
    checked against (with any other the library runs as it is)."""
    import rome.ROME as rome_module

    library = getattr(rome_module, "silhouette_score", None)
    if library is None or _romepy_version() not in _AUDITED_ROMEPY or _sklearn_version() not in _AUDITED_SKLEARN:
        yield
        return
    rome_module.silhouette_score = _rome_silhouette
    try:
        yield
    finally:
        rome_module.silhouette_score = library


@contextlib.contextmanager
def _arrays_not_probed_as_dataframes() -> Iterator[None]:
    """While active, scikit-learn's input checks take a numpy array for what it is instead of asking every
    installed dataframe library whether it is one of theirs (about a quarter of a ROME fit's time, spent in
    ``inspect.getattr_static``). Other inputs are probed as before, so nothing else changes."""
    from sklearn.utils import validation

    probe = getattr(validation, "_nw_into_df_or_series", None)
    if probe is None:
        yield
        return

    def probe_unless_array(x: object) -> bool:
        return False if type(x) is np.ndarray else probe(x)

    validation._nw_into_df_or_series = probe_unless_array
    try:
        yield
    finally:
        validation._nw_into_df_or_series = probe


@contextlib.contextmanager
def _reachability_without_neighbour_queries() -> Iterator[None]:
    """While active, OPTICS (which ROME runs once per fit) updates reachabilities without a neighbour query per point.

    With no distance limit (``max_eps`` infinite, ROME's setting) the library's ``_set_reach_dist`` asks its
    neighbour index for every point within an infinite radius, i.e. all of them, keeps the unprocessed ones and
    computes their distances with ``pairwise_distances``, which for the Minkowski metric ends in scipy's ``cdist``:
    about half of a fit's time, most of it in the two wrappers. This makes the same ``cdist`` call on the
    unprocessed points directly (in ascending order rather than the index's; each distance is computed from its
    own pair alone) and then does the library's own update; each distance and therefore every reachability,
    predecessor and the ordering are the same (tested). Any other setting runs the library's code.
    """
    from scipy.spatial.distance import cdist
    from sklearn.cluster import _optics

    library = getattr(_optics, "_set_reach_dist", None)
    if library is None or _sklearn_version() not in _AUDITED_SKLEARN:
        yield
        return

    def set_reach_dist(core_distances_: np.ndarray, reachability_: np.ndarray, predecessor_: np.ndarray,
                       point_index: int, processed: np.ndarray, X: np.ndarray, nbrs: object, metric: object,
                       metric_params: dict | None, p: float, max_eps: float) -> None:
        if not (max_eps == np.inf and metric == "minkowski" and metric_params is None and type(X) is np.ndarray
                and X.dtype == np.float64):
            return library(core_distances_=core_distances_, reachability_=reachability_, predecessor_=predecessor_,
                           point_index=point_index, processed=processed, X=X, nbrs=nbrs, metric=metric,
                           metric_params=metric_params, p=p, max_eps=max_eps)
        unprocessed = np.flatnonzero(~processed)
        if not unprocessed.size:
            return None
        distances = cdist(X[point_index:point_index + 1], X[unprocessed], metric="minkowski", p=p).ravel()
        reach = np.maximum(distances, core_distances_[point_index])
        np.around(reach, decimals=np.finfo(reach.dtype).precision, out=reach)
        improved = np.where(reach < np.take(reachability_, unprocessed))
        reachability_[unprocessed[improved]] = reach[improved]
        predecessor_[unprocessed[improved]] = point_index
        return None

    _optics._set_reach_dist = set_reach_dist
    try:
        yield
    finally:
        _optics._set_reach_dist = library


@contextlib.contextmanager
def _shortcuts() -> Iterator[None]:
    """Every shortcut of this module at once; none changes a number (see each, and bench/rome_shortcuts.py)."""
    with _arrays_not_probed_as_dataframes(), _distinct_candidates_scored_once(), _silhouettes_computed_directly(), \
            _reachability_without_neighbour_queries():
        yield


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
    store = (RomeCache(cache, tasks, base_seed, patched=_romepy_version() in _AUDITED_ROMEPY)
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
