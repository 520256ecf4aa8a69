"""ROME's density given a clustering: per cluster a whitening (PCA with a minimum std) and a Gaussian KDE, mixed by
cluster size; noise points share one KDE on axis-scaled coordinates."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

#: query points x training points x features per block of the density evaluation
SCORE_BLOCK = 1 << 23


@dataclass(frozen=True)
class Mixture:
    """Fitted densities of B point sets (n points of dimension D each), with up to C clusters per set.

    slot (B, n): each point's cluster slot (slots in ascending label order; noise, when present, is slot 0);
    means (B, C, D) and transforms (B, C, D, D): a point x of slot c maps to (x - means[c]) @ transforms[c];
    whitened (B, n, D): the training points mapped by their own slot; offsets (B, C): each slot's log weight,
    log-determinant, KDE normalisation and 1 / n_c together; inverse_bandwidth (B, C); pca_retries (B,).
    """

    slot: np.ndarray
    means: np.ndarray
    transforms: np.ndarray
    whitened: np.ndarray
    offsets: np.ndarray
    inverse_bandwidth: np.ndarray
    pca_retries: np.ndarray

    def log_density(self, queries: np.ndarray) -> np.ndarray:
        """Natural-log density (B, m) of each set's density at its own queries (B, m, D)."""
        n_sets, m, n_features = queries.shape
        n = self.slot.shape[1]
        out = np.empty((n_sets, m))
        sets_per_block = max(1, SCORE_BLOCK // max(1, m * n * n_features))
        step_m = m if sets_per_block > 1 else max(1, SCORE_BLOCK // (n * n_features))
        for s in range(0, n_sets, sets_per_block):
            block = slice(s, s + sets_per_block)
            means, transforms, slot = self.means[block], self.transforms[block], self.slot[block]
            terms_const = np.take_along_axis(self.offsets[block], slot, axis=1)              # (b, n)
            scale = np.take_along_axis(self.inverse_bandwidth[block], slot, axis=1)          # (b, n)
            for q in range(0, m, step_m):
                centred = queries[block, None, q:q + step_m, :] - means[:, :, None, :]      # (b, C, mq, D)
                mapped = np.matmul(centred, transforms)                                      # (b, C, mq, D)
                own = np.take_along_axis(mapped, slot[:, :, None, None], axis=1)             # (b, n, mq, D)
                difference = own - self.whitened[block][:, :, None, :]
                squared = np.einsum("bnqd,bnqd->bqn", difference, difference)
                terms = -0.5 * squared * (scale ** 2)[:, None, :] + terms_const[:, None, :]
                out[block, q:q + step_m] = logsumexp(terms, axis=2)
        return out


def _principal_axes(centred: np.ndarray, sizes: np.ndarray, n_features: int) -> tuple[np.ndarray, np.ndarray]:
    """(variances (K, D) descending, axes (K, D, D) as columns) of clusters given as zero-padded centred rows
    (K, r, D) with `sizes` real rows, as scikit-learn's PCA finds them for ROME: clusters with fewer points than
    dimensions are repeated (tiled) until they have at least D rows; the covariance route for at least 10 D
    rows, the SVD of the data otherwise."""
    repeats = np.where(sizes < n_features, -(-n_features // np.maximum(sizes, 1)), 1)
    rows = sizes * repeats
    variances = np.empty((sizes.size, n_features))
    axes = np.empty((sizes.size, n_features, n_features))
    by_covariance = rows >= 10 * n_features
    if by_covariance.any():
        data = centred[by_covariance]
        gram = np.matmul(data.transpose(0, 2, 1), data) * repeats[by_covariance, None, None]
        gram /= (rows[by_covariance] - 1)[:, None, None]
        values, vectors = np.linalg.eigh(gram)
        values = values[:, ::-1]
        variances[by_covariance] = np.where(values < 0.0, 0.0, values)
        axes[by_covariance] = vectors[:, :, ::-1]
    by_svd = ~by_covariance
    if by_svd.any():
        data = centred[by_svd]
        if data.shape[1] < n_features:  # zero rows complete the basis; they change no singular value
            data = np.concatenate([data, np.zeros((data.shape[0], n_features - data.shape[1], n_features))], axis=1)
        _, singular, vt = np.linalg.svd(data, full_matrices=False)
        variances[by_svd] = singular ** 2 * repeats[by_svd, None] / (rows[by_svd] - 1)[:, None]
        axes[by_svd] = vt.transpose(0, 2, 1)
    return variances, axes


def fit_mixture(points: np.ndarray, labels: np.ndarray, min_std: float) -> Mixture:
    """ROME's density of each point set (B, n, D) given its chosen clustering (B, n), -1 for noise."""
    n_sets, n, n_features = points.shape
    noise = labels == -1
    has_noise = noise.any(axis=1)
    slot = labels + has_noise[:, None]                                  # noise -> 0, clusters after it
    n_slots = int(slot.max()) + 1
    one_hot = np.zeros((n_sets, n, n_slots))
    np.put_along_axis(one_hot, slot[:, :, None], 1.0, axis=2)
    sizes = one_hot.sum(axis=1)                                          # (B, C)
    present = sizes > 0
    cluster = present & ~(has_noise[:, None] & (np.arange(n_slots) == 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.matmul(one_hot.transpose(0, 2, 1), points) / sizes[:, :, None]
    means[~cluster] = 0.0
    centred = points - np.take_along_axis(means, slot[:, :, None], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        stds = np.sqrt(np.matmul(one_hot.transpose(0, 2, 1), centred ** 2) / sizes[:, :, None])

    transforms = np.zeros((n_sets, n_slots, n_features, n_features))
    log_det = np.zeros((n_sets, n_slots))
    sets, slots = np.nonzero(cluster)
    if sets.size:
        # each cluster's centred points, gathered to the front of a zero-padded block
        members = (slot[sets] == slots[:, None])                         # (K, n)
        order = np.argsort(~members, axis=1, kind="stable")
        counts = sizes[sets, slots].astype(np.int64)
        width = int(counts.max())
        block = np.take_along_axis(centred[sets], order[:, :width, None], axis=1)
        block[np.arange(width)[None, :] >= counts[:, None]] = 0.0
        variances, axes = _principal_axes(block, counts, n_features)
        pca_std = np.sqrt(variances)
        top = pca_std.max(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            pca_std = pca_std * (top - min_std) / top + min_std
        _, log_abs_det = np.linalg.slogdet(axes)
        transforms[sets, slots] = axes / pca_std[:, None, :]
        log_det[sets, slots] = log_abs_det - np.log(pca_std).sum(axis=1)
    if has_noise.any():
        n_clusters = cluster.sum(axis=1)
        with np.errstate(invalid="ignore"):
            mean_std = np.where(cluster[:, :, None], stds, 0.0).sum(axis=1) / np.maximum(n_clusters, 1)[:, None]
        noise_std = np.where((n_clusters > 0)[:, None], np.maximum(mean_std, min_std), 1.0)
        rows = np.flatnonzero(has_noise)
        transforms[rows, 0] = np.eye(n_features) / noise_std[rows, None, :]
        log_det[rows, 0] = np.where(n_clusters[rows] > 0, -np.log(noise_std[rows]).sum(axis=1), 0.0)
    bandwidth = np.where(cluster, (np.maximum(sizes, 1) * (n_features + 2) / 4) ** (-1 / (n_features + 4)),
                         ((n_features + 2) / 4) ** (-1 / (n_features + 4)))
    with np.errstate(divide="ignore", invalid="ignore"):
        offsets = (np.log(sizes / n) + log_det - np.log(sizes)
                   - (0.5 * n_features * np.log(2 * np.pi) + n_features * np.log(bandwidth)))
    offsets[~present] = -np.inf
    own_transform = transforms[np.arange(n_sets)[:, None], slot]                   # (B, n, D, D)
    own_mean = np.take_along_axis(means, slot[:, :, None], axis=1)
    whitened = np.matmul((points - own_mean)[:, :, None, :], own_transform)[:, :, 0, :]
    return Mixture(slot, means, transforms, whitened, offsets, 1.0 / bandwidth,
                   np.zeros(n_sets, dtype=np.int64))
