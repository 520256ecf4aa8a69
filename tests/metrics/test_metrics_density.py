"""NLL and JSD from ROME densities against analytic Gaussians and numerically integrated references.

ROME is a KDE after per-cluster PCA whitening with Silverman's bandwidth, so it smooths: in 2-d with 300
samples the log-density of a Gaussian is recovered to within ~0.3 nats and a JSD to within ~0.08 (the spread
over random seeds measured when choosing these cases); the seeds below are fixed, so the tests are
deterministic and the tolerances are those spreads, not tuned to one draw.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import trapezoid
from scipy.stats import multivariate_normal

from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics import (RomeTask, density_metrics, fit_and_score, jsd, jsd_from_log_densities,
                                       jsd_groups, nll_indep, nll_joint)
from trajflow_pipeline.metrics import density as density_module


def _gaussian_jsd_on_grid(mean_q, cov_q, mean_p, cov_p) -> float:
    """JSD / ln 2 of two 2-d Gaussians by trapezoidal integration on a fine grid (the test's reference)."""
    x = np.linspace(-10.0, 12.0, 1101)
    grid = np.stack(np.meshgrid(x, x, indexing="ij"), axis=-1)
    q = multivariate_normal(mean_q, cov_q).pdf(grid)
    p = multivariate_normal(mean_p, cov_p).pdf(grid)
    m = 0.5 * (p + q)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = 0.5 * (np.where(q > 0, q * np.log(q / m), 0.0) + np.where(p > 0, p * np.log(p / m), 0.0))
    return float(trapezoid(trapezoid(f, x, axis=1), x) / np.log(2.0))


MEAN_Q, COV_Q = np.zeros(2), np.eye(2)
MEAN_P, COV_P = np.array([1.5, 1.0]), np.diag([0.8**2, 1.2**2])


def test_nll_of_gaussian_samples_matches_analytic_log_density() -> None:
    rng = np.random.default_rng(0)
    n, cov, mean = 300, np.diag([0.3**2, 1.0**2]), np.array([2.0, -1.0])
    samples = rng.multivariate_normal(mean, cov, size=(2, n))          # two agents, own sample sets
    points = np.stack([mean, mean + np.sqrt(np.diag(cov)) / np.sqrt(2)])  # at the mean and ~1 sigma away
    nll = nll_indep(samples.reshape(2, n, 1, 2), points.reshape(2, 1, 2), workers=1, quiet=True)
    np.testing.assert_allclose(nll, -multivariate_normal(mean, cov).logpdf(points), atol=0.35)


def test_jsd_estimator_with_exact_densities_matches_integration() -> None:
    rng = np.random.default_rng(1)
    q, p = multivariate_normal(MEAN_Q, COV_Q), multivariate_normal(MEAN_P, COV_P)
    xq, xp = q.rvs(20000, random_state=rng), p.rvs(20000, random_state=rng)
    value = jsd_from_log_densities(q.logpdf(xq), p.logpdf(xq), q.logpdf(xp), p.logpdf(xp))
    assert value == pytest.approx(_gaussian_jsd_on_grid(MEAN_Q, COV_Q, MEAN_P, COV_P), abs=0.01)


def test_jsd_estimator_equals_the_reference_frameworks_formula() -> None:
    """The benchmarking framework (Schumann et al.) tiles each gt's log-likelihoods over the P predictions,
    stacks them with the predictions' ones, and averages (X/M) ln(X/M) over all 2 N P entries for X = Q and
    X = P. Written out here from that description, it must agree with ours to rounding."""
    rng = np.random.default_rng(7)
    n, p = 40, 25
    lq_gt, lp_gt = rng.normal(-3, 2, n), rng.normal(-4, 2, n)
    lq_pred, lp_pred = rng.normal(-5, 2, (n, p)), rng.normal(-3, 2, (n, p))
    log_q = np.concatenate([np.tile(lq_gt[:, None], (1, p)), lq_pred])
    log_p = np.concatenate([np.tile(lp_gt[:, None], (1, p)), lp_pred])
    log_m = np.logaddexp(log_q, log_p) - np.log(2.0)
    kl_q = np.mean(np.exp(log_q - log_m) * (log_q - log_m))
    kl_p = np.mean(np.exp(log_p - log_m) * (log_p - log_m))
    reference = (0.5 * kl_q + 0.5 * kl_p) / np.log(2.0)
    ours = jsd_from_log_densities(lq_gt, lp_gt, lq_pred.ravel(), lp_pred.ravel())
    assert ours == pytest.approx(reference, rel=1e-12, abs=1e-12)


def test_jsd_of_two_gaussians_with_rome_matches_integration() -> None:
    rng = np.random.default_rng(0)
    n = 300
    gt = rng.multivariate_normal(MEAN_Q, COV_Q, size=n).reshape(n, 1, 2)
    pred = rng.multivariate_normal(MEAN_P, COV_P, size=n).reshape(n, 1, 1, 2)
    keys, values = jsd(pred, gt, np.full(n, 3), workers=1, quiet=True)
    np.testing.assert_array_equal(keys, [3])
    reference = _gaussian_jsd_on_grid(MEAN_Q, COV_Q, MEAN_P, COV_P)  # ~0.459
    assert values[0] == pytest.approx(reference, abs=0.08)


def test_jsd_identical_is_zero_and_separated_is_one() -> None:
    rng = np.random.default_rng(2)
    n = 120
    gt = rng.normal(size=(n, 2, 2)).cumsum(axis=1)
    same = gt[:, None]                                 # pooled predictions == the set of gts: P == Q exactly
    far = gt[:, None] + np.array([50.0, 0.0])          # disjoint supports
    group = np.zeros(n, dtype=int)
    _, v_same = jsd(same, gt, group, workers=1, quiet=True)
    _, v_far = jsd(far, gt, group, workers=1, quiet=True)
    assert v_same[0] == pytest.approx(0.0, abs=1e-12)
    assert v_far[0] == pytest.approx(1.0, abs=1e-6)
    # independent draws of the same 2-d distribution (300 each): close to 0 (KDE noise only)
    gt_2d = rng.normal(size=(300, 1, 2))
    _, v_iid = jsd(rng.normal(size=(300, 1, 1, 2)), gt_2d, np.zeros(300, int), workers=1, quiet=True)
    assert 0.0 <= v_iid[0] < 0.05


def test_jsd_skips_singleton_groups_and_needs_group_id() -> None:
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(5, 1, 2))
    pred = gt[:, None] + rng.normal(scale=0.1, size=(5, 4, 1, 2))
    keys, values = jsd(pred, gt, np.array([1, 1, 1, 2, 9]), workers=1, quiet=True)
    np.testing.assert_array_equal(keys, [1])  # groups 2 and 9 have one agent: no ground-truth distribution
    assert values.shape == (1,) and 0.0 <= values[0] <= 1.0
    with pytest.raises(UsageError, match="group_id"):
        jsd(pred, gt, None)


def test_jsd_skips_groups_whose_futures_are_all_the_same() -> None:
    """A point mass has no density: such a group gets no JSD row, where it used to abort the whole evaluation."""
    rng = np.random.default_rng(13)
    gt = rng.normal(size=(7, 3, 2))
    gt[3:6] = gt[3]                                  # group 4: three standing pedestrians, the same future
    group = np.array([1, 1, 1, 4, 4, 4, 9])
    pred = gt[:, None] + rng.normal(scale=0.1, size=(7, 20, 3, 2))
    keys, values = jsd(pred, gt, group, workers=1, quiet=True)
    np.testing.assert_array_equal(keys, [1])
    assert 0.0 <= values[0] <= 1.0
    evaluated, identical = jsd_groups(gt, group)
    np.testing.assert_array_equal(evaluated, [1])
    np.testing.assert_array_equal(identical, [4])
    gt[4, -1, 0] += 1e-6                              # one future differs a little: evaluated again
    np.testing.assert_array_equal(jsd_groups(gt, group)[0], [1, 4])


def test_pooled_nll_fits_the_group_predictions_together() -> None:
    rng = np.random.default_rng(4)
    gt = rng.normal(size=(4, 2, 2))
    pred = rng.normal(size=(4, 15, 2, 2))
    group = np.array([0, 0, 0, 1])
    pooled = nll_indep(pred, gt, group_id=group, workers=1, quiet=True)
    own = nll_indep(pred, gt, group_id=group, pool_groups=False, workers=1, quiet=True)
    expected = -fit_and_score(RomeTask(pred[:3].reshape(45, 4), (gt[:3].reshape(3, 4),)))[0]
    np.testing.assert_allclose(pooled[:3], expected)
    assert pooled[3] == own[3]                       # a group of one: the same fit either way
    np.testing.assert_array_equal(own, nll_indep(pred, gt, workers=1, quiet=True))


def test_joint_nll_concatenates_agents_and_reuses_indep_for_singletons() -> None:
    rng = np.random.default_rng(5)
    gt = rng.normal(size=(3, 2, 2))
    pred = gt[:, None] + rng.normal(scale=0.5, size=(3, 30, 2, 2))
    keys, values = nll_joint(pred, gt, np.array([8, 8, 2]), workers=1, quiet=True)
    np.testing.assert_array_equal(keys, [2, 8])
    joint_samples = np.concatenate([pred[0].reshape(30, 4), pred[1].reshape(30, 4)], axis=1)
    expected = -fit_and_score(RomeTask(joint_samples, (np.concatenate([gt[0].ravel(), gt[1].ravel()])[None],)))[0]
    assert values[1] == pytest.approx(expected[0], rel=0, abs=0)
    assert values[0] == nll_indep(pred, gt, workers=1, quiet=True)[2]


def test_reference_chunking_rule_and_chunked_density_is_deterministic(monkeypatch: pytest.MonkeyPatch) -> None:
    assert density_module.reference_chunk_size(3000, 50, 150_000) == 3000   # synthetic bimodal: 50 fits
    assert density_module.reference_chunk_size(1, 100, 100) == 100          # one agent, 100 samples: one fit
    assert density_module.reference_chunk_size(10, 600, 10_000) == 3000
    monkeypatch.setattr(density_module, "REFERENCE_MIN_CHUNK", 10)          # force 2 chunks of 10 on 20 points
    rng = np.random.default_rng(6)
    gt = rng.normal(size=(10, 1, 2))
    pred = rng.normal(size=(10, 2, 1, 2))
    first = density_metrics(pred, gt, metrics={"nll", "jsd"}, group_id=np.zeros(10, int), workers=1, quiet=True)
    again = density_metrics(pred, gt, metrics={"nll", "jsd"}, group_id=np.zeros(10, int), workers=1, quiet=True)
    assert first.nll is not None and first.jsd is not None
    np.testing.assert_array_equal(first.nll, again.nll)
    np.testing.assert_array_equal(first.jsd, again.jsd)
    capped = density_metrics(pred, gt, metrics={"nll"}, group_id=np.zeros(10, int), max_pooled=10,
                             workers=1, quiet=True)
    assert capped.nll is not None and np.isfinite(capped.nll).all() and not np.array_equal(capped.nll, first.nll)


def test_degenerate_sample_sets_are_data_errors() -> None:
    gt = np.zeros((2, 3, 2))
    pred = np.ones((2, 10, 3, 2))  # every draw identical: no density can be fitted
    with pytest.raises(DataError, match="agent 0"):
        nll_indep(pred, gt, workers=1, quiet=True)
    with pytest.raises(UsageError, match="max_pooled"):
        density_metrics(pred, gt, metrics={"nll"}, max_pooled=1)


@pytest.mark.parametrize("fit, query, message", [
    (np.zeros((0, 4)), np.zeros((1, 4)), "at least 2 samples"),
    (np.ones((1, 4)), np.zeros((1, 4)), "at least 2 samples"),
    (np.ones(4), np.zeros((1, 4)), "at least 2 samples"),
    (np.full((10, 4), np.nan), np.zeros((1, 4)), "non-finite values"),
    (np.arange(40.0).reshape(10, 4), np.zeros((1, 3)), "density is over 4 dimensions"),
    (np.ones((10, 4)), np.zeros((1, 4)), "degenerate"),
])
def test_bad_rome_tasks_are_data_errors_naming_the_task(fit: np.ndarray, query: np.ndarray, message: str) -> None:
    from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score

    with pytest.raises(DataError, match=message) as error:
        fit_and_score(RomeTask(fit=fit, queries=(query,), label="agent 7 of run r"))
    assert "agent 7 of run r" in str(error.value)


def test_points_whose_distances_overflow_are_refused() -> None:
    from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score

    points = np.random.default_rng(0).normal(size=(20, 4)) * 1e154
    with pytest.raises(DataError, match="too far apart for a density estimate"):
        fit_and_score(RomeTask(fit=points, queries=(points[:1],), label="the far ones"))
