"""Metrics over per-agent horizons (rounD's extended evaluation): each agent is scored over its own valid steps."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics import compute_metrics, min_ade, min_ade_joint, min_fde, nll_indep, nll_joint


def _case(n_agents: int = 4, n_samples: int = 20, n_steps: int = 5, seed: int = 0):
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=(n_agents, n_steps, 2)).cumsum(axis=1)
    pred = gt[:, None] + rng.normal(scale=0.4, size=(n_agents, n_samples, n_steps, 2))
    return pred, gt


def _padded(gt: np.ndarray, horizon: np.ndarray) -> np.ndarray:
    """gt with NaN after each agent's horizon, as the extended loader delivers it."""
    out = gt.copy()
    out[np.arange(gt.shape[1])[None, :] >= horizon[:, None]] = np.nan
    return out


def test_ade_averages_own_steps_and_fde_takes_the_last_valid_one() -> None:
    gt = np.zeros((2, 4, 2))
    pred = np.zeros((2, 2, 4, 2))
    pred[:, 0, :, 0] = [1.0, 2.0, 3.0, 4.0]        # draw 0: error grows by 1 per step
    pred[:, 1, :, 0] = 10.0                         # draw 1: far off everywhere
    horizon = np.array([4, 2])
    np.testing.assert_allclose(min_ade(pred, _padded(gt, horizon), k=2, horizon=horizon), [2.5, 1.5])
    np.testing.assert_allclose(min_fde(pred, _padded(gt, horizon), k=2, horizon=horizon), [4.0, 2.0])
    # predictions after the horizon are never looked at, whatever they hold
    pred[1, :, 2:] = np.nan
    np.testing.assert_allclose(min_ade(pred, _padded(gt, horizon), k=2, horizon=horizon), [2.5, 1.5])


def test_full_horizons_give_the_very_same_table() -> None:
    pred, gt = _case()
    kwargs = dict(joint_key=np.array([0, 0, 1, 2]), group_id=np.array([3, 3, 4, 5]), k=10, workers=1, quiet=True)
    plain = compute_metrics(pred, gt, **kwargs)
    assert compute_metrics(pred, gt, horizon=np.full(4, 5), **kwargs).equals(plain)


def test_density_fits_use_each_agents_own_draws_truncated_to_its_horizon() -> None:
    pred, gt = _case()
    horizon = np.array([5, 3, 5, 3])
    table = compute_metrics(pred, _padded(gt, horizon), horizon=horizon, metrics=["nll", "nll_joint"],
                            joint_key=np.array([0, 0, 1, 1]), group_id=None, workers=1, quiet=True)
    nll = table.filter((pl.col("metric") == "nll") & ~pl.col("aggregate")).get_column("value").to_numpy()
    long, short = [0, 2], [1, 3]
    np.testing.assert_allclose(nll[long], nll_indep(pred[long], gt[long], workers=1, quiet=True))
    np.testing.assert_allclose(nll[short], nll_indep(pred[short, :, :3], gt[short, :3], workers=1, quiet=True))
    # joint groups {0, 1} and {2, 3} mix horizons 5 and 3: both use the shortest, 3 steps
    joint = table.filter((pl.col("metric") == "nll_joint") & ~pl.col("aggregate"))
    expected = nll_joint(pred[:, :, :3], gt[:, :3], np.array([0, 0, 1, 1]), workers=1, quiet=True)[1]
    np.testing.assert_allclose(joint.get_column("value").to_numpy(), expected)
    assert joint.get_column("agent_index").to_list() == [0, 2]


def test_joint_displacement_uses_the_groups_shortest_horizon() -> None:
    pred, gt = _case()
    horizon = np.array([5, 3, 5, 5])
    keys, values = min_ade_joint(pred, _padded(gt, horizon), np.array([0, 0, 1, 1]), k=10, horizon=horizon)
    expected = min_ade_joint(pred[:, :, :3], gt[:, :3], np.array([0, 0, 1, 1]), k=10)[1][0]
    assert keys.tolist() == [0, 1] and values[0] == pytest.approx(expected)
    assert values[1] == pytest.approx(min_ade_joint(pred[2:], gt[2:], np.array([1, 1]), k=10)[1][0])


def test_identical_input_groups_pool_only_members_of_one_horizon() -> None:
    pred, gt = _case(n_agents=6)
    horizon = np.array([5, 5, 5, 3, 3, 3])
    group_id = np.zeros(6, dtype=np.int64)
    table = compute_metrics(pred, _padded(gt, horizon), horizon=horizon, group_id=group_id,
                            metrics=["nll", "jsd"], workers=1, quiet=True)
    nll = table.filter((pl.col("metric") == "nll") & ~pl.col("aggregate")).get_column("value").to_numpy()
    pooled_long = nll_indep(pred[:3], gt[:3], group_id=group_id[:3], workers=1, quiet=True)
    pooled_short = nll_indep(pred[3:, :, :3], gt[3:, :3], group_id=group_id[3:], workers=1, quiet=True)
    np.testing.assert_allclose(nll, np.concatenate([pooled_long, pooled_short]))
    jsd = table.filter((pl.col("metric") == "jsd") & ~pl.col("aggregate"))
    assert jsd.get_column("group_key").to_list() == [0, 0] and jsd.get_column("agent_index").to_list() == [0, 3]


def test_bad_horizons_and_gaps_inside_a_horizon() -> None:
    pred, gt = _case()
    with pytest.raises(UsageError, match=r"horizon must lie in \[1, 5\]"):
        min_ade(pred, gt, horizon=np.array([5, 6, 5, 5]))
    with pytest.raises(UsageError, match="one per agent"):
        min_ade(pred, gt, horizon=np.array([5, 5]))
    gt = _padded(gt, np.array([5, 3, 5, 3]))
    with pytest.raises(DataError, match=r"non-finite positions .* agents \[1, 3\]"):
        min_ade(pred, gt, horizon=np.array([5, 4, 5, 4]))
