"""Metrics over each problem's own ground-truth horizon (`trajflow eval --extended-horizon`, the paper's rounD
protocol): every metric again with suffix ``_ext``, and ``_ext_long`` means over the problems that need more steps
than the trained horizon. Only the units a longer horizon can change are scored again."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import polars as pl

from .compute import METRIC_NAMES, SCHEMA, check_metric_names, compute_metrics, metric_rows
from .inputs import group_agents, group_minimum

if TYPE_CHECKING:
    import torch

#: suffix of the metrics scored over each sample's own ground-truth horizon (--extended-horizon)
EXTENDED_SUFFIX = "_ext"
#: further suffix of the extended metrics' means over only the samples that need more than n_future steps
LONG_SUFFIX = "_long"


class HorizonProblems(Protocol):
    """What the extended metrics read of the evaluated problems (trajflow_pipeline.data.Problems has it)."""

    n_future: int
    joint_id: np.ndarray
    extended_future: torch.Tensor | None

    @property
    def horizons(self) -> np.ndarray: ...


def extended_metrics(problems: HorizonProblems, trajectories: np.ndarray, standard: pl.DataFrame,
                      common: dict[str, Any]) -> pl.DataFrame:
    """Every metric over each problem's own ground-truth horizon, named with EXTENDED_SUFFIX, plus LONG_SUFFIX
    aggregates over the problems that need more than n_future steps.

    A unit (agent, joint group, identical-input group) whose fits see only n_future steps has by definition its
    standard value, so only the closure of the long problems under both groupings (`_recompute_set`) is scored
    again, by one compute_metrics call on that subset; every other unit reuses its standard row, and the
    aggregates are the means over all units, as compute_metrics makes them. Most rounD samples end at n_future,
    so this saves most of the second round of ROME fits. ROME seeds each fit by its order in a call, so a
    recomputed density value may differ slightly from a fit of the same unit in a call on all problems. When no
    problem is long, the standard rows are reused as they are (and no LONG rows).
    """
    own = problems.horizons
    if problems.extended_future is None or (own == problems.n_future).all():
        return standard.with_columns(pl.col("metric") + EXTENDED_SUFFIX)
    pred = trajectories[:, :, :int(own.max())]
    gt = problems.extended_future.double().numpy()
    redo = _recompute_set(own > problems.n_future, common["joint_key"], common["group_id"])
    if redo.all():
        table = compute_metrics(pred, gt, horizon=own, **common)
    else:
        table = _merge_units(standard, redo, _subset_units(pred, gt, own, np.flatnonzero(redo), common))
    return pl.concat([table.with_columns(pl.col("metric") + EXTENDED_SUFFIX),
                      _long_aggregates(table, own, problems.joint_id, problems.n_future)], how="vertical")


def _take(key: np.ndarray | None, agents: np.ndarray) -> np.ndarray | None:
    """The keys of `agents` (None stays None: every agent alone)."""
    return None if key is None else np.asarray(key)[agents]


def _recompute_set(long: np.ndarray, joint_key: np.ndarray | None, group_id: np.ndarray | None) -> np.ndarray:
    """(A,) bool: the long agents and, to a fixed point, every agent sharing a joint group or an identical-input
    group with one of them. Outside it, every fit (own, pooled, joint, JSD) sees only n_future steps."""
    indices = [group_agents(key, long.size, name).inverse.ravel()
               for key, name in ((joint_key, "joint_key"), (group_id, "group_id"))]
    redo = long.astype(bool)
    while True:
        grown = np.logical_or.reduce([np.bincount(index, weights=redo)[index] > 0 for index in indices])
        if np.array_equal(grown, redo):
            return redo
        redo = grown


def _subset_units(pred: np.ndarray, gt: np.ndarray, horizon: np.ndarray, agents: np.ndarray,
                  common: dict[str, Any]) -> pl.DataFrame:
    """The unit rows of one compute_metrics call on `agents` (each over its own horizon), agent_index mapped back
    to the full problem set; group_key values are the callers' own keys already."""
    subset = dict(common, joint_key=_take(common["joint_key"], agents), group_id=_take(common["group_id"], agents))
    if not _has_rows(subset, horizon[agents]):
        return pl.DataFrame(schema=SCHEMA)
    units = compute_metrics(pred[agents], gt[agents], horizon=horizon[agents], **subset).filter(~pl.col("aggregate"))
    return units.with_columns(agent_index=pl.Series(agents[units.get_column("agent_index").to_numpy()]))


def _has_rows(common: dict[str, Any], horizon: np.ndarray) -> bool:
    """False when compute_metrics would have nothing to report: only jsd asked for, and no identical-input group
    with two members of one horizon (JSD pools only members sharing their horizon)."""
    if set(check_metric_names(common["metrics"])) != {"jsd"}:
        return True
    ids = group_agents(common["group_id"], horizon.size, "group_id").inverse.ravel()
    return bool((np.unique(np.stack([ids, horizon]), axis=1, return_counts=True)[1] >= 2).any())


def _merge_units(standard: pl.DataFrame, redo: np.ndarray, recomputed: pl.DataFrame) -> pl.DataFrame:
    """The standard unit rows of the units outside `redo` with the `recomputed` unit rows (agent_index global), as
    compute_metrics orders them: per metric, units by (group_key, agent_index), then the aggregate (their mean).
    A group row's agent_index is its first member, and a group lies wholly inside or outside `redo`."""
    units = standard.filter(~pl.col("aggregate"))
    kept = units.filter(pl.Series(~redo[units.get_column("agent_index").to_numpy()]))
    merged = pl.concat([kept, recomputed], how="vertical")
    frames = []
    for metric in METRIC_NAMES:
        rows = merged.filter(pl.col("metric") == metric).sort("group_key", "agent_index", maintain_order=True)
        keys = rows.get_column("group_key")
        frames.append(metric_rows(metric, rows.get_column("value").to_numpy(),
                                  rows.get_column("agent_index").to_numpy(),
                                  None if keys.is_null().all() else keys.to_numpy()))
    return pl.concat(frames, how="vertical")


def _long_aggregates(table: pl.DataFrame, horizon: np.ndarray, joint_id: np.ndarray, n_future: int) -> pl.DataFrame:
    """One aggregate row per metric (named + EXTENDED_SUFFIX + LONG_SUFFIX): the mean over the units (agents, or
    joint / identical-input groups) whose horizon exceeds n_future; a joint group's horizon is its shortest."""
    joint_h = group_minimum(horizon, group_agents(joint_id.astype(np.int64), len(horizon), "joint_key"))
    units = table.filter(~pl.col("aggregate"))
    agent = units.get_column("agent_index").to_numpy()
    steps = np.where(units.get_column("metric").str.ends_with("_joint").to_numpy(), joint_h[agent], horizon[agent])
    return (units.filter(pl.Series(steps > n_future))
            .group_by("metric", maintain_order=True).agg(pl.col("value").mean())
            .select((pl.col("metric") + EXTENDED_SUFFIX + LONG_SUFFIX).alias("metric"), "value",
                    pl.lit(None, dtype=pl.Int64).alias("agent_index"), pl.lit(None, dtype=pl.Int64).alias("group_key"),
                    pl.lit(True).alias("aggregate")))
