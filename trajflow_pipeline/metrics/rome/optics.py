"""OPTICS orderings and reachabilities of many same-shape point sets at once, as scikit-learn's OPTICS computes them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas

#: decimals scikit-learn rounds core and reachability distances to (float64's precision)
ROUNDING = np.finfo(np.float64).precision
#: rows per block of scikit-learn's chunked nearest-neighbour search (its pairwise_dist_chunk_size)
NEIGHBOUR_CHUNK = 256
#: above this many features scikit-learn's neighbour search is brute force (squared-norm expansion), not a k-d tree
TREE_MAX_FEATURES = 15


@dataclass(frozen=True)
class OpticsGraph:
    """OPTICS of B point sets of n points: per set, the visiting order and, per point, its core distance,
    reachability (inf for the first point visited) and predecessor (-1 for none); all (B, n)."""

    ordering: np.ndarray
    core: np.ndarray
    reachability: np.ndarray
    predecessor: np.ndarray
    min_samples: int


def rome_min_samples(n_points: int, n_features: int) -> int:
    """ROME's OPTICS min_samples: n * D / 400 clipped to [min(5, n), min(20, n)]."""
    return int(np.clip(n_points * n_features / 400, min(5, n_points), min(20, n_points)))


def _expanded_core_distances(points: np.ndarray, k: int) -> np.ndarray:
    """Distance to the k-th nearest point (itself included) as scikit-learn's brute-force search finds it:
    sqrt(max(|x|^2 + (-2 x.y) + |y|^2, 0)), the middle term from the same BLAS dgemm call on the same
    256-row blocks, the norms from dot products. (B, n)."""
    n_sets, n, _ = points.shape
    norms = np.matmul(points[:, :, None, :], points[:, :, :, None])[:, :, 0, 0]
    squared = np.empty((n_sets, n, n))
    for b in range(n_sets):  # one BLAS call per set: bit-exact agreement needs this routine's own arithmetic
        for start in range(0, n, NEIGHBOUR_CHUNK):
            rows = points[b, start:start + NEIGHBOUR_CHUNK]
            for column in range(0, n, NEIGHBOUR_CHUNK):
                squared[b, start:start + NEIGHBOUR_CHUNK, column:column + NEIGHBOUR_CHUNK] = blas.dgemm(
                    -2.0, rows, points[b, column:column + NEIGHBOUR_CHUNK], trans_b=True)
    squared += norms[:, :, None]
    squared += norms[:, None, :]
    np.maximum(squared, 0.0, out=squared)
    return np.sqrt(np.partition(squared, k - 1, axis=2)[:, :, k - 1])


def core_distances(points: np.ndarray, distances: np.ndarray, k: int) -> np.ndarray:
    """Each point's distance to its k-th nearest point (itself included), computed as scikit-learn's nearest-
    neighbour search chooses to (k-d tree: exact distances; brute force: the squared-norm expansion), rounded."""
    n_points, n_features = points.shape[1:]
    brute = n_features > TREE_MAX_FEATURES or k >= n_points // 2
    if brute:
        core = _expanded_core_distances(points, k)
    else:
        core = np.partition(distances, k - 1, axis=2)[:, :, k - 1].copy()
    return np.around(core, decimals=ROUNDING, out=core)


def optics_graph(points: np.ndarray, distances: np.ndarray) -> OpticsGraph:
    """OPTICS (no distance limit, Euclidean, ROME's min_samples) of each of B point sets (B, n, D), given their
    distances as scipy's cdist sums them (`distances.distance_matrices`).

    The visiting loop runs once over the n positions for all sets together: the next point is the unvisited one
    with the smallest reachability (lowest index on ties, as scikit-learn), whose distances then lower the others'.
    """
    n_sets, n_points, n_features = points.shape
    k = rome_min_samples(n_points, n_features)
    core = core_distances(points, distances, k)
    reachability = np.full((n_sets, n_points), np.inf)
    predecessor = np.full((n_sets, n_points), -1, dtype=np.int64)
    visited = np.zeros((n_sets, n_points), dtype=bool)
    ordering = np.empty((n_sets, n_points), dtype=np.int64)
    sets = np.arange(n_sets)
    for position in range(n_points):
        point = np.where(visited, np.inf, reachability).argmin(axis=1)
        stale = visited[sets, point]  # every unvisited point is still at inf: take the lowest-index one
        if stale.any():
            point[stale] = (~visited[stale]).argmax(axis=1)
        visited[sets, point] = True
        ordering[:, position] = point
        reach = np.maximum(distances[sets, point], core[sets, point][:, None])
        np.around(reach, decimals=ROUNDING, out=reach)
        improved = ~visited & (reach < reachability)
        reachability[improved] = reach[improved]
        predecessor[improved] = np.broadcast_to(point[:, None], improved.shape)[improved]
    return OpticsGraph(ordering, core, reachability, predecessor, k)
