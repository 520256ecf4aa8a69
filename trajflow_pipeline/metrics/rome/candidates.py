"""ROME's 199 candidate clusterings per point set: 100 DBSCAN cuts and 99 Xi extractions of its OPTICS graph."""

from __future__ import annotations

import numpy as np

from trajflow_pipeline.metrics.rome.optics import OpticsGraph
from trajflow_pipeline.metrics.rome.xi import xi_plot_labels

#: ROME's DBSCAN cuts: squares of 100 even steps in [0, 1], scaled to the finite reachability range
EPS_STEPS = np.linspace(0, 1, 100) ** 2
#: ROME's Xi steepness values
XI_VALUES = np.linspace(0.01, 0.99, 99)
#: ROME asks Xi for clusters of at least this many points
MIN_CLUSTER_SIZE = 2
#: lanes (point sets x xi values) x points per Xi block (bounds its working memory; small enough to stay in cache)
XI_BLOCK = 1 << 19


def dbscan_plot_labels(graph: OpticsGraph) -> np.ndarray:
    """(B, 100, n) labels in plot order of ROME's DBSCAN cuts (scikit-learn's cluster_optics_dbscan)."""
    reach_plot = np.take_along_axis(graph.reachability, graph.ordering, axis=1)
    core_plot = np.take_along_axis(graph.core, graph.ordering, axis=1)
    finite = np.where(np.isfinite(graph.reachability), graph.reachability, np.nan)
    low, high = np.nanmin(finite, axis=1), np.nanmax(finite, axis=1)
    eps = EPS_STEPS[None, :] * (high - low)[:, None] + low[:, None]                 # (B, 100)
    far = reach_plot[:, None, :] > eps[:, :, None]
    near_core = core_plot[:, None, :] <= eps[:, :, None]
    labels = np.cumsum(far & near_core, axis=2) - 1
    labels[far & ~near_core] = -1
    return labels


def predecessor_positions(graph: OpticsGraph) -> np.ndarray:
    """(B, n): for each plot position, the plot position of its point's predecessor (-1 for none)."""
    n_sets, n = graph.ordering.shape
    position = np.empty_like(graph.ordering)
    np.put_along_axis(position, graph.ordering, np.broadcast_to(np.arange(n), (n_sets, n)), axis=1)
    predecessor = np.take_along_axis(graph.predecessor, graph.ordering, axis=1)
    return np.where(predecessor >= 0, np.take_along_axis(position, np.maximum(predecessor, 0), axis=1), -1)


def xi_labels_in_plot_order(graph: OpticsGraph) -> np.ndarray:
    """(B, 99, n) labels in plot order of ROME's Xi extractions, in blocks of point sets."""
    n_sets, n = graph.ordering.shape
    reach_plot = np.take_along_axis(graph.reachability, graph.ordering, axis=1)
    predecessor = predecessor_positions(graph)
    step = max(1, XI_BLOCK // (XI_VALUES.size * n))
    return np.concatenate([
        xi_plot_labels(reach_plot[s:s + step], predecessor[s:s + step], XI_VALUES, graph.min_samples,
                       MIN_CLUSTER_SIZE)
        for s in range(0, n_sets, step)], axis=0)


def unique_rows(rows: np.ndarray, bound: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(first, inverse) for integer rows (R, n): the index of each distinct row's first occurrence, ascending, and
    for every row the position of its distinct twin in `first`. Rows are packed into 64-bit words (as 16-bit
    integers when their values allow: `bound`, when given, is a known bound on their magnitude), grouped by a hash
    of the words and then compared word for word, so a hash collision only costs a repeated row, never a wrong one."""
    words = _packed_words(rows, bound)
    weights = np.random.default_rng(0).integers(0, np.iinfo(np.int64).max, size=words.shape[1], dtype=np.uint64)
    keys = (words * (weights | np.uint64(1))).sum(axis=1, dtype=np.uint64)  # unsigned arithmetic wraps around
    order = np.argsort(keys, kind="stable")
    ordered = words[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    group = np.cumsum(new) - 1
    first = order[new]
    by_position = np.argsort(first, kind="stable")
    rank = np.empty(first.size, dtype=np.int64)
    rank[by_position] = np.arange(first.size)
    inverse = np.empty(order.size, dtype=np.int64)
    inverse[order] = rank[group]
    return first[by_position], inverse


def _packed_words(rows: np.ndarray, bound: int | None) -> np.ndarray:
    """Integer rows (R, n) as (R, w) uint64 words holding the same values (int16 when they fit), zero padded."""
    limit = np.iinfo(np.int16).max
    small = rows.size == 0 or (bound <= limit if bound is not None else
                               rows.min() >= -limit and rows.max() <= limit)
    dtype = np.dtype(np.int16) if small else np.dtype(np.int64)
    per_word = 8 // dtype.itemsize
    packed = np.zeros((rows.shape[0], -(-rows.shape[1] // per_word) * per_word), dtype=dtype)
    packed[:, :rows.shape[1]] = rows
    return packed.view(np.uint64)


def tidy(labels: np.ndarray) -> np.ndarray:
    """ROME's clean-up of a candidate with more than one label: clusters of one point become noise (-1) and the
    others are renumbered 0, 1, ... in the order of their old labels; a candidate with a single label becomes
    all zeros. labels (..., n) with values in [-1, n); each distinct candidate is tidied once."""
    shape = labels.shape
    first, inverse = unique_rows(labels.reshape(-1, shape[-1]), bound=shape[-1])
    return _tidy_rows(labels.reshape(-1, shape[-1])[first])[inverse].reshape(shape)


def _tidy_rows(flat: np.ndarray) -> np.ndarray:
    """`tidy` of rows (R, n)."""
    rows, n = flat.shape
    buckets = flat + 1 + (n + 1) * np.arange(rows)[:, None]
    counts = np.bincount(buckets.ravel(), minlength=rows * (n + 1)).reshape(rows, n + 1)
    several = (counts > 0).sum(axis=1) > 1
    kept = counts >= 2
    kept[:, 0] = False
    renumbered = np.cumsum(kept, axis=1) - 1
    new = np.where(kept, renumbered, -1)
    out = np.take_along_axis(new, flat + 1, axis=1)
    out[~several] = 0
    return out


def candidate_clusterings(graph: OpticsGraph) -> np.ndarray:
    """(B, 199, n) int64: ROME's candidates in its order (100 DBSCAN cuts, then 99 Xi values), in point order."""
    plot_labels = np.concatenate([dbscan_plot_labels(graph), xi_labels_in_plot_order(graph)], axis=1)
    plot_labels = tidy(plot_labels)
    labels = np.empty_like(plot_labels)
    np.put_along_axis(labels, np.broadcast_to(graph.ordering[:, None, :], labels.shape), plot_labels, axis=2)
    return labels
