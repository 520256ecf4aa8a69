"""Seeded fold and train / val assignment of whole units (moments, situations, scenes, groups), shared by the
Forking Paths, rounD and CSV ingests so that one seed gives one assignment everywhere."""

from __future__ import annotations

import math

import numpy as np
import polars as pl


def rounded_share(count: int, fraction: float) -> int:
    """Units validating: `fraction` of `count` rounded, at least one while two or more units exist (Forking Paths,
    CSV); none for a zero fraction."""
    return max(1, round(fraction * count)) if count >= 2 and fraction > 0 else 0


def ceiled_share(count: int, fraction: float) -> int:
    """Units validating: `fraction` of `count` rounded up (rounD)."""
    return math.ceil(fraction * count)


def fold_arrays(count: int, folds: int, n_val: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Per unit its fold (0..folds-1, balanced: a seeded permutation dealt round-robin) and whether it validates
    (`n_val` units of a second permutation of the same generator)."""
    rng = np.random.default_rng(seed)
    fold = np.empty(count, dtype=np.int64)
    fold[rng.permutation(count)] = np.arange(count) % folds
    is_val = np.zeros(count, dtype=bool)
    is_val[rng.permutation(count)[:n_val]] = True
    return fold, is_val


def assign_folds(moments: list[str], folds: int, val_fraction: float, seed: int) -> pl.DataFrame:
    """moment -> group_id (sorted order), fold ("0".."folds-1", seeded, balanced) and split (seeded val groups)."""
    n = len(moments)
    fold, val = fold_arrays(n, folds, rounded_share(n, val_fraction), seed)
    return pl.DataFrame({"moment": moments, "group_id": np.arange(n, dtype=np.int64),
                         "fold": [str(f) for f in fold], "split": np.where(val, "val", "train")})
