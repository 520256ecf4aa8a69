"""NLL (indep and joint) and JSD from ROME density estimates of drawn samples (paper section IV-B).

All densities are over flattened future positions in metres, x0, y0, x1, y1, ... of the first `t_eval`
steps (dimension 2T per agent; 2T per agent times the number of agents for a joint density), and all logs
are natural, so NLL is in nats of that 2T- (or 2nT-) dimensional density.

How each number is made (matching the reference benchmarking framework of Schumann et al. in numbers):
  * NLL indep, agent a: -log P_a(gt_a), P_a a ROME density of the predicted samples for a's input.
    Without `group_id` (or with `pool_groups=False`) P_a is fitted on agent a's own S samples. With
    `group_id`, the agents of a group share their input, so the model's predictive distribution is the same
    for all of them and P is fitted on the group's pooled predictions (a better estimate of the same
    density) — this is what the reference does; for groups of one agent both are the same fit.
    The aggregate is the mean over agents.
  * NLL joint, group G of `joint_key`: -log P_G(gt_G), P_G a ROME density fitted on the S joint samples
    (the agents' draws concatenated in ascending agent order: dimension n_G * 2T); the aggregate is the mean
    over groups. For a group of one agent the joint density is the indep one, so its value is reused
    (no second fit). Joint groups are not pooled across identical inputs.
  * JSD, group g of `group_id` with >= 2 agents: Q = ROME on the group's ground-truth futures (the set of
    gts is the ground-truth distribution), P = the group's pooled predicted density (as for NLL), and the
    Monte-Carlo estimator of `divergence.jsd_from_log_densities` on the gts and the pooled predictions.
    Groups of one agent have no ground-truth distribution and get no JSD row; neither do groups whose
    ground truths are all the same (a point mass has no density; real data has them: ETH/UCY's hotel has
    standing pedestrians whose inputs and futures agree). `jsd_groups` says which groups get a row. The
    aggregate is the mean over groups.
  * Large pooled sets follow the reference's scheme: when a group pools more predictions than
    max(n_gt, 5 S, 2500), they are shuffled (seeded) and split into chunks of that size, one ROME fit per
    chunk, and P is the average of the chunk densities (left-over points are scored but not fitted).
    `max_pooled` caps the pooled predictions per group (seeded random subset) to bound the cost; the
    default None uses all, like the reference.
  * ROME's log-densities are finite even far from every sample (its KDE works in log space), so no floor
    or clipping is applied to NLL, like the reference; a single far-off ground truth can therefore dominate
    an average, which is the metric's known behaviour, not an artefact.
  * Variable horizons (`horizon`, (A,): rounD scores each sample up to its own ``n_future_max``): a density is
    only defined over a fixed dimension, so agents are split by horizon h and every fit of an agent uses its
    own draws (and ground truth) truncated to its h steps (dimension 2h). Pooled identical-input densities
    (NLL, JSD) pool only the members that share h -- truncating the others' draws would also be valid, but
    one rule keeps each fit's dimension and meaning plain; their rows keep the group_id as key. A joint group
    is evaluated over its shortest member horizon (rounD's target / ego pairs share theirs, so this never
    truncates there). NLL values of different horizons are densities of different dimension (about 2h times
    a per-coordinate term); their mean is what the extended evaluation reports, and per-sample rows let a
    reader split it by horizon. All fits of all horizons run in one pool, seeded by their order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics.divergence import jsd_from_log_densities
from trajflow_pipeline.metrics.inputs import (Groups, check_trajectories, evaluated_horizon, flatten_futures,
                                              group_agents, group_minimum)
from trajflow_pipeline.metrics.parallel import RomeTally, RomeTask, run_rome_tasks
from trajflow_pipeline.metrics.rome import KDE_CHOICES, KDE_EXACT

#: Smallest chunk the reference uses for a pooled predicted density (points per ROME fit).
REFERENCE_MIN_CHUNK = 2500
#: The reference's chunk is also at least this many times the number of samples per agent.
REFERENCE_SAMPLES_FACTOR = 5


@dataclass
class DensityResults:
    """Per-agent and per-group density metrics; a field is None when that metric was not requested."""

    nll: np.ndarray | None = None                 # (A,) per agent
    nll_joint_keys: np.ndarray | None = None      # (G,) joint_key values, ascending
    nll_joint: np.ndarray | None = None           # (G,)
    jsd_keys: np.ndarray | None = None            # (H,) group_id values of the groups `jsd_groups` evaluates
    jsd: np.ndarray | None = None                 # (H,)
    jsd_agents: np.ndarray | None = None          # (H,) the lowest agent index of each JSD group


@dataclass
class _Plan:
    """ROME tasks to run and, for each quantity, the task indices whose results make it."""

    tasks: list[RomeTask] = field(default_factory=list)
    agent_fit: dict[int, int] = field(default_factory=dict)          # agent -> task (own samples)
    pooled_fits: dict[int, list[int]] = field(default_factory=dict)  # group -> chunk tasks
    pooled_mc: dict[int, np.ndarray] = field(default_factory=dict)   # group -> MC prediction points
    gt_fit: dict[int, int] = field(default_factory=dict)             # group -> task (ground truths)
    joint_fit: dict[int, int] = field(default_factory=dict)          # joint group -> task
    want_indep: bool = False  # per-agent NLL needed (for "nll" or singleton joint groups)
    pooled: bool = False      # per-agent densities come from identical-input groups' pooled fits
    kde: str = KDE_EXACT      # how every fit's density is computed (rome.KDE_CHOICES)

    def add(self, fit: np.ndarray, queries: tuple[np.ndarray, ...], label: str) -> int:
        """Append a task after checking that ROME can fit `fit`; return its index."""
        if fit.shape[0] < 2 or not np.ptp(fit, axis=0).max() > 0.0:
            raise DataError(f"cannot estimate a density for {label}: it needs at least 2 distinct samples, "
                            f"got {fit.shape[0]} sample(s), all identical")
        self.tasks.append(RomeTask(fit=fit, queries=queries, label=label, kde=self.kde))
        return len(self.tasks) - 1


def reference_chunk_size(n_gt: int, n_samples: int, n_pooled: int) -> int:
    """Points per ROME fit of a pooled predicted density in the reference: max(n_gt, 5 S, 2500), at most all."""
    return min(max(n_gt, REFERENCE_SAMPLES_FACTOR * n_samples, REFERENCE_MIN_CHUNK), n_pooled)


def _pooled_points(pred_flat: np.ndarray, members: np.ndarray, group_key: int, max_pooled: int | None,
                   seed: int) -> tuple[np.ndarray, np.random.Generator]:
    """The group's pooled predictions (n_members * S, D), subsampled to `max_pooled` with a group-seeded RNG."""
    points = pred_flat[members].reshape(-1, pred_flat.shape[-1])
    rng = np.random.default_rng([seed, int(group_key) % 2**64])
    if max_pooled is not None and points.shape[0] > max_pooled:
        points = points[np.sort(rng.permutation(points.shape[0])[:max_pooled])]
    return points, rng


def _plan_pooled(plan: _Plan, pred_flat: np.ndarray, gt_flat: np.ndarray, groups: Groups, g: int,
                 with_mc: bool, max_pooled: int | None, seed: int) -> None:
    """Tasks for group g's pooled predicted density: chunk fits scored at the gts (and MC points if `with_mc`)."""
    members, key = groups.members[g], groups.keys[g]
    points, rng = _pooled_points(pred_flat, members, key, max_pooled, seed)
    chunk = reference_chunk_size(members.size, pred_flat.shape[1], points.shape[0])
    n_chunks = points.shape[0] // chunk
    # One chunk holding every point: fit in data order; otherwise a seeded shuffle decides the chunks.
    whole = n_chunks == 1 and chunk == points.shape[0]
    order = np.arange(points.shape[0]) if whole else rng.permutation(points.shape[0])
    queries = (gt_flat[members], points) if with_mc else (gt_flat[members],)
    plan.pooled_fits[g] = [
        plan.add(points[order[i * chunk:(i + 1) * chunk]], queries,
                 f"predictions of group_id {key}" + (f" (chunk {i + 1}/{n_chunks})" if n_chunks > 1 else ""))
        for i in range(n_chunks)
    ]
    if with_mc:
        plan.pooled_mc[g] = points


def _chunk_mean(results: list[tuple[np.ndarray, ...]], indices: list[int], query: int) -> np.ndarray:
    """log of the mean over chunk fits of the density at query array `query` (log-mean-exp)."""
    stacked = np.stack([results[i][query] for i in indices])
    return logsumexp(stacked, axis=0) - np.log(len(indices))


def _check_options(metrics: set[str], max_pooled: int | None, seed: int) -> None:
    """UsageError for anything but {"nll", "nll_joint", "jsd"}, a max_pooled below 2, or a negative seed."""
    unknown = set(metrics) - {"nll", "nll_joint", "jsd"}
    if unknown:
        raise UsageError(f"not a density metric: {sorted(unknown)}; valid: nll, nll_joint, jsd")
    if max_pooled is not None and (isinstance(max_pooled, bool) or not isinstance(max_pooled, (int, np.integer))
                                   or max_pooled < 2):
        raise UsageError(f"max_pooled must be an integer >= 2 or None; got {max_pooled!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UsageError(f"seed must be a non-negative integer; got {seed!r}")


def jsd_groups(gt: np.ndarray, group_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which identical-input groups JSD can evaluate: (keys of groups with two or more different ground-truth
    futures, keys of groups with several futures that are all the same), for gt (A, T, 2) and group_id (A,).
    Groups of one future are in neither."""
    groups = group_agents(group_id, len(gt), "group_id")
    several = np.flatnonzero(groups.counts >= 2)
    spread = _has_spread(flatten_futures(np.asarray(gt, dtype=np.float64)), groups, several)
    return groups.keys[several[spread]], groups.keys[several[~spread]]


def _has_spread(gt_flat: np.ndarray, groups: Groups, which: np.ndarray) -> np.ndarray:
    """For groups `which`: whether their members' ground truths differ anywhere (one bool per group)."""
    if which.size == 0:
        return np.zeros(0, dtype=bool)
    order = np.concatenate([groups.members[g] for g in which])
    starts = np.concatenate([[0], np.cumsum(groups.counts[which])[:-1]])
    values = gt_flat[order]
    ptp = np.maximum.reduceat(values, starts, axis=0) - np.minimum.reduceat(values, starts, axis=0)
    return ptp.max(axis=1) > 0.0


def _build_plan(pred_flat: np.ndarray, gt_flat: np.ndarray, metrics: set[str], id_groups: Groups,
                joint_groups: Groups, pooled: bool, max_pooled: int | None, seed: int,
                agent_ids: np.ndarray | None = None, kde: str = KDE_EXACT) -> _Plan:
    """Every ROME fit the requested metrics need, each made once (see `density_metrics`); `agent_ids` are the
    agents' indices in the caller's arrays (for error messages; default: their row here)."""
    plan = _Plan(kde=kde)
    n_agents, n_samples = pred_flat.shape[:2]
    plan.want_indep = "nll" in metrics or ("nll_joint" in metrics and bool((joint_groups.counts == 1).any()))
    plan.pooled = pooled
    with_jsd: list[int] = []
    if "jsd" in metrics:
        several = np.flatnonzero(id_groups.counts >= 2)
        with_jsd = several[_has_spread(gt_flat, id_groups, several)].tolist()
    if plan.want_indep and not pooled:
        for a in range(n_agents):
            name = a if agent_ids is None else int(agent_ids[a])
            plan.agent_fit[a] = plan.add(pred_flat[a], (gt_flat[a:a + 1],), f"the samples of agent {name}")
    pooled_groups = set(with_jsd) | (set(range(id_groups.keys.size)) if plan.want_indep and pooled else set())
    for g in sorted(pooled_groups):
        _plan_pooled(plan, pred_flat, gt_flat, id_groups, g, g in with_jsd, max_pooled, seed)
    for g in with_jsd:
        members = id_groups.members[g]
        plan.gt_fit[g] = plan.add(gt_flat[members], (gt_flat[members], plan.pooled_mc[g]),
                                  f"the ground truths of group_id {id_groups.keys[g]}")
    if "nll_joint" in metrics:
        for j in np.flatnonzero(joint_groups.counts > 1):
            members = joint_groups.members[j]
            joint_samples = pred_flat[members].transpose(1, 0, 2).reshape(n_samples, -1)
            plan.joint_fit[int(j)] = plan.add(joint_samples, (gt_flat[members].reshape(1, -1),),
                                              f"the joint samples of joint_key {joint_groups.keys[j]}")
    return plan


def _log_p_at_gt(plan: _Plan, results: list[tuple[np.ndarray, ...]], id_groups: Groups, n_agents: int) -> np.ndarray:
    """log P_a(gt_a) for every agent, from its own fit or its group's pooled (chunk-averaged) fit."""
    if not plan.pooled:
        return np.array([results[plan.agent_fit[a]][0][0] for a in range(n_agents)])
    log_p = np.empty(n_agents)
    for g in range(id_groups.keys.size):
        log_p[id_groups.members[g]] = _chunk_mean(results, plan.pooled_fits[g], 0)
    return log_p


def _group_jsd(plan: _Plan, results: list[tuple[np.ndarray, ...]], g: int) -> float:
    """JSD of group g: Q (gt fit) and P (pooled prediction fits) at the group's gts and its MC predictions."""
    gt_fit = results[plan.gt_fit[g]]
    return jsd_from_log_densities(gt_fit[0], _chunk_mean(results, plan.pooled_fits[g], 0),
                                  gt_fit[1], _chunk_mean(results, plan.pooled_fits[g], 1))


@dataclass
class _Part:
    """Agents evaluated over one common number of steps, the metrics computed for them, and their fits."""

    agents: np.ndarray          # (n,) global agent indices, ascending
    metrics: set[str]
    plan: _Plan
    id_groups: Groups           # identical-input groups among `agents` (indices local to the part)
    joint_groups: Groups        # joint groups among `agents`
    offset: int = 0             # index of the part's first task in the combined task list


def _parts(pred: np.ndarray, gt: np.ndarray, metrics: set[str], joint_key: np.ndarray | None,
           group_id: np.ndarray | None, horizon: np.ndarray, pooled: bool, max_pooled: int | None,
           seed: int, kde: str) -> list[_Part]:
    """Split agents by evaluated steps (indep metrics: own horizon; nll_joint: its group's shortest) and plan
    each part's fits on draws and ground truths truncated to those steps."""
    n_agents = pred.shape[0]
    joint_h = group_minimum(horizon, group_agents(joint_key, n_agents, "joint_key"))
    if np.array_equal(joint_h, horizon):
        splits = [(horizon, set(metrics))]
    else:
        indep = set(metrics) - {"nll_joint"}
        splits = [(horizon, indep)] * bool(indep) + [(joint_h, {"nll_joint"})] * ("nll_joint" in metrics)
    parts: list[_Part] = []
    offset = 0
    for steps_of, wanted in splits:
        for steps in np.unique(steps_of):
            agents = np.flatnonzero(steps_of == steps)
            ids = group_agents(None if group_id is None else np.asarray(group_id)[agents], agents.size, "group_id")
            joint = group_agents(None if joint_key is None else np.asarray(joint_key)[agents], agents.size,
                                 "joint_key")
            every = agents.size == n_agents and steps == pred.shape[2]    # the common case: views, no copies
            sub_pred, sub_gt = (pred, gt) if every else (pred[agents, :, :steps], gt[agents, :steps])
            plan = _build_plan(flatten_futures(sub_pred), flatten_futures(sub_gt), wanted, ids, joint,
                               pooled=pooled, max_pooled=max_pooled, seed=seed, agent_ids=agents, kde=kde)
            parts.append(_Part(agents, wanted, plan, ids, joint, offset))
            offset += len(plan.tasks)
    return parts


def _assemble(part: _Part, results: list[tuple[np.ndarray, ...]]) -> DensityResults:
    """One part's metrics from its fits' results (indices local to the part, keys global)."""
    plan, id_groups, joint_groups, metrics = part.plan, part.id_groups, part.joint_groups, part.metrics
    out = DensityResults()
    log_p_gt = _log_p_at_gt(plan, results, id_groups, part.agents.size) if plan.want_indep else None
    if "nll" in metrics and log_p_gt is not None:
        out.nll = -log_p_gt
    if "nll_joint" in metrics:
        values = np.empty(joint_groups.keys.size)
        singles = np.flatnonzero(joint_groups.counts == 1)
        if singles.size and log_p_gt is not None:
            values[singles] = -log_p_gt[[joint_groups.members[j][0] for j in singles]]
        for j, task in plan.joint_fit.items():
            values[j] = -results[task][0][0]
        out.nll_joint_keys, out.nll_joint = joint_groups.keys, values
    if "jsd" in metrics:
        groups = sorted(plan.gt_fit)
        out.jsd_keys = id_groups.keys[groups].astype(np.int64)
        out.jsd = np.array([_group_jsd(plan, results, g) for g in groups], dtype=np.float64)
        out.jsd_agents = part.agents[[id_groups.members[g][0] for g in groups]].astype(np.int64)
    return out


def _merge(parts: list[_Part], results: list[DensityResults], metrics: set[str], n_agents: int) -> DensityResults:
    """The parts' results as one DensityResults over all agents (group rows ascending by key, then agent)."""
    out = DensityResults()
    if "nll" in metrics:
        out.nll = np.empty(n_agents)
        for part, result in zip(parts, results):
            if result.nll is not None:
                out.nll[part.agents] = result.nll
    if "nll_joint" in metrics:
        keys = np.concatenate([r.nll_joint_keys for r in results if r.nll_joint_keys is not None])
        values = np.concatenate([r.nll_joint for r in results if r.nll_joint is not None])
        order = np.argsort(keys, kind="stable")
        out.nll_joint_keys, out.nll_joint = keys[order], values[order]
    if "jsd" in metrics:
        done = [r for r in results if r.jsd_keys is not None]
        keys = np.concatenate([r.jsd_keys for r in done]).astype(np.int64)
        agents = np.concatenate([r.jsd_agents for r in done]).astype(np.int64)
        order = np.lexsort((agents, keys))
        out.jsd_keys, out.jsd_agents = keys[order], agents[order]
        out.jsd = np.concatenate([r.jsd for r in done])[order]
    return out


def density_metrics(pred: np.ndarray, gt: np.ndarray, *, metrics: set[str], joint_key: np.ndarray | None = None,
                    group_id: np.ndarray | None = None, pool_groups: bool = True, max_pooled: int | None = None,
                    t_eval: int | None = None, horizon: np.ndarray | None = None, workers: int | None = None,
                    quiet: bool = False, seed: int = 0, fallbacks: RomeTally | None = None,
                    cache: Path | None = None, kde: str = KDE_EXACT, ray: str | None = None) -> DensityResults:
    """Compute any of {"nll", "nll_joint", "jsd"} with one shared pool of ROME fits.

    Fits needed by several metrics are made once (the pooled predicted density serves NLL and JSD; a
    singleton joint group reuses the indep NLL). `horizon` (A,) scores each agent over its own first steps
    (see the module docstring). `seed` only drives the subsampling / chunking of large pooled sets and the
    per-task RNG seeds; results do not depend on `workers`. `fallbacks` tallies the fits that needed ROME's
    PCA fallback; `cache` keeps finished fits on disk so that an interrupted call resumes (see `run_rome_tasks`);
    `kde` is how the densities are computed (`rome.KDE_CHOICES`; docs/rome.md); with `ray` (a Ray address) the
    fits run on that cluster, with the same results.
    """
    _check_options(metrics, max_pooled, seed)
    if kde not in KDE_CHOICES:
        raise UsageError(f"unknown ROME KDE {kde!r}; valid: {', '.join(KDE_CHOICES)}")
    n_steps = np.shape(pred)[2] if np.ndim(pred) == 4 else 0
    pred, gt = check_trajectories(pred, gt, t_eval, horizon)
    n_agents = pred.shape[0]
    steps = evaluated_horizon(horizon, n_agents, n_steps, t_eval)
    for key, name in ((group_id, "group_id"), (joint_key, "joint_key")):
        group_agents(key, n_agents, name)  # validated before any fit
    parts = _parts(pred, gt, set(metrics), joint_key, group_id, steps,
                   pooled=pool_groups and group_id is not None, max_pooled=max_pooled, seed=seed, kde=kde)

    results = run_rome_tasks([task for part in parts for task in part.plan.tasks], workers=workers, quiet=quiet,
                             base_seed=seed, fallbacks=fallbacks, cache=cache, ray=ray)

    assembled = [_assemble(part, results[part.offset:part.offset + len(part.plan.tasks)]) for part in parts]
    return _merge(parts, assembled, set(metrics), n_agents)


def nll_indep(pred: np.ndarray, gt: np.ndarray, *, group_id: np.ndarray | None = None, pool_groups: bool = True,
              max_pooled: int | None = None, t_eval: int | None = None, horizon: np.ndarray | None = None,
              workers: int | None = None, quiet: bool = False, seed: int = 0) -> np.ndarray:
    """NLL of each agent's ground truth under the ROME density of its predictions, shape (A,) (see module doc)."""
    result = density_metrics(pred, gt, metrics={"nll"}, group_id=group_id, pool_groups=pool_groups,
                             max_pooled=max_pooled, t_eval=t_eval, horizon=horizon, workers=workers, quiet=quiet,
                             seed=seed)
    assert result.nll is not None
    return result.nll


def nll_joint(pred: np.ndarray, gt: np.ndarray, joint_key: np.ndarray | None, *, group_id: np.ndarray | None = None,
              pool_groups: bool = True, max_pooled: int | None = None, t_eval: int | None = None,
              horizon: np.ndarray | None = None, workers: int | None = None, quiet: bool = False,
              seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Joint NLL per group of `joint_key`: (group keys (G,), values (G,)) (see module doc)."""
    result = density_metrics(pred, gt, metrics={"nll_joint"}, joint_key=joint_key, group_id=group_id,
                             pool_groups=pool_groups, max_pooled=max_pooled, t_eval=t_eval, horizon=horizon,
                             workers=workers, quiet=quiet, seed=seed)
    assert result.nll_joint_keys is not None and result.nll_joint is not None
    return result.nll_joint_keys, result.nll_joint


def jsd(pred: np.ndarray, gt: np.ndarray, group_id: np.ndarray, *, max_pooled: int | None = None,
        t_eval: int | None = None, horizon: np.ndarray | None = None, workers: int | None = None,
        quiet: bool = False, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """JSD in [0, 1] per group of identical inputs with different ground truths (see `jsd_groups`):
    (group_id values (H,), values (H,))."""
    if group_id is None:
        raise UsageError("jsd needs group_id: the ground-truth distribution is the set of gts of a group")
    result = density_metrics(pred, gt, metrics={"jsd"}, group_id=group_id, max_pooled=max_pooled,
                             t_eval=t_eval, horizon=horizon, workers=workers, quiet=quiet, seed=seed)
    assert result.jsd_keys is not None and result.jsd is not None
    return result.jsd_keys, result.jsd
