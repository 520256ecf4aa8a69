"""ROME's choice among its candidate clusterings: the best noise-weighted silhouette, first one on ties."""

from __future__ import annotations

import numpy as np

from trajflow_pipeline.metrics.rome.candidates import unique_rows

#: ROME's score for a candidate it does not consider (a single label): below any silhouette
UNSCORED = -1.1
#: bytes of the per-candidate distance blocks scored at once (small enough to stay in cache)
SCORE_BLOCK_BYTES = 1 << 24
def distinct_rows(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For candidates (B, C, n): (first, inverse) with `first` the flat indices (b * C + c) of each distinct
    candidate of each set (first occurrence, ascending) and `inverse` (B, C) the position in `first` of each
    candidate's distinct twin. A candidate's set is part of its identity."""
    n_sets, n_candidates, n = labels.shape
    tagged = np.concatenate([np.repeat(np.arange(n_sets), n_candidates)[:, None], labels.reshape(-1, n)], axis=1)
    first, inverse = unique_rows(tagged, bound=max(n_sets, n))
    return first, inverse.reshape(n_sets, n_candidates)


def neighbour_ranks(distances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted (n, n), ranks (n, n)): each point's distances in ascending order and the rank of every point in its
    row's order, in the smallest unsigned type that holds n + 1 (`nearest_member` reads them)."""
    n = distances.shape[0]
    dtype = np.uint8 if n < 255 else np.uint16 if n < 65535 else np.uint32
    order = np.argsort(distances, axis=1)  # any order of tied distances gives the same nearest distance
    ranks = np.empty((n, n), dtype=dtype)
    np.put_along_axis(ranks, order, np.arange(n, dtype=dtype)[None, :], axis=1)
    return np.take_along_axis(distances, order, axis=1), ranks


def nearest_member(sorted_distances: np.ndarray, ranks: np.ndarray, members: np.ndarray) -> np.ndarray:
    """(U, n): each point's distance to its nearest point of each subset members (U, n) of one set, inf where a
    subset is empty: a minimum over small integer ranks (an eighth of the memory traffic of one over the
    distances), then one lookup, so the value is the distance itself."""
    n = members.shape[1]
    outside = np.where(members, 0, np.iinfo(ranks.dtype).max).astype(ranks.dtype)
    rank = np.maximum(ranks[None, :, :], outside[:, None, :]).min(axis=2)            # (U, n)
    found = rank < n
    value = sorted_distances[np.arange(n)[None, :], np.minimum(rank, n - 1)]
    return np.where(found, value, np.inf)


def _silhouette_pair(distances: np.ndarray, labels: np.ndarray, nearest_noise: np.ndarray) -> np.ndarray:
    """ROME's noise-weighted score of candidates (U, n) of one set with distances (n, n), given each point's
    distance to its nearest noise point (U, n): with noise as one cluster and with each noise point its own
    cluster, scikit-learn's silhouette_score of each, mixed by the noise fraction."""
    n_candidates, n = labels.shape
    n_buckets = int(labels.max()) + 2                                  # bucket 0 is the noise
    buckets = labels + 1
    member = buckets[None, :, :] == np.arange(n_buckets)[:, None, None]                   # (K, U, n)
    # each point's distance sums to each bucket (K, U, n): one matrix product (distances are symmetric)
    sums = (member.reshape(-1, n).astype(np.float64) @ distances).reshape(member.shape)
    sizes = member.sum(axis=2)                                                          # (K, U)
    own = np.take_along_axis(sums, buckets[None], axis=0)[0]                            # (U, n)
    own_size = sizes[buckets, np.arange(n_candidates)[:, None]]                         # (U, n)
    noise = labels == -1
    with np.errstate(divide="ignore", invalid="ignore"):
        intra = own / (own_size - 1)
        # mean distance to each other, non-empty bucket; inf for a point's own bucket and for empty ones
        means = np.where(member | (sizes == 0)[:, :, None], np.inf, sums / sizes[:, :, None])
        inter_combined = np.minimum.reduce(means, axis=0)
        inter_separate = np.minimum(np.minimum.reduce(means[1:], axis=0), nearest_noise)
        intra_separate = np.where(noise, np.nan, intra)
        scores = []
        for inter, intra_of in ((inter_separate, intra_separate), (inter_combined, intra)):
            samples = (inter - intra_of) / np.maximum(intra_of, inter)   # nan (0/0, inf/inf) counts as 0
            scores.append(np.where(np.isnan(samples), 0.0, samples).mean(axis=1))
    noise_fraction = noise.sum(axis=1) / n
    return noise_fraction * scores[0] + (1 - noise_fraction) * scores[1]


def best_clustering(candidates: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """(B, n): per set, ROME's chosen candidate among (B, C, n), scored with the sets' distances (B, n, n).

    Each distinct candidate is scored once, a set's candidates together (a few at a time for big sets, so that the
    rank arrays stay within SCORE_BLOCK_BYTES)."""
    n_sets, n_candidates, n = candidates.shape
    first, inverse = distinct_rows(candidates)
    flat = candidates.reshape(-1, n)[first]
    sets = first // n_candidates
    useful = flat.max(axis=1) > flat.min(axis=1)
    values = np.full(first.size, UNSCORED)
    scored = np.flatnonzero(useful)                                    # ascending, so grouped by set
    bounds = np.searchsorted(sets[scored], np.arange(n_sets + 1))
    step = max(1, SCORE_BLOCK_BYTES // (n * n))
    for b in range(n_sets):
        of_set = scored[bounds[b]:bounds[b + 1]]
        if of_set.size == 0:
            continue
        sorted_distances, ranks = neighbour_ranks(distances[b])
        for start in range(0, of_set.size, step):
            rows = of_set[start:start + step]
            labels = flat[rows]
            values[rows] = _silhouette_pair(distances[b], labels,
                                            nearest_member(sorted_distances, ranks, labels == -1))
    chosen = np.argmax(values[inverse], axis=1)
    return candidates[np.arange(n_sets), chosen]
