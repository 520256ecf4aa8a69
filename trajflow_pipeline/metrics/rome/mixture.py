"""ROME's density given a clustering, computed exactly for a batch of point sets: per cluster a whitening (PCA with a
minimum std) and a Gaussian KDE, mixed by cluster size; noise points share one KDE on axis-scaled coordinates."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

#: most array elements one block of the density evaluation holds (query images x points x axes)
SCORE_BLOCK = 1 << 22
#: ROME re-runs a cluster's PCA with added jitter before this attempt, which runs unguarded
PCA_ATTEMPTS = 10


@dataclass(frozen=True)
class ClusterGroup:
    """The clusters of one size s (k of them, from any sets of a batch), each decomposed on exactly its own rows, so
    that a fit's numbers never depend on the other fits of its batch.

    Cluster i of set `sets[i]` holds the points `members[i]` (s,) and maps a point x to
    (x - means[i]) @ axes[i] * inverse_std[i] on its r = min(s, D) principal axes; every direction outside them has
    zero variance, whose floored std is min_std, so it adds |residual|^2 * null_inverse_std[i]^2 to a squared
    distance. `whitened` (k, s, r): the members' own images.
    """

    sets: np.ndarray
    members: np.ndarray
    means: np.ndarray
    axes: np.ndarray
    inverse_std: np.ndarray
    null_inverse_std: np.ndarray
    whitened: np.ndarray


@dataclass(frozen=True)
class Mixture:
    """Fitted densities of B point sets of n points in D dimensions each (docs/rome.md, "The density").

    `groups`: the clusters, by size (ClusterGroup). Per point (B, n): `cluster_of` its cluster (-1: noise),
    `offset` its kernel's log weight, Jacobian and normalisation together, `inverse_bandwidth`. Noise points are
    scaled per axis by `noise_scale` (B, D) (`noise_whitened`: all points so scaled). `pca_retries` (B,).
    """

    cluster_of: np.ndarray
    groups: tuple[ClusterGroup, ...]
    noise_scale: np.ndarray
    noise_whitened: np.ndarray
    offset: np.ndarray
    inverse_bandwidth: np.ndarray
    pca_retries: np.ndarray

    def log_density(self, queries: np.ndarray, sets: np.ndarray | None = None) -> np.ndarray:
        """Natural-log density (len(sets), m) of each of `sets` (ascending set indices; default all) at its own
        query points (len(sets), m, D)."""
        sets = np.arange(self.cluster_of.shape[0]) if sets is None else np.asarray(sets, dtype=np.int64)
        out = np.empty(queries.shape[:2])
        for rows, columns in _score_blocks(self, queries.shape[1], sets.size):
            out[rows, columns] = self._block(queries[rows, columns], sets[rows])
        return out

    def _block(self, queries: np.ndarray, sets: np.ndarray) -> np.ndarray:
        """Log-densities (b, m) of the b `sets` at their queries (b, m, D), in one pass."""
        cluster_of = self.cluster_of[sets]                                          # (b, n)
        squared = np.zeros(cluster_of.shape + queries.shape[1:2])                   # (b, n, m)
        for group in self.groups:
            chosen = np.flatnonzero(np.isin(group.sets, sets))
            if chosen.size == 0:
                continue
            rows = np.searchsorted(sets, group.sets[chosen])                        # each cluster's row in sets
            centred = queries[rows] - group.means[chosen][:, None, :]               # (k, m, D)
            axes = group.axes[chosen]
            projected = np.matmul(centred, axes)                                   # (k, m, r)
            residual = centred - np.matmul(projected, axes.transpose(0, 2, 1))
            null_part = np.einsum("kmd,kmd->km", residual, residual) * group.null_inverse_std[chosen, None] ** 2
            images = projected * group.inverse_std[chosen][:, None, :]
            difference = images[:, None, :, :] - group.whitened[chosen][:, :, None, :]      # (k, s, m, r)
            squared[rows[:, None], group.members[chosen]] = (np.einsum("ksmr,ksmr->ksm", difference, difference)
                                                             + null_part[:, None, :])
        noise = cluster_of < 0
        if noise.any():
            scaled = queries * self.noise_scale[sets][:, None, :]
            members = np.argsort(~noise, axis=1, kind="stable")[:, :int(noise.sum(axis=1).max())]
            difference = scaled[:, None, :, :] - np.take_along_axis(
                self.noise_whitened[sets], members[:, :, None], axis=1)[:, :, None, :]
            noise_squared = np.einsum("bzmd,bzmd->bzm", difference, difference)
            np.put_along_axis(squared, members[:, :, None],
                              np.where(np.take_along_axis(noise, members, axis=1)[:, :, None], noise_squared,
                                       np.take_along_axis(squared, members[:, :, None], axis=1)), axis=1)
        terms = (-0.5 * squared * (self.inverse_bandwidth[sets] ** 2)[:, :, None]
                 + self.offset[sets][:, :, None])
        return logsumexp(terms, axis=1)


def _score_blocks(mixture: Mixture, n_queries: int, n_sets: int) -> Iterator[tuple[slice, slice]]:
    """(sets, queries) slices whose evaluation holds at most about SCORE_BLOCK elements at once."""
    per_query = mixture.cluster_of.shape[1] * mixture.noise_scale.shape[1]   # points x D (each cluster's r <= D)
    queries_per_block = max(1, min(n_queries, SCORE_BLOCK // per_query))
    sets_per_block = max(1, SCORE_BLOCK // (per_query * max(1, n_queries))) if queries_per_block == n_queries else 1
    for s in range(0, n_sets, sets_per_block):
        for q in range(0, n_queries, queries_per_block):
            yield slice(s, s + sets_per_block), slice(q, q + queries_per_block)


def _principal_axes(centred: np.ndarray, sizes: np.ndarray, n_features: int) -> tuple[np.ndarray, np.ndarray,
                                                                                        np.ndarray]:
    """(variances (K, r) descending, axes (K, D, r) as columns, PCA retries (K,)) of K clusters given as zero-padded
    centred rows (K, w, D) with `sizes` real rows, r = min(w, D), as scikit-learn's PCA finds them for ROME.

    ROME repeats (tiles) a cluster with fewer points than dimensions until it has at least D rows; the tiles change
    no axis and scale the variances by repeats * (size - 1) / (rows - 1), so the untiled rows are decomposed. The
    axes of zero variance that tiling and the full decomposition would add all get the floored std, so they are left
    implicit (docs/rome.md). Covariance route for at least 10 D (tiled) rows, the SVD of the data otherwise, as
    scikit-learn chooses. A failed decomposition is re-run per cluster with ROME's jitter on the tiled rows.
    """
    repeats = np.where(sizes < n_features, -(-n_features // np.maximum(sizes, 1)), 1)
    rows = sizes * repeats
    try:
        variances, axes = _decompose(centred, repeats, rows, n_features)
        return variances, axes, np.zeros(sizes.size, dtype=np.int64)
    except np.linalg.LinAlgError:
        pass
    results = [_jittered_axes(centred[k, :sizes[k]], n_features) for k in range(sizes.size)]
    width = max(axes.shape[1] for _, axes, _ in results)
    variances = np.zeros((sizes.size, width))
    axes = np.zeros((sizes.size, n_features, width))  # zero columns: zero variance, like the implicit axes
    for k, (values, vectors, _) in enumerate(results):
        variances[k, :values.size], axes[k, :, :values.size] = values, vectors
    return variances, axes, np.array([retries for _, _, retries in results], dtype=np.int64)


def _decompose(centred: np.ndarray, repeats: np.ndarray, rows: np.ndarray,
               n_features: int) -> tuple[np.ndarray, np.ndarray]:
    """Variances and axes (see _principal_axes) of all clusters at once; LinAlgError when a decomposition fails."""
    n_clusters, width, _ = centred.shape
    rank = min(width, n_features)
    variances = np.zeros((n_clusters, rank))
    axes = np.zeros((n_clusters, n_features, rank))
    by_covariance = rows >= 10 * n_features
    if by_covariance.any():  # then width >= 10 D, so rank == D
        data = centred[by_covariance]
        gram = np.matmul(data.transpose(0, 2, 1), data) * repeats[by_covariance, None, None]
        gram /= (rows[by_covariance] - 1)[:, None, None]
        values, vectors = np.linalg.eigh(gram)
        variances[by_covariance] = np.maximum(values[:, ::-1], 0.0)
        axes[by_covariance] = vectors[:, :, ::-1]
    by_svd = ~by_covariance
    if by_svd.any():
        _, singular, vt = np.linalg.svd(centred[by_svd], full_matrices=False)
        variances[by_svd] = singular ** 2 * repeats[by_svd, None] / (rows[by_svd] - 1)[:, None]
        axes[by_svd] = vt.transpose(0, 2, 1)
    return variances, axes


def _jittered_axes(members: np.ndarray, n_features: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(variances, axes, retries) of one cluster's centred points by ROME's fallback: its tiled rows decomposed,
    re-run with jitter 10^(a/2 - 6) on the first D rows' diagonal before attempt a + 1 while the SVD fails."""
    data = repeated_rows(members, n_features)
    for attempt in range(PCA_ATTEMPTS + 1):
        try:
            _, singular, vt = np.linalg.svd(data - data.mean(axis=0), full_matrices=False)
            return singular ** 2 / (data.shape[0] - 1), vt.T, attempt
        except np.linalg.LinAlgError:
            if attempt == PCA_ATTEMPTS:
                raise
            add_jitter(data, attempt)
    raise AssertionError("unreachable")


def repeated_rows(members: np.ndarray, n_features: int) -> np.ndarray:
    """A cluster's rows (n, D) as ROME decomposes them: repeated until there are at least D of them (a copy)."""
    n_points = members.shape[0]
    return np.tile(members, (-(-n_features // n_points), 1)) if n_points < n_features else members.copy()


def add_jitter(data: np.ndarray, attempt: int) -> None:
    """ROME's jitter after failed PCA attempt `attempt`: 10^(attempt/2 - 6) on the diagonal of the first D rows."""
    n_features = data.shape[1]
    data[:n_features] += np.eye(n_features) * 10 ** (0.5 * attempt - 6)


def fit_mixture(points: np.ndarray, labels: np.ndarray, min_std: float | np.ndarray) -> Mixture:
    """ROME's density of each point set (B, n, D) given its chosen clustering (B, n), -1 for noise; `min_std` is
    one floor for all sets or one per set (B,)."""
    n_sets, n, n_features = points.shape
    min_std = np.broadcast_to(np.asarray(min_std, dtype=np.float64), (n_sets,))
    noise = labels == -1
    n_labels = max(int(labels.max()) + 1, 1)
    counts = np.zeros((n_sets, n_labels), dtype=np.int64)
    set_of_point = np.broadcast_to(np.arange(n_sets)[:, None], labels.shape)
    np.add.at(counts, (set_of_point[~noise], labels[~noise]), 1)
    cluster_set, cluster_label = np.nonzero(counts)                       # K clusters, ordered by set
    sizes = counts[cluster_set, cluster_label]
    index = np.full((n_sets, n_labels), -1)
    index[cluster_set, cluster_label] = np.arange(cluster_set.size)
    cluster_of = np.where(noise, -1, index[set_of_point, np.maximum(labels, 0)])

    # clusters grouped by size, each decomposed on exactly its own rows (no padding: batch-independent numbers)
    stds = np.zeros((sizes.size, n_features))
    cluster_log_det = np.zeros(sizes.size)
    retries = np.zeros(sizes.size, dtype=np.int64)
    groups = []
    for size in np.unique(sizes):
        chosen = np.flatnonzero(sizes == size)
        members = np.argsort(cluster_of[cluster_set[chosen]] != chosen[:, None], axis=1, kind="stable")[:, :size]
        block = points[cluster_set[chosen][:, None], members]                          # (k, s, D)
        means = block.mean(axis=1)
        centred = block - means[:, None, :]
        stds[chosen] = np.sqrt((centred ** 2).mean(axis=1))
        variances, axes, retries[chosen] = _principal_axes(centred, sizes[chosen], n_features)
        floor = min_std[cluster_set[chosen]]
        pca_std = np.sqrt(variances)
        top = pca_std.max(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            pca_std = pca_std * (top - floor[:, None]) / top + floor[:, None]
        implicit = n_features - pca_std.shape[1]                          # axes of zero variance left implicit
        cluster_log_det[chosen] = -np.log(pca_std).sum(axis=1) - implicit * np.log(floor)
        groups.append(ClusterGroup(sets=cluster_set[chosen], members=members, means=means, axes=axes,
                                   inverse_std=1.0 / pca_std, null_inverse_std=1.0 / floor,
                                   whitened=np.matmul(centred, axes) / pca_std[:, None, :]))

    n_clusters = np.bincount(cluster_set, minlength=n_sets)
    mean_std = np.zeros((n_sets, n_features))
    np.add.at(mean_std, cluster_set, stds)
    mean_std /= np.maximum(n_clusters, 1)[:, None]
    noise_std = np.where((n_clusters > 0)[:, None], np.maximum(mean_std, min_std[:, None]), 1.0)
    noise_log_det = np.where(n_clusters > 0, -np.log(noise_std).sum(axis=1), 0.0)

    n_noise = noise.sum(axis=1)
    own_size = np.where(noise, n_noise[:, None], sizes[np.maximum(cluster_of, 0)] if sizes.size else 1)
    log_det = np.where(noise, noise_log_det[:, None],
                       cluster_log_det[np.maximum(cluster_of, 0)] if sizes.size else 0.0)
    bandwidth = np.where(noise, ((n_features + 2) / 4) ** (-1 / (n_features + 4)),
                         (own_size * (n_features + 2) / 4) ** (-1 / (n_features + 4)))
    offset = (np.log(own_size / n) + log_det - np.log(own_size)
              - (0.5 * n_features * np.log(2 * np.pi) + n_features * np.log(bandwidth)))
    pca_retries = np.zeros(n_sets, dtype=np.int64)
    np.add.at(pca_retries, cluster_set, retries)
    return Mixture(cluster_of=cluster_of, groups=tuple(groups), noise_scale=1.0 / noise_std, noise_whitened=points * (1.0 / noise_std)[:, None, :], offset=offset,
                   inverse_bandwidth=1.0 / bandwidth, pca_retries=pca_retries)
