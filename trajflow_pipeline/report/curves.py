"""minADE as a function of K, from a run's predictions and ground truth.

Per (sample, draw) the ADE over the future steps both tables have (the trained horizon when a model predicted
further) is computed by a polars join + group-by (which streams large prediction files), then numpy gives,
for every K = 1..S, the *expected* minADE over a uniformly random K-subset of the S draws: with the per-sample
ADEs sorted ascending, a_(1) <= ... <= a_(S), the i-th smallest is the subset's minimum with probability
C(S - i, K - 1) / C(S, K), so the curve is a weighted sum of sorted ADEs. This uses every draw (smoother than
"the first K draws") and at K = S it is the plain minimum over all draws.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from scipy.special import gammaln

from ..errors import DataError


def ade_per_draw(predictions: pl.LazyFrame, ground_truth: pl.LazyFrame, path: Path) -> np.ndarray:
    """(N, S) ADE of every draw of every sample that has a ground-truth future (metres)."""
    future = ground_truth.filter(pl.col("step") >= 1).select("sample_id", "step", gx="x", gy="y")
    per_draw = (predictions.join(future, on=["sample_id", "step"], how="inner")
                .group_by("sample_id", "draw")
                .agg(((pl.col("x") - pl.col("gx")) ** 2 + (pl.col("y") - pl.col("gy")) ** 2).sqrt().mean()
                     .alias("ade"))
                .sort("sample_id", "draw"))
    try:
        table = per_draw.collect()
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable predictions ({error})", path) from None
    if table.is_empty():
        return np.zeros((0, 0))
    draws = table.group_by("sample_id").len().get_column("len")
    if draws.n_unique() != 1:
        raise DataError(f"samples have different numbers of draws ({draws.min()} to {draws.max()}); every "
                        "problem must have the same draws", path)
    return table.get_column("ade").to_numpy().reshape(-1, int(draws[0]))


def _log_comb(n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """log C(n, k), -inf where k > n or k < 0 (broadcasting)."""
    valid = (k >= 0) & (k <= n)
    n_, k_ = np.where(valid, n, 0), np.where(valid, k, 0)
    return np.where(valid, gammaln(n_ + 1) - gammaln(k_ + 1) - gammaln(n_ - k_ + 1), -np.inf)


def subset_min_weights(draws: int) -> np.ndarray:
    """(S, S) matrix W: W[K-1, i] = P(the (i+1)-th smallest of S values is the minimum of a random K-subset)."""
    i = np.arange(draws)[None, :]
    k = np.arange(1, draws + 1)[:, None]
    return np.exp(_log_comb(draws - 1 - i, k - 1) - _log_comb(np.full_like(k, draws), k))


def expected_min_curve(ade: np.ndarray) -> np.ndarray:
    """(S,) expected minADE_K for K = 1..S, averaged over samples, from (N, S) per-draw ADEs."""
    if ade.size == 0:
        return np.zeros(0)
    ordered = np.sort(ade, axis=1)
    return (ordered @ subset_min_weights(ade.shape[1]).T).mean(axis=0)


def min_ade_curve(predictions: pl.LazyFrame, ground_truth: pl.LazyFrame, path: Path) -> np.ndarray:
    """(S,) expected minADE_K, K = 1..S, of one run (empty when no sample has a future to compare with)."""
    return expected_min_curve(ade_per_draw(predictions, ground_truth, path))
