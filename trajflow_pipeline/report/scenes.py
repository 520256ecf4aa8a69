"""What the example and density figures show: which runs and samples, and their trajectories as numpy arrays.

Only the rows needed are read: predictions and ground truth are scanned lazily and filtered by sample or group
before they are collected, so a report over large evaluations stays cheap.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from ..errors import DataError
from ..rundir import GROUND_TRUTH_FILE, PREDICTIONS_FILE
from .collect import Run, collect, scan_ground_truth, scan_predictions
from .paper import model_order

#: How many predicted trajectories the density panel pools per model (the paper used 3000).
DENSITY_TRAJECTORIES = 3000


@dataclass(frozen=True)
class Panel:
    """One sample as one model's run saw it: past, every ground-truth future of its group, and the draws.

    Futures and draws start at the last observed position (step 0) so the lines join the past.
    """

    sample_id: int
    past: np.ndarray                 # (P, 2)
    futures: list[np.ndarray]        # each (F + 1, 2)
    draws: np.ndarray | None         # (D, H + 1, 2), None when the run has no predictions for the sample
    log_lik: np.ndarray | None       # (D,)


@dataclass(frozen=True)
class DensityData:
    """Point clouds of the density figure: the group's ground-truth futures and each model's draws (all steps)."""

    past: np.ndarray                           # (P, 2)
    ground_truth: np.ndarray                   # (N, 2)
    models: list[tuple[str, np.ndarray]]       # (model, (M, 2))
    group_id: int
    futures: int                               # ground-truth futures in the group


def reference_runs(runs: list[Run]) -> dict[str, Run]:
    """One run per model for the figures: the fold most models share (first in order), then the lowest seed."""
    by_model: dict[str, list[Run]] = {}
    for run in runs:
        by_model.setdefault(run.model, []).append(run)
    shared = Counter(fold for _, fold in {(r.model, r.fold) for r in runs})
    fold = min(shared, key=lambda f: (-shared[f], f is not None, f or ""))
    chosen = {}
    for model in model_order(list(by_model)):
        candidates = sorted(by_model[model], key=lambda r: (r.fold != fold, r.fold is not None, r.fold or "",
                                                            r.seed))
        chosen[model] = candidates[0]
    return chosen


def choose_examples(ground_truth: pl.DataFrame, count: int) -> list[int]:
    """Up to `count` sample ids spread evenly over the data; for multi-future data one per group."""
    if count <= 0 or ground_truth.is_empty():
        return []
    groups = ground_truth.group_by("group_id").agg(pl.col("sample_id").min().alias("first"),
                                                   pl.col("sample_id").n_unique().alias("futures"))
    multi = groups.filter(pl.col("futures") > 1)
    candidates = (multi.sort("group_id").get_column("first") if not multi.is_empty()
                  else ground_truth.get_column("sample_id").unique().sort()).to_numpy()
    picks = np.unique(np.linspace(0, candidates.size - 1, min(count, candidates.size)).round().astype(int))
    return candidates[picks].tolist()


def split_lines(frame: pl.DataFrame, key: str) -> list[np.ndarray]:
    """(n, 2) coordinate arrays, one per value of `key`, from a frame sorted by `key` then step."""
    if frame.is_empty():
        return []
    keys = frame.get_column(key).to_numpy()
    xy = frame.select("x", "y").to_numpy()
    return np.split(xy, np.flatnonzero(np.diff(keys)) + 1)


def _draw_array(predictions: pl.DataFrame, t0: np.ndarray, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(D, H + 1, 2) draws starting at t0 and their (D,) log-likelihoods, from one sample's sorted rows."""
    draws = predictions.get_column("draw").n_unique()
    if predictions.height % draws or predictions.group_by("draw").len().get_column("len").n_unique() != 1:
        raise DataError(f"sample {predictions['sample_id'][0]}: its draws have different numbers of steps", path)
    xy = predictions.select("x", "y").to_numpy().reshape(draws, -1, 2)
    start = np.broadcast_to(t0, (draws, 1, 2))
    log_lik = predictions.get_column("log_lik").to_numpy().reshape(draws, -1)[:, 0]
    return np.concatenate([start, xy], axis=1), log_lik


def example_panels(run: Run, sample_ids: list[int]) -> dict[int, Panel]:
    """The panels of `sample_ids` in `run` (samples the run did not evaluate are left out)."""
    gt_path, pred_path = run.eval_dir / GROUND_TRUTH_FILE, run.eval_dir / PREDICTIONS_FILE
    wanted = collect(scan_ground_truth(run).filter(pl.col("sample_id").is_in(sample_ids))
                     .select("sample_id", "group_id").unique(), gt_path)
    group_of = dict(wanted.iter_rows())
    gt = collect(scan_ground_truth(run).filter(pl.col("group_id").is_in(list(set(group_of.values()))))
                 .sort("sample_id", "step"), gt_path)
    predictions = collect(scan_predictions(run).filter(pl.col("sample_id").is_in(list(group_of)))
                          .sort("sample_id", "draw", "step"), pred_path)
    panels = {}
    for sample_id, group_id in group_of.items():
        own = gt.filter(pl.col("sample_id") == sample_id)
        past = own.filter(pl.col("step") <= 0).select("x", "y").to_numpy()
        futures = split_lines(gt.filter((pl.col("group_id") == group_id) & (pl.col("step") >= 0)), "sample_id")
        drawn = predictions.filter(pl.col("sample_id") == sample_id)
        draws, log_lik = (_draw_array(drawn, past[-1], pred_path) if not drawn.is_empty() and past.size
                          else (None, None))
        panels[sample_id] = Panel(sample_id, past, futures, draws, log_lik)
    return panels


def density_data(runs: dict[str, Run]) -> DensityData | None:
    """The largest group's ground-truth futures (from the first model's run) and each model's pooled draws.

    All samples of a group share their input, so draws for any of them come from the same predictive
    distribution; up to DENSITY_TRAJECTORIES of them are pooled, taking whole samples in id order.
    """
    first = next(iter(runs.values()))
    gt_path = first.eval_dir / GROUND_TRUTH_FILE
    sizes = collect(scan_ground_truth(first).group_by("group_id").agg(pl.col("sample_id").n_unique().alias("n"))
                    .sort("n", "group_id", descending=[True, False]).head(1), gt_path)
    if sizes.is_empty():
        return None
    group_id = int(sizes["group_id"][0])
    gt = collect(scan_ground_truth(first).filter(pl.col("group_id") == group_id).sort("sample_id", "step"), gt_path)
    sample_ids = gt.get_column("sample_id").unique().sort()
    past = gt.filter((pl.col("sample_id") == sample_ids[0]) & (pl.col("step") <= 0)).select("x", "y").to_numpy()
    truth = gt.filter(pl.col("step") >= 1).select("x", "y").to_numpy()
    models = []
    for model, run in runs.items():
        path = run.eval_dir / PREDICTIONS_FILE
        group = collect(scan_ground_truth(run).filter(pl.col("group_id") == group_id).select("sample_id").unique()
                        .sort("sample_id"), run.eval_dir / GROUND_TRUTH_FILE).get_column("sample_id")
        if group.is_empty():
            continue
        draws = collect(scan_predictions(run).filter(pl.col("sample_id") == group[0])
                        .select(pl.col("draw").n_unique()), path).item()
        if not draws:
            continue
        keep = group.head(max(1, DENSITY_TRAJECTORIES // draws)).to_list()
        points = collect(scan_predictions(run).filter(pl.col("sample_id").is_in(keep)).select("x", "y"), path)
        models.append((model, points.to_numpy()))
    return DensityData(past=past, ground_truth=truth, models=models, group_id=group_id,
                       futures=sample_ids.len())
