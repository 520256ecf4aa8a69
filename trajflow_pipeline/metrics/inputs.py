"""Validation of metric inputs and grouping helpers shared by the displacement and density metrics.

Conventions (metres, any frame common to `pred` and `gt`):
  pred: (A, S, T, 2) — S drawn sample trajectories for each of A predicted agents;
  gt:   (A, T, 2)    — the ground-truth future of each agent;
  keys: (A,) integers — `joint_key` (agents predicted together: same scene and t0) or `group_id`
        (problems with identical inputs).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from trajflow_pipeline.errors import DataError, UsageError


def check_trajectories(pred: np.ndarray, gt: np.ndarray, t_eval: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and values and return float64 copies cut to the first `t_eval` steps.

    `t_eval` (None: all T steps) evaluates a shorter horizon than predicted, e.g. the trained horizon when
    the model predicts further (rounD: trained on 25 steps, predicted up to 35).
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.ndim != 4 or pred.shape[-1] != 2:
        raise UsageError(f"pred must have shape (agents, samples, steps, 2); got {pred.shape}")
    if gt.ndim != 3 or gt.shape[-1] != 2:
        raise UsageError(f"gt must have shape (agents, steps, 2); got {gt.shape}")
    n_agents, n_samples, n_steps, _ = pred.shape
    if gt.shape[0] != n_agents or gt.shape[1] != n_steps:
        raise UsageError(f"pred {pred.shape} and gt {gt.shape} disagree on agents or steps")
    if n_agents == 0 or n_samples == 0 or n_steps == 0:
        raise UsageError(f"nothing to evaluate: pred has shape {pred.shape}")
    if t_eval is not None:
        if isinstance(t_eval, bool) or not isinstance(t_eval, (int, np.integer)) or not 1 <= t_eval <= n_steps:
            raise UsageError(f"t_eval must be an integer in [1, {n_steps}] (the predicted steps); got {t_eval!r}")
        pred = pred[:, :, :t_eval]
        gt = gt[:, :t_eval]
    pred = np.array(pred, dtype=np.float64)
    gt = np.array(gt, dtype=np.float64)
    bad_pred = ~np.isfinite(pred).all(axis=(1, 2, 3))
    bad_gt = ~np.isfinite(gt).all(axis=(1, 2))
    if bad_pred.any() or bad_gt.any():
        which = np.flatnonzero(bad_pred | bad_gt)
        raise DataError(f"non-finite positions (NaN / inf) in the evaluated steps of agents {which[:10].tolist()}"
                        + (" ..." if which.size > 10 else ""))
    return pred, gt


class Groups(NamedTuple):
    """Agents grouped by an integer key: group `g` has key `keys[g]` and members `members[g]` (agent indices)."""

    keys: np.ndarray      # (G,) the distinct key values, ascending
    inverse: np.ndarray   # (A,) group index of each agent
    counts: np.ndarray    # (G,) agents per group
    members: list[np.ndarray]  # G arrays of agent indices, ascending


def group_agents(key: np.ndarray | None, n_agents: int, name: str) -> Groups:
    """Group agents by `key` (shape (A,), integers); None puts every agent in its own group."""
    if key is None:
        key_arr = np.arange(n_agents, dtype=np.int64)
    else:
        key_arr = np.asarray(key)
        if key_arr.shape != (n_agents,):
            raise UsageError(f"{name} must have shape ({n_agents},) (one key per agent); got {key_arr.shape}")
        if not np.issubdtype(key_arr.dtype, np.integer):
            raise UsageError(f"{name} must hold integers; got dtype {key_arr.dtype}")
        key_arr = key_arr.astype(np.int64)
    keys, inverse, counts = np.unique(key_arr, return_inverse=True, return_counts=True)
    order = np.argsort(inverse, kind="stable")
    members = np.split(order, np.cumsum(counts)[:-1])
    return Groups(keys=keys, inverse=inverse, counts=counts, members=members)


def flatten_futures(traj: np.ndarray) -> np.ndarray:
    """Flatten trajectories (..., T, 2) to vectors (..., T*2) in the order x0, y0, x1, y1, ... (ROME input)."""
    return traj.reshape(*traj.shape[:-2], traj.shape[-2] * 2)
