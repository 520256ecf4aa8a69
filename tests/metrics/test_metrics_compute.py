"""compute_metrics: the long table, its aggregates, metric-name checking, and serial == parallel."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.metrics import (METRIC_NAMES, RomeTally, RomeTask, compute_metrics, fit_and_score,
                                       min_ade, nll_indep, run_rome_tasks)


def _case(seed: int = 0, n_agents: int = 6, n_samples: int = 25, n_steps: int = 4):
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=(n_agents, n_steps, 2)).cumsum(axis=1)
    pred = gt[:, None] + rng.normal(scale=0.4, size=(n_agents, n_samples, n_steps, 2))
    joint_key = np.array([0, 0, 1, 2, 2, 2])[:n_agents]
    group_id = np.array([5, 5, 5, 7, 7, 9])[:n_agents]
    return pred, gt, joint_key, group_id


def test_long_table_schema_rows_and_aggregates() -> None:
    pred, gt, joint_key, group_id = _case()
    table = compute_metrics(pred, gt, joint_key=joint_key, group_id=group_id, k=10, workers=1, quiet=True)
    assert table.schema == {"metric": pl.Utf8, "value": pl.Float64, "agent_index": pl.Int64,
                            "group_key": pl.Int64, "aggregate": pl.Boolean}
    counts = dict(table.group_by("metric").len().iter_rows())
    # per agent + 1 aggregate; joint: 3 groups + 1; jsd: groups 5 and 7 (>= 2 agents) + 1
    assert counts == {"min_ade": 7, "min_fde": 7, "min_ade_joint": 4, "min_fde_joint": 4, "nll": 7,
                      "nll_joint": 4, "jsd": 3}
    assert table["metric"].unique(maintain_order=True).to_list() == list(METRIC_NAMES)
    for metric in METRIC_NAMES:
        rows = table.filter(pl.col("metric") == metric)
        units, agg = rows.filter(~pl.col("aggregate")), rows.filter(pl.col("aggregate"))
        assert agg.height == 1 and agg["agent_index"].is_null().all() and agg["group_key"].is_null().all()
        assert agg["value"][0] == pytest.approx(units["value"].mean())
    ade = table.filter((pl.col("metric") == "min_ade") & ~pl.col("aggregate"))
    np.testing.assert_allclose(ade["value"].to_numpy(), min_ade(pred, gt, k=10))
    np.testing.assert_array_equal(ade["agent_index"].to_numpy(), np.arange(6))
    joint = table.filter((pl.col("metric") == "nll_joint") & ~pl.col("aggregate"))
    assert joint["group_key"].to_list() == [0, 1, 2] and joint["agent_index"].to_list() == [0, 2, 3]
    nll = table.filter((pl.col("metric") == "nll") & ~pl.col("aggregate"))["value"].to_numpy()
    np.testing.assert_allclose(nll, nll_indep(pred, gt, group_id=group_id, workers=1, quiet=True))
    assert joint["value"][1] == nll[2]  # singleton joint group reuses the indep NLL
    jsd_rows = table.filter((pl.col("metric") == "jsd") & ~pl.col("aggregate"))
    assert jsd_rows["group_key"].to_list() == [5, 7] and jsd_rows["agent_index"].to_list() == [0, 3]
    assert ((jsd_rows["value"] >= 0) & (jsd_rows["value"] <= 1)).all()


def test_t_eval_and_subset_of_metrics() -> None:
    pred, gt, _, _ = _case()
    table = compute_metrics(pred, gt, metrics=["min_fde", "min_ade"], k=5, t_eval=2, quiet=True)
    assert table["metric"].unique(maintain_order=True).to_list() == ["min_ade", "min_fde"]
    expected = min_ade(pred[:, :, :2], gt[:, :2], k=5)
    np.testing.assert_allclose(table.filter(~pl.col("aggregate"))["value"][:6].to_numpy(), expected)


def test_unknown_metric_lists_the_valid_ones() -> None:
    pred, gt, _, _ = _case()
    with pytest.raises(UsageError, match=r"unknown metric\(s\) 'min_ad'.*valid: min_ade, min_fde"):
        compute_metrics(pred, gt, metrics=["min_ade", "min_ad"], quiet=True)
    with pytest.raises(UsageError, match="jsd needs a group_id"):
        compute_metrics(pred, gt, metrics=["jsd"], quiet=True)
    with pytest.raises(UsageError, match="workers"):
        compute_metrics(pred, gt, metrics=["nll"], workers=0, quiet=True)


def test_parallel_equals_serial() -> None:
    pred, gt, joint_key, group_id = _case(seed=1, n_samples=20)
    kwargs = dict(joint_key=joint_key, group_id=group_id, k=10, quiet=True)
    serial = compute_metrics(pred, gt, workers=1, **kwargs)
    parallel = compute_metrics(pred, gt, workers=2, **kwargs)
    assert serial.equals(parallel)  # bit-identical, not merely close
    tasks = [RomeTask(fit=pred[a].reshape(20, -1), queries=(gt[a].reshape(1, -1),), label=f"agent {a}")
             for a in range(pred.shape[0])]
    results = run_rome_tasks(tasks, workers=2, quiet=True, base_seed=3)
    for index, task in enumerate(tasks):  # in task order, each as the task alone gives it
        np.testing.assert_array_equal(results[index][0], fit_and_score(task)[0])


@pytest.mark.usefixtures("rome_pca_fails_twice")
def test_rome_pca_fallback_is_counted_not_printed(capsys: pytest.CaptureFixture) -> None:
    """A fit whose cluster PCA fails re-runs it with jitter (ROME's fallback); nothing reaches stdout (it would
    break progress bars and tables): the fits go on, one note on stderr says how many needed the fallback, and a
    tally given by the caller adds them up."""
    pred, gt, _, _ = _case(seed=2, n_samples=20)
    tasks = [RomeTask(fit=pred[a].reshape(20, -1), queries=(gt[a].reshape(1, -1),)) for a in range(3)]
    tally = RomeTally(fits=4, fallback_fits=1, retries=1)  # from an earlier call
    results = run_rome_tasks(tasks, workers=1, fallbacks=tally)
    captured = capsys.readouterr()
    assert "PCA failed" not in captured.out
    assert "1 of 3 ROME fits re-ran a failed PCA" in captured.err and "2 retries" in captured.err
    assert tally == RomeTally(fits=7, fallback_fits=2, retries=3)
    assert tally.note().startswith("2 of 7 ROME fits re-ran a failed PCA") and RomeTally().note() == ""
    assert all(np.isfinite(r[0]).all() for r in results)


def test_an_interrupted_rome_run_resumes_from_its_cache(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Finished fits are saved as they come; a rerun over the same tasks fits only the others and returns the very
    same arrays; other tasks (here: another seed) never reuse them."""
    from trajflow_pipeline.metrics import parallel

    pred, gt, _, _ = _case(seed=4, n_samples=20)
    tasks = [RomeTask(fit=pred[a].reshape(20, -1), queries=(gt[a].reshape(1, -1), pred[a, :3].reshape(3, -1)))
             for a in range(pred.shape[0])]
    reference = run_rome_tasks(tasks, workers=1, quiet=True, base_seed=5)
    real_fit, calls = parallel._fit_batch, []

    def fit_until(limit: int):
        def fit(batch):
            if len(calls) + len(batch) > limit:
                raise KeyboardInterrupt
            calls.extend(batch)
            return real_fit(batch)
        return fit

    monkeypatch.setattr(parallel, "BATCH_FITS", 2)
    monkeypatch.setattr(parallel, "_fit_batch", fit_until(5))
    with pytest.raises(KeyboardInterrupt):
        run_rome_tasks(tasks, workers=1, quiet=True, base_seed=5, cache=tmp_path)
    calls.clear()
    monkeypatch.setattr(parallel, "_fit_batch", fit_until(100))
    resumed = run_rome_tasks(tasks, workers=1, quiet=True, base_seed=5, cache=tmp_path)
    assert len(calls) == len(tasks) - 4                      # two saved batches of 2; the third was interrupted
    for got, expected in zip(resumed, reference):
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)
    calls.clear()
    run_rome_tasks(tasks, workers=1, quiet=True, base_seed=6, cache=tmp_path)
    assert len(calls) == len(tasks)                          # other seeds: other results, nothing reused
    monkeypatch.setattr(parallel, "_fit_batch", fit_until(0))
    tally = RomeTally()
    again = run_rome_tasks(tasks, workers=1, quiet=True, base_seed=5, cache=tmp_path, fallbacks=tally)
    assert tally.resumed == len(tasks)                       # everything saved: no fit at all
    np.testing.assert_array_equal(again[3][1], reference[3][1])


def _same(results, reference) -> bool:
    return all(np.array_equal(a, b) for got, expected in zip(results, reference, strict=True)
               for a, b in zip(got, expected, strict=True))


def test_a_cache_serves_only_the_very_same_tasks(tmp_path) -> None:
    """Saved fits are never reused for another task list: a changed point, query, minimum std or task count, or
    a damaged part, all give what an uncached run gives."""
    from dataclasses import replace

    pred, gt, _, _ = _case(seed=5, n_samples=20)
    tasks = [RomeTask(fit=pred[a].reshape(20, -1), queries=(gt[a].reshape(1, -1),)) for a in range(pred.shape[0])]
    run_rome_tasks(tasks, workers=1, quiet=True, cache=tmp_path)          # every fit of `tasks` saved
    moved_point = tasks[2].fit.copy()
    moved_point[0, 0] += 0.5
    variants = {
        "point": [*tasks[:2], replace(tasks[2], fit=moved_point), *tasks[3:]],
        "query": [*tasks[:2], replace(tasks[2], queries=(tasks[2].queries[0] + 0.5,)), *tasks[3:]],
        "min_std": [*tasks[:2], replace(tasks[2], min_std=0.3), *tasks[3:]],
        "count": tasks[:4],
    }
    for name, variant in variants.items():
        uncached = run_rome_tasks(variant, workers=1, quiet=True)
        assert _same(run_rome_tasks(variant, workers=1, quiet=True, cache=tmp_path), uncached), name
    reference = run_rome_tasks(tasks, workers=1, quiet=True)
    (tmp_path / "damaged").mkdir()
    for directory in tmp_path.iterdir():                                  # an empty part, as a crash can leave
        (directory / "part-empty.npz").write_bytes(b"")
    tally = RomeTally()
    assert _same(run_rome_tasks(tasks, workers=1, quiet=True, cache=tmp_path, fallbacks=tally), reference)
    assert tally.resumed == len(tasks)


def test_parallel_fits_are_saved_per_batch_and_resume_with_any_worker_count(tmp_path) -> None:
    pred, gt, _, _ = _case(seed=6, n_samples=20)
    tasks = [RomeTask(fit=pred[a].reshape(20, -1), queries=(gt[a].reshape(1, -1),)) for a in range(pred.shape[0])]
    reference = run_rome_tasks(tasks, workers=1, quiet=True, base_seed=2)
    assert _same(run_rome_tasks(tasks, workers=2, quiet=True, base_seed=2, cache=tmp_path), reference)
    parts = sorted(tmp_path.glob("*/part-*.npz"))
    assert len(parts) > 1                                                  # one per finished batch
    for part in parts[::2]:
        part.unlink()
    for workers in (2, 1):
        tally = RomeTally()
        assert _same(run_rome_tasks(tasks, workers=workers, quiet=True, base_seed=2, cache=tmp_path,
                                    fallbacks=tally), reference)
        assert 0 < tally.resumed <= len(tasks)
