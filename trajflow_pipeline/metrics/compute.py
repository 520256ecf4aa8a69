"""The eval stage's single entry point: every requested metric as one long-format polars table.

Table columns (one row per evaluated unit plus one aggregate row per metric):
  metric       str      one of METRIC_NAMES
  value        float64
  agent_index  int64    the agent (row of pred / gt) for per-agent metrics; for group metrics (joint,
                        JSD) the group's first (lowest-index) agent, so a row maps back to a sample / scene;
                        null on aggregate rows
  group_key    int64    the joint_key (min_*_joint, nll_joint) or group_id (jsd) of a group row;
                        null on per-agent and aggregate rows
  aggregate    bool     True on the one summary row per metric: the mean over agents (min_ade, min_fde,
                        nll) or over groups (min_*_joint, nll_joint, jsd), as the paper averages
A metric with no unit to evaluate (JSD without any group of >= 2 agents) contributes no rows at all.

With `horizon` (A,), each agent is scored over its own first horizon[a] steps (rounD's extended evaluation);
see `metrics.displacement` and `metrics.density` for what that means per metric.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import polars as pl

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.metrics.density import density_metrics
from trajflow_pipeline.metrics.displacement import DEFAULT_K, ade_fde_per_draw, joint_horizon, joint_min
from trajflow_pipeline.metrics.inputs import Groups, check_trajectories, evaluated_horizon, group_agents
from trajflow_pipeline.metrics.parallel import RomeTally
from trajflow_pipeline.metrics.rome import KDE_EXACT

#: Every metric `compute_metrics` knows, in table order.
METRIC_NAMES: tuple[str, ...] = ("min_ade", "min_fde", "min_ade_joint", "min_fde_joint", "nll", "nll_joint", "jsd")

_DENSITY = frozenset({"nll", "nll_joint", "jsd"})

SCHEMA: dict[str, pl.DataType] = {"metric": pl.Utf8, "value": pl.Float64, "agent_index": pl.Int64,
                                  "group_key": pl.Int64, "aggregate": pl.Boolean}


def check_metric_names(metrics: Sequence[str]) -> tuple[str, ...]:
    """Validate requested metric names (UsageError listing the valid ones) and return them in table order."""
    if isinstance(metrics, str):
        metrics = (metrics,)
    unknown = [m for m in metrics if m not in METRIC_NAMES]
    if unknown:
        raise UsageError(f"unknown metric(s) {', '.join(map(repr, unknown))}; valid: {', '.join(METRIC_NAMES)}")
    if not metrics:
        raise UsageError(f"no metric requested; valid: {', '.join(METRIC_NAMES)}")
    return tuple(m for m in METRIC_NAMES if m in set(metrics))


def metric_rows(metric: str, values: np.ndarray, agent_index: np.ndarray,
                group_key: np.ndarray | None) -> pl.DataFrame:
    """Per-unit rows of one metric followed by its aggregate (mean) row."""
    n = values.size
    if n == 0:
        return pl.DataFrame(schema=SCHEMA)
    return pl.DataFrame({
        "metric": [metric] * (n + 1),
        "value": np.append(values.astype(np.float64), values.mean()),
        "agent_index": [*agent_index.astype(np.int64).tolist(), None],
        "group_key": [None] * (n + 1) if group_key is None else [*group_key.astype(np.int64).tolist(), None],
        "aggregate": [False] * n + [True],
    }, schema=SCHEMA)


def _first_members(groups: Groups, keys: np.ndarray) -> np.ndarray:
    """The lowest agent index of each group whose key is in `keys` (keys ascending, a subset of groups.keys)."""
    positions = np.searchsorted(groups.keys, keys)
    return np.array([groups.members[p][0] for p in positions], dtype=np.int64)


def compute_metrics(pred: np.ndarray, gt: np.ndarray, *, joint_key: np.ndarray | None = None,
                    group_id: np.ndarray | None = None, k: int = DEFAULT_K, t_eval: int | None = None,
                    horizon: np.ndarray | None = None, metrics: Sequence[str] = METRIC_NAMES,
                    pool_groups: bool = True, max_pooled: int | None = None, workers: int | None = None,
                    quiet: bool = False, seed: int = 0, fallbacks: RomeTally | None = None,
                    rome_cache: Path | None = None, rome_kde: str = KDE_EXACT,
                    ray: str | None = None) -> pl.DataFrame:
    """Evaluate `pred` (A, S, T, 2) against `gt` (A, T, 2) (metres) and return the long table described above.

    joint_key  (A,) int: agents predicted together (same scene and t0) — joint metrics; None: each agent alone
               (then joint == indep).
    group_id   (A,) int: problems with identical inputs — JSD, and the pooled predicted density for NLL
               (see `metrics.density`); None: each agent alone (no JSD rows).
    k          draws used by minADE / minFDE (the first k of the S).
    t_eval     evaluate the first t_eval steps only (None: all T).
    horizon    (A,) int: evaluate agent a over its first horizon[a] steps only (None: all); `gt` (and `pred`)
               may hold NaN after it. Joint metrics use each joint group's shortest horizon.
    pool_groups  False fits each agent's NLL density on its own samples even when group_id is given.
    max_pooled   cap on pooled predictions per identical-input group (None: all, as the reference).
    workers    processes for the ROME fits (None: all cores; 1: in this process); numbers do not depend on it.
    seed       drives only the subsampling / chunking of large pooled sets and the per-fit RNG seeds.
    fallbacks  tally of the ROME fits that needed ROME's PCA fallback (see `metrics.parallel`).
    rome_cache directory keeping finished ROME fits, so that an interrupted evaluation resumes (`metrics.rome_cache`).
    rome_kde   how ROME's densities are computed: "exact" (default) or "reference" (romepy's arithmetic; docs/rome.md).
    ray        a Ray address: the ROME fits run on that cluster (`metrics.parallel`); numbers do not depend on it.
    """
    wanted = check_metric_names(metrics)
    n_steps = np.shape(pred)[2] if np.ndim(pred) == 4 else 0
    pred, gt = check_trajectories(pred, gt, t_eval, horizon)  # validated once, cut to t_eval
    n_agents = pred.shape[0]
    steps = None if horizon is None else evaluated_horizon(horizon, n_agents, n_steps, t_eval)
    agents = np.arange(n_agents)
    joint = group_agents(joint_key, n_agents, "joint_key")
    ids = group_agents(group_id, n_agents, "group_id")
    frames: list[pl.DataFrame] = []
    if any(m in wanted for m in ("min_ade", "min_fde", "min_ade_joint", "min_fde_joint")):
        ade, fde = ade_fde_per_draw(pred, gt, k=k, horizon=steps)
        joint_steps = joint_horizon(steps, joint_key, n_agents)
        if steps is not None and not np.array_equal(joint_steps, steps):   # mixed within a joint group
            joint_ade, joint_fde = ade_fde_per_draw(pred, gt, k=k, horizon=joint_steps)
        else:
            joint_ade, joint_fde = ade, fde
        per_metric = {
            "min_ade": lambda: (ade.min(axis=1), agents, None),
            "min_fde": lambda: (fde.min(axis=1), agents, None),
            "min_ade_joint": lambda: (joint_min(joint_ade, joint), _first_members(joint, joint.keys), joint.keys),
            "min_fde_joint": lambda: (joint_min(joint_fde, joint), _first_members(joint, joint.keys), joint.keys),
        }
        frames += [metric_rows(m, *per_metric[m]()) for m in wanted if m in per_metric]
    density_wanted = {m for m in wanted if m in _DENSITY}
    if density_wanted:
        res = density_metrics(pred, gt, metrics=density_wanted, joint_key=joint_key, group_id=group_id,
                              horizon=steps, pool_groups=pool_groups, max_pooled=max_pooled, workers=workers,
                              quiet=quiet, seed=seed, fallbacks=fallbacks, cache=rome_cache, kde=rome_kde, ray=ray)
        if res.nll is not None:
            frames.append(metric_rows("nll", res.nll, agents, None))
        if res.nll_joint is not None and res.nll_joint_keys is not None:
            frames.append(metric_rows("nll_joint", res.nll_joint, _first_members(joint, res.nll_joint_keys),
                                res.nll_joint_keys))
        if res.jsd is not None and res.jsd_keys is not None:
            first = res.jsd_agents if res.jsd_agents is not None else _first_members(ids, res.jsd_keys)
            frames.append(metric_rows("jsd", res.jsd, first, res.jsd_keys))
    table = pl.concat(frames, how="vertical") if frames else pl.DataFrame(schema=SCHEMA)
    if table.height == 0:
        raise UsageError(f"nothing to report for metrics {list(wanted)}: jsd needs a group_id with groups of "
                         "at least 2 agents whose ground truths differ")
    return table
