"""Aggregate per-run metric values into the report's tables: mean ± std over folds and seeds, per-fold breakdowns,
the paper targets and how our TrajFlow compares with our other models.

The input is :func:`collect.metrics_frame`: one aggregate value per (run, metric). Standard deviations are
population standard deviations over runs (ddof = 0, numpy's default, which is how mean ± std over seeds /
folds is usually reported); a single run shows its value without ± part. Every metric is lower-is-better.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import polars as pl

from .document import Cell, Table
from .paper import OUR_TRAJFLOW, PAPER_TRAJFLOW, MetricSpec, metric_columns, model_label, model_order

MISSING = "—"
PAPER_LABEL = "TrajFlow (paper)"


def summary_stats(metrics: pl.DataFrame) -> pl.DataFrame:
    """Mean, std (over runs, ddof 0) and run count per (dataset, model, metric)."""
    return (metrics.group_by("dataset", "model", "metric")
            .agg(pl.col("value").mean().alias("mean"), pl.col("value").std(ddof=0).alias("std"),
                 pl.len().alias("runs"))
            .sort("dataset", "model", "metric"))


def fold_stats(metrics: pl.DataFrame) -> pl.DataFrame:
    """Mean over seeds and seed count per (dataset, fold, model, metric)."""
    return (metrics.group_by("dataset", "fold", "model", "metric")
            .agg(pl.col("value").mean().alias("mean"), pl.len().alias("seeds"))
            .sort("dataset", "fold", "model", "metric", nulls_last=False))


def format_value(value: float | None, decimals: int) -> str:
    """A number with the metric's decimals; the dash for missing values."""
    if value is None:
        return MISSING
    if math.isnan(value) or math.isinf(value):
        return str(value)
    return f"{value:.{decimals}f}"


def format_mean_std(mean: float | None, std: float | None, runs: int, decimals: int) -> str:
    """`mean ± std` (just the mean for a single run)."""
    if mean is None:
        return MISSING
    if runs < 2 or std is None:
        return format_value(mean, decimals)
    return f"{format_value(mean, decimals)} ± {format_value(std, decimals)}"


def _best(values: list[float | None]) -> float | None:
    """The lowest finite value of a column (None when there is none)."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return min(finite) if finite else None


def _pivot(stats: pl.DataFrame, index: str, field: str) -> dict[tuple[str | None, str], float | int | None]:
    """(index value, metric) -> field, from a long stats frame."""
    return {(row[index], row["metric"]): row[field] for row in stats.iter_rows(named=True)}


def metric_header(spec: MetricSpec, k: int | None) -> str:
    """Column label; minADE / minFDE carry their K when all runs of the section share it."""
    if k is not None and spec.name.startswith(("min_ade", "min_fde")):
        return f"{spec.label} (K={k})"
    return spec.label


def summary_table(stats: pl.DataFrame, dataset: str, k: int | None = None, *, of: str = "",
                  paper_row: bool = True) -> Table:
    """One row per model (mean ± std over runs), the best mean per column in bold, then the paper's TrajFlow row.

    `stats` is :func:`summary_stats` restricted to `dataset`. With `paper_row` (the aggregates) every standard
    metric gets a column, a dash where nobody evaluated it; without (other statistics, e.g. medians, which the
    paper's numbers cannot be compared with) only the metrics in `stats` do. `of` says what each run's value is,
    for the caption.
    """
    present = stats.get_column("metric").to_list()
    columns = [spec for spec in metric_columns(present) if paper_row or spec.name in present]
    models = model_order(stats.get_column("model").to_list())
    mean, std, runs = _pivot(stats, "model", "mean"), _pivot(stats, "model", "std"), _pivot(stats, "model", "runs")
    run_count = dict(stats.group_by("model").agg(pl.col("runs").max()).iter_rows())
    best = {spec.name: _best([mean.get((m, spec.name)) for m in models]) for spec in columns}
    rows = [
        (Cell(model_label(model)), Cell(str(run_count[model])),
         *(Cell(format_mean_std(mean.get((model, spec.name)), std.get((model, spec.name)),
                                int(runs.get((model, spec.name)) or 0), spec.decimals),
                bold=best[spec.name] is not None and mean.get((model, spec.name)) == best[spec.name])
           for spec in columns))
        for model in models
    ]
    paper = PAPER_TRAJFLOW.get(dataset) if paper_row else None
    if paper is not None:
        rows.append((Cell(PAPER_LABEL), Cell("paper"),
                     *(Cell(format_value(paper.get(spec.name), spec.decimals)) for spec in columns)))
    return Table(header=("model", "runs", *(metric_header(spec, k) for spec in columns)), rows=tuple(rows),
                 numeric=(False, True, *(True for _ in columns)),
                 caption=f"{of}mean ± std over folds and seeds (std over runs); bold: best of our models per column "
                         "(lower is better)" + ("; last row: the paper's TrajFlow" if paper else ""))


def fold_tables(stats: pl.DataFrame, of: str = "") -> list[tuple[MetricSpec, Table]]:
    """Per metric, a fold × model table of means over seeds, the best per fold in bold.

    `stats` is :func:`fold_stats` restricted to one dataset; metrics nobody evaluated get no table. When cells
    average different numbers of seeds, each cell shows its count in parentheses. `of` says what each run's value
    is, for the captions.
    """
    tables = []
    models = model_order(stats.get_column("model").to_list())
    folds = sorted(stats.get_column("fold").unique().to_list(), key=lambda f: (f is not None, f or ""))
    for spec in metric_columns(stats.get_column("metric").to_list()):
        part = stats.filter(pl.col("metric") == spec.name)
        if part.is_empty():
            continue
        mean = {(row["fold"], row["model"]): row["mean"] for row in part.iter_rows(named=True)}
        seeds = {(row["fold"], row["model"]): row["seeds"] for row in part.iter_rows(named=True)}
        uneven = len(set(seeds.values())) > 1
        rows = []
        for fold in folds:
            best = _best([mean.get((fold, m)) for m in models])
            rows.append((Cell(MISSING if fold is None else fold),
                         *(Cell(format_value(mean.get((fold, m)), spec.decimals)
                                + (f" ({seeds[(fold, m)]})" if uneven and (fold, m) in seeds else ""),
                                bold=best is not None and mean.get((fold, m)) == best) for m in models)))
        count = "" if uneven else f" ({next(iter(seeds.values()))} per cell)"
        tables.append((spec, Table(header=("fold", *(model_label(m) for m in models)), rows=tuple(rows),
                                   numeric=(False, *(True for _ in models)),
                                   caption=f"{spec.label}: {of}mean over seeds{count}"
                                           + ("; seeds per cell in parentheses" if uneven else "")
                                           + "; bold: best per fold")))
    return tables


def model_folds(per_fold: pl.DataFrame) -> dict[str, set[str | None]]:
    """The folds each model has evaluated runs on; `per_fold` is :func:`fold_stats` restricted to one dataset."""
    return {str(model): set(part.get_column("fold").to_list()) for (model,), part in per_fold.group_by("model")}


def uneven_seeds(per_fold: pl.DataFrame) -> dict[str, dict[str | None, int]]:
    """Per model whose folds have different numbers of seeds, each fold's seed count (`per_fold`: one dataset's
    :func:`fold_stats`)."""
    counts = per_fold.group_by("model", "fold").agg(pl.col("seeds").max())
    return {str(model): dict(zip(part.get_column("fold").to_list(), part.get_column("seeds").to_list()))
            for (model,), part in counts.group_by("model") if part.get_column("seeds").n_unique() > 1}


def fold_list(folds: Iterable[str | None]) -> str:
    """`fold zara2`, `folds univ, zara2`; runs without a fold are "the test set" (alone) or named beside them."""
    folds = set(folds)
    names = sorted(f for f in folds if f is not None)
    parts = [f"fold{'s' if len(names) > 1 else ''} {', '.join(names)}"] if names else []
    if None in folds:
        parts.append("the runs without a fold" if names else "the test set")
    return " and ".join(parts)


def fold_mean(per_fold: pl.DataFrame, model: str, metric: str, folds: set[str | None] | None = None) -> float | None:
    """A model's mean over folds of its per-fold means (over seeds) of `metric`: each fold counts once, however many
    seeds it has, as the paper averages locations. Over `folds` only when given; None when one lacks the metric."""
    part = per_fold.filter((pl.col("model") == model) & (pl.col("metric") == metric))
    means = {row["fold"]: row["mean"] for row in part.iter_rows(named=True)}
    wanted = set(means) if folds is None else folds
    if not wanted or not wanted <= set(means):
        return None
    return sum(means[f] for f in wanted) / len(wanted)


def targets(per_fold: pl.DataFrame, dataset: str, expected: set[str | None] | None = None) -> list[str]:
    """Plain sentences: does our TrajFlow mean (over folds of the per-fold means) meet (≤) the paper's value?

    `per_fold` is :func:`fold_stats` for one dataset. The paper's values are means over every fold: where TrajFlow
    has no run on some of the `expected` folds (planned, or evaluated for another model), its mean over the
    others is shown and not judged.
    """
    paper = PAPER_TRAJFLOW.get(dataset)
    if paper is None:
        return [f"The paper reports no TrajFlow results for `{dataset}`; no targets to check."]
    have = model_folds(per_fold).get(OUR_TRAJFLOW)
    if not have:
        return ["No TrajFlow (`trajflow`) runs for this dataset; the paper targets were not checked."]
    missing = (expected or set()) - have
    lines = []
    for spec in metric_columns(list(paper)):
        if spec.name not in paper:
            continue
        target, value = paper[spec.name], fold_mean(per_fold, OUR_TRAJFLOW, spec.name)
        if value is None:
            lines.append(f"{spec.label}: not evaluated (paper {target:g}).")
        elif missing:
            lines.append(f"{spec.label}: NOT CHECKED — no TrajFlow run on {fold_list(missing)} yet; our TrajFlow "
                         f"{value:.4g} on {fold_list(have)}, paper {target:g} over all of them.")
        elif math.isfinite(value) and value <= target:
            lines.append(f"{spec.label}: MET — our TrajFlow {value:.4g} ≤ paper {target:g}.")
        elif not math.isfinite(value):
            lines.append(f"{spec.label}: NOT MET — our TrajFlow mean is {value} (paper {target:g}).")
        else:
            lines.append(f"{spec.label}: NOT MET — our TrajFlow {value:.4g} > paper {target:g}.")
    return lines


#: The paper's claims about TrajFlow against the other models: a better distribution fit than its ablation and
#: FloMo, by NLL and JSD on the synthetic sets and by both NLLs, indep and joint, on ETH/UCY (section VI).
CLAIMED_BETTER_ON = ("nll", "nll_joint", "jsd")


def comparisons(per_fold: pl.DataFrame) -> list[str]:
    """Plain sentences: is our TrajFlow better (lower) than each other model, on each metric the paper claims it is
    (NLL, JSD) and both were evaluated on? `per_fold` is :func:`fold_stats` for one dataset; each model's value is
    its mean over folds of the per-fold means. Where the two models' runs cover different folds, both are compared
    on the folds they share (a mean over other folds is not comparable), and the sentence says which."""
    folds = model_folds(per_fold)
    others = [m for m in model_order(list(folds)) if m != OUR_TRAJFLOW]
    present = per_fold.get_column("metric").unique().to_list()
    specs = [spec for spec in metric_columns(present) if spec.name in CLAIMED_BETTER_ON]
    ours_folds = folds.get(OUR_TRAJFLOW, set())
    lines = []
    for other in others:
        shared = ours_folds & folds[other]
        where = ""
        if shared != ours_folds or shared != folds[other]:
            only = "the only one" if len(shared) == 1 else "the only ones"
            where = f" (on {fold_list(shared)}, {only} both have runs on)"
        for spec in specs:
            ours = fold_mean(per_fold, OUR_TRAJFLOW, spec.name, shared)
            theirs = fold_mean(per_fold, other, spec.name, shared)
            if ours is None or theirs is None:
                continue
            better = math.isfinite(ours) and (not math.isfinite(theirs) or ours < theirs)
            verdict = "BETTER" if better else "NOT BETTER"
            lines.append(f"{spec.label} vs {model_label(other)}: {verdict} — our TrajFlow "
                         f"{format_value(ours, spec.decimals)}, {model_label(other)} "
                         f"{format_value(theirs, spec.decimals)}{where}.")
        if specs and ours_folds and not shared:
            lines.append(f"{model_label(other)}: not compared with TrajFlow — it has no run on a fold TrajFlow "
                         f"has ({fold_list(ours_folds)}).")
    return lines
