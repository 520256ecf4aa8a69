"""minADE_K / minFDE_K, per agent ("indep") and joint over agents predicted together (vectorised numpy).

Definitions (paper section IV-B; SPEC section 4): with the first K of the S drawn samples,
  indep:  minADE_K(a) = min_s mean_t |pred[a, s, t] - gt[a, t]|,  minFDE_K(a) = min_s |pred[a, s, T-1] - gt[a, T-1]|;
  joint:  for a group G of agents predicted together (same scene and t0) whose draws are aligned (draw s of
          every agent comes from the same joint sample), minADE_K(G) = min_s mean_{a in G} ADE(a, s), and
          likewise for FDE. A group of one agent has joint == indep.
The first K draws are used (not a random subset): draws are i.i.d., so this is an unbiased choice and it is
reproducible without an RNG.

Variable horizons (`horizon`, (A,): rounD scores each sample up to its own ``n_future_max``): ADE is the mean
over the agent's own valid steps and FDE the error at its last valid step; a joint group is evaluated over the
steps every member has ground truth for (its shortest horizon; rounD's target / ego pairs share theirs).
"""

from __future__ import annotations

import numpy as np

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.metrics.inputs import Groups, check_trajectories, group_agents, group_minimum, valid_steps

#: K of minADE_K / minFDE_K in the paper.
DEFAULT_K = 20


def _first_k(pred: np.ndarray, k: int) -> np.ndarray:
    """The first `k` draws of `pred` (A, S, T, 2); refuses k > S rather than silently using fewer."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise UsageError(f"k must be a positive integer; got {k!r}")
    if k > pred.shape[1]:
        raise UsageError(f"k={k} exceeds the {pred.shape[1]} drawn samples per agent; draw more samples or lower k")
    return pred[:, :k]


def displacement_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean error of every draw at every step: (A, S, T, 2) vs (A, T, 2) -> (A, S, T) metres."""
    return np.linalg.norm(pred - gt[:, None], axis=-1)


def ade_fde_per_draw(pred: np.ndarray, gt: np.ndarray, *, k: int = DEFAULT_K, t_eval: int | None = None,
                     horizon: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ADE and FDE of each of the first `k` draws of each agent: two (A, k) arrays over the first `t_eval` steps,
    or over each agent's own first `horizon[a]` steps (ADE: their mean; FDE: the last of them)."""
    pred, gt = check_trajectories(pred, gt, t_eval, horizon)
    err = displacement_errors(_first_k(pred, k), gt)
    if horizon is None:
        return err.mean(axis=-1), err[..., -1]
    h = np.minimum(np.asarray(horizon, dtype=np.int64), err.shape[-1])   # validated above; cut to t_eval
    ade = np.where(valid_steps(h, err.shape[-1])[:, None], err, 0.0).sum(axis=-1) / h[:, None]
    fde = np.take_along_axis(err, np.broadcast_to((h - 1)[:, None, None], (*err.shape[:2], 1)), axis=-1)[..., 0]
    return ade, fde


def min_ade(pred: np.ndarray, gt: np.ndarray, *, k: int = DEFAULT_K, t_eval: int | None = None,
            horizon: np.ndarray | None = None) -> np.ndarray:
    """minADE_K per agent, shape (A,)."""
    return ade_fde_per_draw(pred, gt, k=k, t_eval=t_eval, horizon=horizon)[0].min(axis=1)


def min_fde(pred: np.ndarray, gt: np.ndarray, *, k: int = DEFAULT_K, t_eval: int | None = None,
            horizon: np.ndarray | None = None) -> np.ndarray:
    """minFDE_K per agent, shape (A,)."""
    return ade_fde_per_draw(pred, gt, k=k, t_eval=t_eval, horizon=horizon)[1].min(axis=1)


def joint_horizon(horizon: np.ndarray | None, joint_key: np.ndarray | None, n_agents: int) -> np.ndarray | None:
    """Per agent, the shortest horizon of its joint group (None stays None: every agent has all steps)."""
    if horizon is None:
        return None
    return group_minimum(np.asarray(horizon), group_agents(joint_key, n_agents, "joint_key"))


def joint_min(per_draw: np.ndarray, groups: Groups) -> np.ndarray:
    """For each group, min over draws of the mean over the group's agents of `per_draw` (A, K) -> (G,)."""
    sums = np.zeros((groups.keys.size, per_draw.shape[1]))
    np.add.at(sums, groups.inverse, per_draw)
    return (sums / groups.counts[:, None]).min(axis=1)


def _joint_min_displacement(pred: np.ndarray, gt: np.ndarray, joint_key: np.ndarray | None, *, k: int,
                            t_eval: int | None, horizon: np.ndarray | None,
                            final: bool) -> tuple[np.ndarray, np.ndarray]:
    """Joint min over draws of the group-mean ADE (or FDE when `final`): (group keys (G,), values (G,))."""
    ade, fde = ade_fde_per_draw(pred, gt, k=k, t_eval=t_eval,
                                horizon=joint_horizon(horizon, joint_key, np.shape(pred)[0]))
    per_draw = fde if final else ade
    groups = group_agents(joint_key, per_draw.shape[0], "joint_key")
    return groups.keys, joint_min(per_draw, groups)


def min_ade_joint(pred: np.ndarray, gt: np.ndarray, joint_key: np.ndarray | None, *, k: int = DEFAULT_K,
                  t_eval: int | None = None, horizon: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Joint minADE_K per group of `joint_key`: returns (group keys (G,), values (G,)), keys ascending."""
    return _joint_min_displacement(pred, gt, joint_key, k=k, t_eval=t_eval, horizon=horizon, final=False)


def min_fde_joint(pred: np.ndarray, gt: np.ndarray, joint_key: np.ndarray | None, *, k: int = DEFAULT_K,
                  t_eval: int | None = None, horizon: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Joint minFDE_K per group of `joint_key`: returns (group keys (G,), values (G,)), keys ascending."""
    return _joint_min_displacement(pred, gt, joint_key, k=k, t_eval=t_eval, horizon=horizon, final=True)
