"""Shortcuts through the libraries a ROME fit runs on, each giving the same numbers as the library as it is.

A ROME fit of 100 draws of 12 steps (100 x 24 points) runs OPTICS once, extracts 199 candidate clusterings from
its ordering and scores every usable one by silhouette, then whitens and fits a KDE per cluster. Most of that time
goes to scikit-learn's per-call overhead, not to arithmetic. While :func:`shortcuts` is active:

* scikit-learn takes a numpy array for what it is instead of asking every installed dataframe library whether it
  is one of theirs (:func:`arrays_not_probed_as_dataframes`);
* OPTICS computes each point's distances to the unprocessed points without a neighbour query first
  (:func:`reachability_without_neighbour_queries`);
* ROME scores each distinct candidate once (:func:`distinct_candidates_scored_once`), with silhouettes computed
  directly from its distance matrix (:func:`silhouettes_computed_directly`).

Each is exact, argued in its docstring and tested against the library (tests/test_metrics_density.py);
bench/rome_shortcuts.py times whole fits both ways on real draws and checks every log-density. The ones that rest
on a library function's body apply only to the versions they were checked against; with any other version the
library runs as it is. The shortcuts replace module attributes for the duration of the block, so they are
process-wide: :mod:`trajflow_pipeline.metrics.parallel` holds a lock around each fit.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any

import numpy as np

#: romepy versions whose candidate selection (_silhouette_multiple_clusterings) was read and tested here.
AUDITED_ROMEPY = frozenset({"0.1.4"})
#: scikit-learn versions whose silhouette_score and OPTICS (_set_reach_dist) were read and mirrored here.
AUDITED_SKLEARN = frozenset({"1.9.1"})


@functools.cache
def installed_version(package: str) -> str | None:
    """The installed version of `package` (None when it is not installed)."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def romepy_audited() -> bool:
    """Whether the installed romepy is one the candidate-selection shortcut was checked against."""
    return installed_version("romepy") in AUDITED_ROMEPY


def sklearn_audited() -> bool:
    """Whether the installed scikit-learn is one the silhouette and OPTICS shortcuts were checked against."""
    return installed_version("scikit-learn") in AUDITED_SKLEARN


@contextlib.contextmanager
def _replaced(module: ModuleType, name: str, replacement: Callable[[Any], Any], applies: bool) -> Iterator[None]:
    """While active, ``module.name`` is ``replacement(original)`` where `applies` and the attribute exists, and the
    original again afterwards, however the block ends."""
    original = getattr(module, name, None)
    if original is None or not applies:
        yield
        return
    setattr(module, name, replacement(original))
    try:
        yield
    finally:
        setattr(module, name, original)


def distinct_candidates_scored_once() -> contextlib.AbstractContextManager[None]:
    """While active, ROME's choice among its candidate clusterings scores each distinct candidate only once.

    The candidates repeat: for 100 draws of 12 steps, ~45 of ~180 usable ones are distinct. ROME keeps the first
    candidate with the best score, and a repeated candidate scores exactly what its first occurrence did, so
    passing ROME's own selection function only the first occurrence of each distinct candidate, in their order,
    picks the same clustering bit for bit (tested against the unmodified library). The argument rests on that
    function's body, so only the romepy versions it was checked against are changed.
    """
    import rome.ROME as rome_module

    def among_distinct(select: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> Callable[..., np.ndarray]:
        def select_among_distinct(points: np.ndarray, clusterings: np.ndarray) -> np.ndarray:
            _, first = np.unique(clusterings, axis=1, return_index=True)
            return select(points, clusterings[:, np.sort(first)])
        return select_among_distinct

    return _replaced(rome_module, "_silhouette_multiple_clusterings", among_distinct, romepy_audited())


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


def silhouettes_computed_directly() -> contextlib.AbstractContextManager[None]:
    """While active, ROME's candidate scoring uses :func:`silhouette_precomputed` (same numbers, ~20x less time
    per call) instead of scikit-learn's ``silhouette_score``; only for the romepy and scikit-learn versions it was
    checked against."""
    import rome.ROME as rome_module

    return _replaced(rome_module, "silhouette_score", lambda library: _rome_silhouette,
                     romepy_audited() and sklearn_audited())


def arrays_not_probed_as_dataframes() -> contextlib.AbstractContextManager[None]:
    """While active, scikit-learn's input checks take a numpy array for what it is instead of asking every
    installed dataframe library whether it is one of theirs (about a quarter of a ROME fit's time, spent in
    ``inspect.getattr_static``). Other inputs are probed as before, so nothing else changes."""
    from sklearn.utils import validation

    def unless_array(probe: Callable[[object], bool]) -> Callable[[object], bool]:
        def probe_unless_array(x: object) -> bool:
            return False if type(x) is np.ndarray else probe(x)
        return probe_unless_array

    return _replaced(validation, "_nw_into_df_or_series", unless_array, True)


def reachability_without_neighbour_queries() -> contextlib.AbstractContextManager[None]:
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

    def direct(library: Callable[..., None]) -> Callable[..., None]:
        def set_reach_dist(core_distances_: np.ndarray, reachability_: np.ndarray, predecessor_: np.ndarray,
                           point_index: int, processed: np.ndarray, X: np.ndarray, nbrs: object, metric: object,
                           metric_params: dict | None, p: float, max_eps: float) -> None:
            if not (max_eps == np.inf and metric == "minkowski" and metric_params is None
                    and type(X) is np.ndarray and X.dtype == np.float64):
                return library(core_distances_=core_distances_, reachability_=reachability_,
                               predecessor_=predecessor_, point_index=point_index, processed=processed, X=X,
                               nbrs=nbrs, metric=metric, metric_params=metric_params, p=p, max_eps=max_eps)
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
        return set_reach_dist

    return _replaced(_optics, "_set_reach_dist", direct, sklearn_audited())


@contextlib.contextmanager
def shortcuts() -> Iterator[None]:
    """Every shortcut of this module at once; none changes a number."""
    with arrays_not_probed_as_dataframes(), distinct_candidates_scored_once(), silhouettes_computed_directly(), \
            reachability_without_neighbour_queries():
        yield
