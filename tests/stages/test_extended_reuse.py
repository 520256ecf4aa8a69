"""`--extended-horizon` scores again only the problems whose fits see more than n_future steps: every other unit
reuses its standard row, the aggregates are the means over all units, and compute_metrics sees only the subset."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.metrics import METRIC_NAMES, compute_metrics
from trajflow_pipeline.metrics import extended
from trajflow_pipeline.metrics.extended import EXTENDED_SUFFIX, LONG_SUFFIX, _recompute_set
from trajflow_pipeline.metrics.extended import extended_metrics as _extended_metrics

N_FUTURE, LONGEST, DRAWS = 4, 6, 20
DETERMINISTIC = ("min_ade", "min_fde", "min_ade_joint", "min_fde_joint")
UNIT = ["metric", "agent_index", "group_key"]

# Agent (before shuffling): horizon, joint_key, group_id. Agents 0 / 1 are a long joint pair; identical-input
# group 100 mixes long agents 0, 12 with short agent 2, whose joint partner 3 shares group 101 with agent 4 (a
# second step of the closure); agent 7 is long alone. Agents 5, 6, 8-11 and all their groups end at n_future.
LAYOUT = [(6, 10, 100), (6, 10, 107), (4, 11, 100), (4, 11, 101), (4, 18, 101), (4, 12, 102), (4, 12, 102),
          (5, 13, 103), (4, 14, 104), (4, 14, 105), (4, 15, 106), (4, 16, 106), (6, 17, 100)]
RECOMPUTED = {0, 1, 2, 3, 4, 7, 12}


def _case(seed: int = 0) -> tuple[SimpleNamespace, np.ndarray, dict[str, Any], np.ndarray]:
    """Problems-like object, (A, S, LONGEST, 2) draws, compute_metrics options as metrics_table builds them, and
    the shuffle (position of each LAYOUT agent), so that the recomputed agents are scattered."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(LAYOUT))
    horizon, joint_key, group_id = (np.array([LAYOUT[i][c] for i in order], dtype=np.int64) for c in range(3))
    gt = rng.normal(size=(len(LAYOUT), LONGEST, 2)).cumsum(axis=1)
    pred = gt[:, None] + rng.normal(scale=0.5, size=(len(LAYOUT), DRAWS, LONGEST, 2))
    extended = gt.copy()
    extended[np.arange(LONGEST)[None, :] >= horizon[:, None]] = np.nan
    problems = SimpleNamespace(horizons=horizon, n_future=N_FUTURE, joint_id=joint_key, group_id=group_id,
                               extended_future=_Tensor(extended))
    common = dict(joint_key=joint_key, group_id=group_id, k=10, metrics=METRIC_NAMES, workers=1, quiet=True,
                  seed=0, max_pooled=None)
    return problems, pred, common, np.argsort(order)


class _Tensor:
    """Just what _extended_metrics asks of Problems.extended_future: .double().numpy()."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = values

    def double(self) -> "_Tensor":
        return self

    def numpy(self) -> np.ndarray:
        return self.values


def _standard(problems: SimpleNamespace, pred: np.ndarray, common: dict[str, Any]) -> pl.DataFrame:
    return compute_metrics(pred[:, :, :N_FUTURE], problems.extended_future.values[:, :N_FUTURE], **common)


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Replace the extended metrics' compute_metrics by a wrapper recording how many problems each call gets."""
    calls: list[int] = []

    def counted(pred: np.ndarray, *args: Any, **kwargs: Any) -> pl.DataFrame:
        calls.append(pred.shape[0])
        return compute_metrics(pred, *args, **kwargs)

    monkeypatch.setattr(extended, "compute_metrics", counted)
    return calls


def _units(table: pl.DataFrame, suffix: str = "") -> pl.DataFrame:
    """Unit rows with the metric named without `suffix`."""
    return (table.filter(~pl.col("aggregate") & pl.col("metric").str.ends_with(suffix))
            .with_columns(pl.col("metric").str.strip_suffix(suffix)) if suffix else table.filter(~pl.col("aggregate")))


def _global(table: pl.DataFrame, agents: np.ndarray) -> pl.DataFrame:
    return table.with_columns(agent_index=pl.Series(agents[table.get_column("agent_index").to_numpy()]))


def test_closure_of_the_long_agents_under_both_groupings() -> None:
    problems, _, common, position = _case()
    redo = _recompute_set(problems.horizons > N_FUTURE, common["joint_key"], common["group_id"])
    assert set(np.flatnonzero(redo).tolist()) == {int(position[a]) for a in RECOMPUTED}
    assert not _recompute_set(np.zeros(4, dtype=bool), None, None).any()


def test_extended_metrics_reuse_standard_units_and_recompute_only_the_closure(
        monkeypatch: pytest.MonkeyPatch) -> None:
    problems, pred, common, position = _case()
    standard = _standard(problems, pred, common)
    calls = _counting(monkeypatch)
    table = _extended_metrics(problems, pred, standard, common)
    redo = np.zeros(len(LAYOUT), dtype=bool)
    redo[position[sorted(RECOMPUTED)]] = True
    agents = np.flatnonzero(redo)
    assert calls == [agents.size]                                   # (4) one call, on the closure only
    ext = _units(table, EXTENDED_SUFFIX).filter(~pl.col("metric").str.ends_with(LONG_SUFFIX))
    inside = pl.col("agent_index").is_in(agents.tolist())

    # (1) outside the closure: the standard rows' very values
    outside = _units(standard).filter(~inside)
    reused = ext.filter(~inside).join(outside, on=UNIT, how="full", suffix="_std", nulls_equal=True)
    assert reused.height == outside.height == ext.filter(~inside).height > 0
    assert reused.get_column("value").to_list() == reused.get_column("value_std").to_list()

    # (2) inside: the numbers of one compute_metrics call on the closure; displacement also as on all problems
    own, gt = problems.horizons, problems.extended_future.values
    subset = dict(common, joint_key=common["joint_key"][agents], group_id=common["group_id"][agents])
    direct = _global(_units(compute_metrics(pred[agents], gt[agents], horizon=own[agents], **subset)), agents)
    redone = ext.filter(inside).join(direct, on=UNIT, how="full", suffix="_direct", nulls_equal=True)
    assert redone.height == direct.height == ext.filter(inside).height
    assert set(redone.get_column("metric")) == set(METRIC_NAMES)
    assert redone.get_column("value").to_list() == redone.get_column("value_direct").to_list()
    full = _units(compute_metrics(pred, gt, horizon=own, **common))
    assert ext.select(UNIT).equals(full.select(UNIT))               # the same units, in the same order
    shown = ext.filter(pl.col("metric").is_in(DETERMINISTIC))
    assert shown.get_column("value").to_list() == full.filter(pl.col("metric").is_in(DETERMINISTIC)).get_column(
        "value").to_list()
    jsd = ext.filter(inside & (pl.col("metric") == "jsd"))          # group 100 keeps a long row, 101 is redone
    assert sorted(jsd.get_column("group_key").to_list()) == [100, 101]

    # (3) one aggregate row per metric after its units: their mean, as compute_metrics makes it
    for metric in METRIC_NAMES:
        rows = table.filter(pl.col("metric") == metric + EXTENDED_SUFFIX)
        assert rows.get_column("aggregate").to_list() == [False] * (rows.height - 1) + [True]
        values = rows.get_column("value").to_numpy()
        assert values[-1] == values[:-1].mean()
    long = own > N_FUTURE
    ade = ext.filter(pl.col("metric") == "min_ade").sort("agent_index").get_column("value").to_numpy()
    aggregates = dict(table.filter(pl.col("aggregate")).select("metric", "value").iter_rows())
    assert aggregates["min_ade" + EXTENDED_SUFFIX + LONG_SUFFIX] == pytest.approx(ade[long].mean())
    assert set(table.schema.items()) == set(standard.schema.items())


def test_no_long_problem_reuses_everything_and_all_long_recomputes_all(monkeypatch: pytest.MonkeyPatch) -> None:
    problems, pred, common, _ = _case()
    calls = _counting(monkeypatch)
    short = SimpleNamespace(**{**vars(problems), "horizons": np.full(len(LAYOUT), N_FUTURE)})
    standard = _standard(problems, pred, {**common, "metrics": DETERMINISTIC})
    table = _extended_metrics(short, pred, standard, {**common, "metrics": DETERMINISTIC})
    assert calls == [] and table.get_column("value").to_list() == standard.get_column("value").to_list()
    every = SimpleNamespace(**{**vars(problems), "group_id": np.zeros(len(LAYOUT), dtype=np.int64)})
    options = {**common, "group_id": every.group_id, "metrics": DETERMINISTIC}
    _extended_metrics(every, pred, _standard(every, pred, options), options)
    assert calls == [len(LAYOUT)]


def test_jsd_alone_with_nothing_to_redo_in_the_closure(monkeypatch: pytest.MonkeyPatch) -> None:
    """A closure without an identical-input group of two same-horizon members has no JSD row to recompute: the
    subset is not evaluated (compute_metrics would refuse), and the standard JSD rows are the extended ones."""
    problems, pred, common, position = _case()
    group_id = common["group_id"].copy()
    group_id[position[[12, 4]]] = [200, 201]      # group 100: long 0 with short 2 only; 101: agent 3 alone
    options = {**common, "group_id": group_id, "metrics": ("jsd",)}
    problems = SimpleNamespace(**{**vars(problems), "group_id": group_id})
    standard = _standard(problems, pred, options)
    calls = _counting(monkeypatch)
    table = _extended_metrics(problems, pred, standard, options)
    assert calls == []
    ext = table.filter(pl.col("metric") == "jsd" + EXTENDED_SUFFIX)
    kept = standard.filter(~pl.col("group_key").is_in([100]) | pl.col("aggregate"))
    assert ext.filter(~pl.col("aggregate")).get_column("group_key").to_list() == kept.filter(
        ~pl.col("aggregate")).get_column("group_key").to_list()
    values = ext.get_column("value").to_numpy()
    assert values[-1] == values[:-1].mean()
