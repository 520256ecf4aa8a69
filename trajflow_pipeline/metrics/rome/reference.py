"""ROME's density given a clustering, through scikit-learn's public PCA and KernelDensity as the reference fits it.

scikit-learn's KD-tree evaluation of a KDE is exact near the points but, for clusters of more than 80 points,
loses precision far from them (docs/rome.md); fitting the same estimators on the same arrays keeps those numbers
identical to the reference's. One small fit per cluster, so this is the one per-fit loop of the estimator.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from trajflow_pipeline.metrics.rome.mixture import PCA_ATTEMPTS, add_jitter, repeated_rows



class ReferenceDensity:
    """ROME's fitted density of one point set (n, D) given its labels (n,), -1 for noise."""

    def __init__(self, points: np.ndarray, labels: np.ndarray, min_std: float) -> None:
        from sklearn.neighbors import KernelDensity

        n_features = points.shape[1]
        unique, sizes = np.unique(labels, return_counts=True)
        self.means = np.zeros((unique.size, n_features))
        self.transforms = np.zeros((unique.size, n_features, n_features))
        self.log_det = np.zeros(unique.size)
        self.models: list[KernelDensity] = []
        self.pca_retries = 0
        stds = np.zeros((unique.size, n_features))
        for i, label in enumerate(unique):
            if label == -1:
                self.models.append(None)  # type: ignore[arg-type]  # the noise model follows below
                continue
            members = points[labels == label]
            self.means[i] = members.mean(0)
            stds[i] = members.std(0)
            centred = members - self.means[[i]]
            self.models.append(KernelDensity(kernel="gaussian", bandwidth="silverman").fit(
                centred @ self._whitening(i, centred, min_std)))
        if unique[0] == -1:
            if unique.size > 1:
                noise_std = np.maximum(stds[1:].mean(0), min_std)
                self.transforms[0] = np.diag(1 / noise_std)
                self.log_det[0] = -np.sum(np.log(noise_std))
            else:
                self.transforms[0] = np.eye(n_features)
                self.log_det[0] = 0.0
            bandwidth = ((n_features + 2) / 4) ** (-1 / (n_features + 4))
            self.models[0] = KernelDensity(kernel="gaussian", bandwidth=bandwidth).fit(
                (points[labels == -1] - self.means[[0]]) @ self.transforms[0])
        self.log_weights = np.log(sizes / sizes.sum())

    def _whitening(self, i: int, centred: np.ndarray, min_std: float) -> np.ndarray:
        """Cluster i's rotation to principal axes scaled by ROME's floored stds (stored; also returned)."""
        from sklearn.decomposition import PCA

        data = repeated_rows(centred, centred.shape[1])
        for attempt in range(PCA_ATTEMPTS + 1):
            try:
                pca = PCA(random_state=attempt).fit(data)
                break
            except Exception:  # noqa: BLE001 - ROME retries whatever the PCA raised, with jitter
                if attempt == PCA_ATTEMPTS:
                    raise
                add_jitter(data, attempt)
                self.pca_retries += 1
        pca_std = np.sqrt(pca.explained_variance_)
        self.transforms[i] = pca.components_.T
        self.log_det[i] = np.log(np.abs(np.linalg.det(self.transforms[i])))
        pca_std = pca_std * (pca_std.max() - min_std) / pca_std.max() + min_std
        self.transforms[i] /= pca_std[np.newaxis]
        self.log_det[i] -= np.log(pca_std).sum()
        return self.transforms[i]

    def log_density(self, queries: np.ndarray) -> np.ndarray:
        """Natural-log density at each query point (m, D)."""
        per_cluster = np.stack([
            model.score_samples((queries - self.means[[i]]) @ self.transforms[i]) + self.log_det[i]
            + self.log_weights[i]
            for i, model in enumerate(self.models)], axis=1)
        return logsumexp(per_cluster, axis=-1)
