"""minADE_K / minFDE_K, indep and joint, on hand-crafted cases whose answers are computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics import min_ade, min_ade_joint, min_fde, min_fde_joint


def _crafted() -> tuple[np.ndarray, np.ndarray]:
    """2 agents, 3 draws, 2 steps; gt at the origin-line, draws offset by known distances (3-4-5 triangles)."""
    gt = np.array([[[0.0, 0.0], [1.0, 0.0]],
                   [[5.0, 5.0], [5.0, 6.0]]])
    offsets = np.array([
        # agent 0: draw errors per step (as vectors)
        [[[3.0, 4.0], [0.0, 1.0]],    # |e| = 5, 1     -> ADE 3,   FDE 1
         [[1.0, 0.0], [0.0, -2.0]],   # |e| = 1, 2     -> ADE 1.5, FDE 2
         [[0.0, 0.0], [0.0, 0.0]]],   # perfect, but it is the 3rd draw (excluded with k=2)
        # agent 1
        [[[0.0, 2.0], [6.0, 8.0]],    # |e| = 2, 10    -> ADE 6,   FDE 10
         [[0.0, 0.0], [0.0, 4.0]],    # |e| = 0, 4     -> ADE 2,   FDE 4
         [[0.5, 0.0], [0.0, 0.5]]],   # 0.5, 0.5 (3rd draw)
    ])
    return gt[:, None] + offsets, gt


def test_min_ade_fde_use_first_k_draws() -> None:
    pred, gt = _crafted()
    np.testing.assert_allclose(min_ade(pred, gt, k=2), [1.5, 2.0])
    np.testing.assert_allclose(min_fde(pred, gt, k=2), [1.0, 4.0])  # min over draws of each metric separately
    np.testing.assert_allclose(min_ade(pred, gt, k=3), [0.0, 0.5])
    np.testing.assert_allclose(min_fde(pred, gt, k=3), [0.0, 0.5])


def test_t_eval_evaluates_only_the_first_steps() -> None:
    pred, gt = _crafted()
    np.testing.assert_allclose(min_ade(pred, gt, k=2, t_eval=1), [1.0, 0.0])
    np.testing.assert_allclose(min_fde(pred, gt, k=2, t_eval=1), [1.0, 0.0])
    with pytest.raises(UsageError, match="t_eval"):
        min_ade(pred, gt, k=2, t_eval=3)


def test_joint_takes_min_over_aligned_draws_of_the_group_mean() -> None:
    pred, gt = _crafted()
    # one group: per draw mean ADE over agents = (3+6)/2, (1.5+2)/2 -> 1.75; FDE (1+10)/2, (2+4)/2 -> 3
    keys, ade = min_ade_joint(pred, gt, np.array([7, 7]), k=2)
    _, fde = min_fde_joint(pred, gt, np.array([7, 7]), k=2)
    np.testing.assert_array_equal(keys, [7])
    np.testing.assert_allclose(ade, [1.75])
    np.testing.assert_allclose(fde, [3.0])
    # the joint value is never below the mean of the indep values
    assert ade[0] >= min_ade(pred, gt, k=2).mean()


def test_joint_of_singleton_groups_equals_indep() -> None:
    pred, gt = _crafted()
    keys, ade = min_ade_joint(pred, gt, np.array([4, 1]), k=2)
    np.testing.assert_array_equal(keys, [1, 4])
    np.testing.assert_allclose(ade, min_ade(pred, gt, k=2)[[1, 0]])
    _, fde_none = min_fde_joint(pred, gt, None, k=2)
    np.testing.assert_allclose(fde_none, min_fde(pred, gt, k=2))


def test_bad_inputs_are_clear_errors() -> None:
    pred, gt = _crafted()
    with pytest.raises(UsageError, match="exceeds the 3 drawn samples"):
        min_ade(pred, gt, k=20)
    with pytest.raises(UsageError, match="shape"):
        min_ade(pred[0], gt)
    with pytest.raises(UsageError, match="joint_key"):
        min_ade_joint(pred, gt, np.array([1, 2, 3]), k=2)
    bad = pred.copy()
    bad[1, 0, 0, 0] = np.nan
    with pytest.raises(DataError, match=r"agents \[1\]"):
        min_ade(bad, gt, k=2)
