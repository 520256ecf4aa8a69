"""ROME, the TrajFlow paper's density estimator (Mészáros et al.), fitted to many same-shape point sets at once.

The reference code's clustering (romepy 0.1.4 on scikit-learn) bit for bit, and its density computed exactly
(or, as KDE_REFERENCE, through scikit-learn as romepy computes it): docs/rome.md describes the algorithm, where
each step matches the reference's arithmetic, and where the reference's own arithmetic is inexact.
"""

from __future__ import annotations

import numpy as np

from trajflow_pipeline.metrics.rome.candidates import candidate_clusterings
from trajflow_pipeline.metrics.rome.distances import distance_matrices
from trajflow_pipeline.metrics.rome.mixture import Mixture, fit_mixture
from trajflow_pipeline.metrics.rome.optics import optics_graph
from trajflow_pipeline.metrics.rome.selection import best_clustering

#: ROME's default minimum standard deviation (metres here); the reference framework uses the default too
DEFAULT_MIN_STD = 0.1
#: the density computed exactly, batched (the default)
KDE_EXACT = "exact"
#: each cluster's PCA and KDE fitted through scikit-learn as romepy fits them: romepy's numbers to the bit,
#: rounding residue of its KD-tree and its SVD included (docs/rome.md); needs scikit-learn
KDE_REFERENCE = "reference"
KDE_CHOICES = (KDE_EXACT, KDE_REFERENCE)
#: below this many points ROME does not cluster: all points form one cluster
MIN_POINTS_TO_CLUSTER = 5


def cluster(points: np.ndarray) -> np.ndarray:
    """ROME's clustering (B, n) of each of B point sets (B, n, D): -1 for noise, clusters 0, 1, ..."""
    n_sets, n, _ = points.shape
    if n < MIN_POINTS_TO_CLUSTER:
        return np.zeros((n_sets, n), dtype=np.int64)
    in_order, pairwise = distance_matrices(points)
    return best_clustering(candidate_clusterings(optics_graph(points, in_order)), pairwise)


def fit(points: np.ndarray, min_std: float | np.ndarray = DEFAULT_MIN_STD) -> Mixture:
    """ROME fitted to each of B point sets (B, n, D) of finite float64 coordinates (one `min_std` for all, or one
    per set); see Mixture.log_density."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 3:
        raise ValueError(f"points must be (sets, points, dimensions); got shape {points.shape}")
    return fit_mixture(points, cluster(points), min_std)
