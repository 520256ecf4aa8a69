"""Validation of metric inputs and grouping helpers shared by the displacement and density metrics.

Conventions (metres, any frame common to `pred` and `gt`):
  pred: (A, S, T, 2) — S drawn sample trajectories for each of A predicted agents;
  gt:   (A, T, 2)    — the ground-truth future of each agent;
  keys: (A,) integers — `joint_key` (agents predicted together: same scene and t0) or `group_id`
        (problems with identical inputs);
  horizon: (A,) integers, optional — each agent's own number of ground-truth steps when they differ
        (rounD's ``n_future_max``); `gt` (and `pred`) may hold anything, e.g. NaN, after it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from trajflow_pipeline.errors import DataError, UsageError


def check_horizon(horizon: np.ndarray | None, n_agents: int, n_steps: int) -> np.ndarray | None:
    """Validate per-agent horizons: None, or (A,) integers in [1, n_steps]; returned as int64.

    A horizon says how many of an agent's first steps have ground truth (rounD: each sample's own
    ``n_future_max``); the metrics ignore the steps after it, whatever `gt` holds there (NaN is fine).
    """
    if horizon is None:
        return None
    h = np.asarray(horizon)
    if h.shape != (n_agents,):
        raise UsageError(f"horizon must have shape ({n_agents},) (one per agent); got {h.shape}")
    if not np.issubdtype(h.dtype, np.integer):
        raise UsageError(f"horizon must hold integers; got dtype {h.dtype}")
    if n_agents and (h.min() < 1 or h.max() > n_steps):
        raise UsageError(f"horizon must lie in [1, {n_steps}] (the predicted steps); got {h.min()}..{h.max()}")
    return h.astype(np.int64)


def valid_steps(horizon: np.ndarray, n_steps: int) -> np.ndarray:
    """(A, T) bool: True on the steps each agent has ground truth for (step index < its horizon)."""
    return np.arange(n_steps)[None, :] < np.asarray(horizon)[:, None]


def check_trajectories(pred: np.ndarray, gt: np.ndarray, t_eval: int | None = None,
                       horizon: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and values and return float64 copies cut to the first `t_eval` steps.

    `t_eval` (None: all T steps) evaluates a shorter horizon than predicted, e.g. the trained horizon when
    the model predicts further (rounD: trained on 25 steps, predicted up to 35). `horizon` (A,) is each
    agent's own number of valid steps (:func:`check_horizon`, then cut to `t_eval`): only those must be
    finite, and the copies hold NaN after them so that nothing downstream can use them by accident.
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
    h = check_horizon(horizon, n_agents, n_steps)
    if t_eval is not None:
        if isinstance(t_eval, bool) or not isinstance(t_eval, (int, np.integer)) or not 1 <= t_eval <= n_steps:
            raise UsageError(f"t_eval must be an integer in [1, {n_steps}] (the predicted steps); got {t_eval!r}")
        pred = pred[:, :, :t_eval]
        gt = gt[:, :t_eval]
    pred = np.array(pred, dtype=np.float64)
    gt = np.array(gt, dtype=np.float64)
    valid = np.ones(gt.shape[:2], dtype=bool) if h is None else valid_steps(h, gt.shape[1])
    if h is not None:
        gt[~valid] = np.nan
        pred[np.broadcast_to(~valid[:, None], pred.shape[:3])] = np.nan
    bad_pred = ~(np.isfinite(pred).all(axis=-1) | ~valid[:, None]).all(axis=(1, 2))
    bad_gt = ~(np.isfinite(gt).all(axis=-1) | ~valid).all(axis=1)
    if bad_pred.any() or bad_gt.any():
        which = np.flatnonzero(bad_pred | bad_gt)
        raise DataError(f"non-finite positions (NaN / inf) in the evaluated steps of agents {which[:10].tolist()}"
                        + (" ..." if which.size > 10 else ""))
    return pred, gt


def evaluated_horizon(horizon: np.ndarray | None, n_agents: int, n_steps: int,
                      t_eval: int | None = None) -> np.ndarray:
    """Each agent's evaluated steps (A,) int64: its horizon (all `n_steps` when None), cut to `t_eval`."""
    h = check_horizon(horizon, n_agents, n_steps)
    h = np.full(n_agents, n_steps, dtype=np.int64) if h is None else h
    return h if t_eval is None else np.minimum(h, t_eval)


def group_minimum(values: np.ndarray, groups: "Groups") -> np.ndarray:
    """Per agent (A,), the minimum of `values` (A,) over the agent's group (e.g. a joint group's common horizon)."""
    lowest = np.full(groups.keys.size, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(lowest, groups.inverse, values.astype(np.int64))
    return lowest[groups.inverse]


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
