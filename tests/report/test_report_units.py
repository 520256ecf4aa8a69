"""Report building blocks on hand-computed cases: minADE(K), number formatting, escaping, example choice, PNGs."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from trajflow_pipeline.errors import DataError
from trajflow_pipeline.report.curves import ade_per_draw, expected_min_curve, subset_min_weights
from trajflow_pipeline.report.document import Cell, Code, Figure, Heading, Paragraph, Table
from trajflow_pipeline.report import figures
from trajflow_pipeline.report.figures import kde_colours, plot_min_ade_k, relative_scale
from trajflow_pipeline.report.paper import METRICS, metric_columns
from trajflow_pipeline.report.render import to_html, to_markdown
from trajflow_pipeline.report.scenes import choose_examples
from trajflow_pipeline.report.tables import (comparisons, fold_list, fold_stats, format_mean_std, summary_stats,
                                              targets, uneven_seeds)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_expected_min_matches_brute_force_over_subsets() -> None:
    ade = np.array([[0.4, 0.1, 0.3, 0.2, 0.9], [1.0, 2.0, 0.5, 0.5, 3.0]])
    draws = ade.shape[1]
    brute = [np.mean([ade[:, list(subset)].min(axis=1) for subset in itertools.combinations(range(draws), k)],
                     axis=0).mean() for k in range(1, draws + 1)]
    curve = expected_min_curve(ade)
    np.testing.assert_allclose(curve, brute)
    assert curve[0] == pytest.approx(ade.mean()) and curve[-1] == pytest.approx(ade.min(axis=1).mean())
    np.testing.assert_allclose(subset_min_weights(100).sum(axis=1), 1.0)


def test_ade_per_draw_uses_the_common_horizon() -> None:
    gt = pl.LazyFrame({"sample_id": [7] * 4, "step": [-1, 0, 1, 2], "x": [-1.0, 0.0, 1.0, 2.0],
                       "y": [0.0] * 4})
    # two draws, three predicted steps (one beyond the ground truth): ADE over steps 1..2 only
    predictions = pl.LazyFrame({"sample_id": [7] * 6, "draw": [0, 0, 0, 1, 1, 1], "step": [1, 2, 3] * 2,
                                "x": [1.0, 2.0, 99.0, 1.0, 2.0, 3.0], "y": [0.0, 0.0, 0.0, 3.0, 4.0, 0.0]})
    np.testing.assert_allclose(ade_per_draw(predictions, gt, Path("p")), [[0.0, 3.5]])
    ragged = predictions.filter(~((pl.col("draw") == 1) & (pl.col("sample_id") == 7)))
    more = pl.concat([ragged, predictions.with_columns(sample_id=pl.lit(8, pl.Int64))])
    with pytest.raises(DataError, match="different numbers of draws"):
        ade_per_draw(more, pl.concat([gt, gt.with_columns(sample_id=pl.lit(8, pl.Int64))]), Path("p"))


def test_mean_std_formatting_and_stats() -> None:
    frame = pl.DataFrame({"dataset": ["d"] * 3, "model": ["m"] * 3, "metric": ["nll"] * 3,
                          "value": [-1.0, -2.0, -3.0]})
    row = summary_stats(frame).row(0, named=True)
    assert row["mean"] == pytest.approx(-2.0) and row["std"] == pytest.approx(np.std([-1, -2, -3]))
    assert format_mean_std(row["mean"], row["std"], row["runs"], 2) == "-2.00 ± 0.82"
    assert format_mean_std(0.5, None, 1, 3) == "0.500" and format_mean_std(None, None, 0, 3) == "—"


def test_choose_examples_spreads_samples_and_takes_one_per_group() -> None:
    single = pl.DataFrame({"sample_id": np.repeat(np.arange(10), 3), "group_id": np.repeat(np.arange(10), 3)})
    assert choose_examples(single, 3) == [0, 4, 9]  # evenly spread over the sorted sample ids
    grouped = pl.DataFrame({"sample_id": np.arange(12), "group_id": np.repeat([5, 1, 9], 4)})
    assert choose_examples(grouped, 4) == [4, 0, 8]  # first sample of each group, groups in id order
    assert choose_examples(grouped, 0) == []


def test_markdown_and_html_escape_text_and_keep_code() -> None:
    blocks = [Heading(1, "runs <of> *x*"), Paragraph("see `a|b` and a <tag>"),
              Table(header=("model", "v"), rows=((Cell("a|b"), Cell("1.0", bold=True)),), numeric=(False, True)),
              Code('{"k": "<v>"}', "json", "config of `r`"),
              Figure("figures/f.png", PNG_SIGNATURE + b"xx", "short", "long caption")]
    markdown, html = to_markdown(blocks), to_html(blocks, "t")
    assert "# runs \\<of> \\*x\\*" in markdown and "see `a|b` and a \\<tag>" in markdown
    assert "| a\\|b | **1.0** |" in markdown and "|:---|---:|" in markdown
    assert '```json\n{"k": "<v>"}\n```' in markdown and "![short](figures/f.png)" in markdown
    assert "runs &lt;of&gt; *x*" in html and "<code>a|b</code>" in html and "<strong>1.0</strong>" in html
    assert "<details><summary>config of <code>r</code></summary>" in html and "&lt;v&gt;" in html
    assert 'src="data:image/png;base64,iVBORw0KGgp4eA=="' in html


def test_figure_helpers_handle_degenerate_input() -> None:
    assert relative_scale(np.array([np.nan, np.inf])).tolist() == [0.0, 0.0]
    np.testing.assert_allclose(relative_scale(np.array([1.0, 1.0])), [1.0, 1.0])
    assert kde_colours(np.zeros((50, 2))).tolist() == [1.0] * 50  # singular covariance: no density
    png = plot_min_ade_k([("cv", np.array([0.5]), None)], 1, "one draw")
    assert png.startswith(PNG_SIGNATURE) and len(png) > 1000


def test_training_figure_marks_the_one_epoch_of_a_closed_form_stage(monkeypatch: pytest.MonkeyPatch) -> None:
    """A closed-form stage (here "temperature": no training loss, its validation NLL) is one epoch per run: drawn
    as a point, which a line alone would leave invisible; gradient stages stay lines."""
    monkeypatch.setattr(figures, "to_png", lambda figure: figure)
    log = pl.DataFrame({"epoch": [1, 2, 3, 1], "stage": ["flow", "flow", "flow", "temperature"],
                        "train_loss": [-1.0, -2.0, -3.0, float("nan")], "val_loss": [-0.5, -1.5, -2.5, -24.6]})
    figure = figures.plot_training([("run a", log)], "training")
    flow, temperature = figure.axes[:2]
    assert [line.get_marker() for line in flow.get_lines()] == ["None", "None"]
    assert [line.get_marker() for line in temperature.get_lines()] == ["o", "o"]
    assert temperature.get_lines()[1].get_ydata().tolist() == [-24.6] and temperature.get_xticks().tolist() == [1]


def test_extended_horizon_metrics_get_labelled_columns_after_the_standard_ones() -> None:
    columns = metric_columns(["min_ade", "nll_ext_long", "min_ade_ext", "custom", "min_fde_ext"])
    names = [spec.name for spec in columns]
    assert names[:len(METRICS)] == [spec.name for spec in METRICS]
    assert names[len(METRICS):] == ["min_ade_ext", "min_fde_ext", "nll_ext_long", "custom"]
    labels = {spec.name: spec.label for spec in columns}
    assert labels["min_ade_ext"] == "minADE (to own horizon)"
    assert labels["nll_ext_long"] == "NLL indep (to own horizon, long samples only)"
    assert labels["custom"] == "custom"


def test_comparisons_say_where_trajflow_is_and_is_not_better() -> None:
    runs = {("trajflow", 0): (-41.0, 0.40, 0.10), ("trajflow", 1): (-39.0, 0.20, 0.12),
            ("trajflow-no-ae", 0): (-41.5, 0.50, 0.09), ("flomo", 0): (-38.0, 0.70, 0.15),
            ("cv", 0): (16.0, 1.0, 0.65)}
    metrics = pl.DataFrame(
        [{"dataset": "synthetic_bimodal", "model": model, "run": f"{model}-s{seed}", "metric": metric, "value": value}
         for (model, seed), values in runs.items() for metric, value in zip(("nll", "jsd", "min_ade"), values)])
    metrics = metrics.with_columns(fold=pl.lit(None, pl.String))
    lines = comparisons(fold_stats(metrics))
    # TrajFlow's means: NLL -40.0, JSD 0.30 (minADE is not a claimed metric, so it is not compared).
    assert lines == [
        "NLL indep vs TrajFlow w/o AE: NOT BETTER — our TrajFlow -40.00, TrajFlow w/o AE -41.50.",
        "JSD vs TrajFlow w/o AE: BETTER — our TrajFlow 0.300, TrajFlow w/o AE 0.500.",
        "NLL indep vs FloMo: BETTER — our TrajFlow -40.00, FloMo -38.00.",
        "JSD vs FloMo: BETTER — our TrajFlow 0.300, FloMo 0.700.",
        "NLL indep vs Constant velocity: BETTER — our TrajFlow -40.00, Constant velocity 16.00.",
        "JSD vs Constant velocity: BETTER — our TrajFlow 0.300, Constant velocity 1.000.",
    ]
    flomo = metrics.filter(pl.col("model") == "flomo")
    assert comparisons(fold_stats(flomo)) == []


def _fold_metrics(values: dict[tuple[str, str | None, int], float]) -> pl.DataFrame:
    """Aggregate NLL rows of ETH/UCY-like runs: (model, fold, seed) -> value."""
    return pl.DataFrame([{"dataset": "eth_ucy", "model": model, "run": f"{model}-{fold}-s{seed}", "fold": fold,
                          "seed": seed, "metric": "nll", "value": value}
                         for (model, fold, seed), value in values.items()], schema_overrides={"fold": pl.String})


def test_models_with_different_folds_are_compared_on_the_shared_ones_and_targets_wait_for_every_fold() -> None:
    per_fold = fold_stats(_fold_metrics({
        ("trajflow", "eth", 0): -1.0, ("trajflow", "hotel", 0): -26.0, ("trajflow", "univ", 0): -22.0,
        ("cv", "eth", 0): 10.0, ("cv", "hotel", 0): 50.0, ("flomo", "zara1", 0): -30.0}))
    # TrajFlow's eth + hotel mean is -13.5 (its mean over its three folds, -16.33, is not comparable); FloMo shares
    # no fold with it.
    assert comparisons(per_fold) == [
        "FloMo: not compared with TrajFlow — it has no run on a fold TrajFlow has (folds eth, hotel, univ).",
        "NLL indep vs Constant velocity: BETTER — our TrajFlow -13.50, Constant velocity 30.00 (on folds eth, "
        "hotel, the only ones both have runs on).",
    ]
    expected = {"eth", "hotel", "univ", "zara1", "zara2"}
    assert targets(per_fold, "eth_ucy", expected)[2] == (
        "NLL indep: NOT CHECKED — no TrajFlow run on folds zara1, zara2 yet; our TrajFlow -16.33 on folds eth, "
        "hotel, univ, paper -21.05 over all of them.")
    assert targets(per_fold, "eth_ucy")[2] == "NLL indep: NOT MET — our TrajFlow -16.33 > paper -21.05."


def test_every_fold_counts_once_however_many_seeds_it_has() -> None:
    # TrajFlow is better than cv on both folds; eth has three TrajFlow seeds, hotel one. The mean over runs (-7.25)
    # would say otherwise; the mean over folds (-13.5) does not.
    per_fold = fold_stats(_fold_metrics({
        ("trajflow", "eth", 0): -1.0, ("trajflow", "eth", 1): -1.0, ("trajflow", "eth", 2): -1.0,
        ("trajflow", "hotel", 0): -26.0, ("cv", "eth", 0): 0.0, ("cv", "hotel", 0): -20.0}))
    assert comparisons(per_fold) == [
        "NLL indep vs Constant velocity: BETTER — our TrajFlow -13.50, Constant velocity -10.00."]
    assert uneven_seeds(per_fold) == {"trajflow": {"eth": 3, "hotel": 1}}
    # -30 on eth (3 seeds) and -10 on hotel: a run mean of -25 would pass the paper's -21.05; the fold mean -20 fails
    skewed = fold_stats(_fold_metrics({("trajflow", "eth", s): -30.0 for s in range(3)} | {
        ("trajflow", "hotel", 0): -10.0}))
    assert targets(skewed, "eth_ucy", {"eth", "hotel"})[2] == "NLL indep: NOT MET — our TrajFlow -20 > paper -21.05."


def test_the_joint_nll_is_compared_too() -> None:
    """On ETH/UCY the paper claims TrajFlow's distribution fit is better by both NLLs."""
    metrics = _fold_metrics({("trajflow", "eth", 0): -60.0, ("cv", "eth", 0): 85.0}).with_columns(
        metric=pl.lit("nll_joint"))
    assert comparisons(fold_stats(metrics)) == [
        "NLL joint vs Constant velocity: BETTER — our TrajFlow -60.00, Constant velocity 85.00."]


def test_fold_lists_name_runs_without_a_fold() -> None:
    assert fold_list(["zara2"]) == "fold zara2"
    assert fold_list(["zara2", "univ", "univ"]) == "folds univ, zara2"
    assert fold_list([None]) == "the test set"
    assert fold_list([None, "eth"]) == "fold eth and the runs without a fold"


def test_provenance_names_the_code_that_trained_and_evaluated_a_run() -> None:
    from trajflow_pipeline.stages.report import _code_text

    a, b = "a" * 40, "b" * 40
    assert _code_text({"trajflow_version": "0.1.0"}) == "0.1.0"
    assert _code_text({"trajflow_version": "0.1.0", "code_revision": a, "training_code_revisions": [a]}) == (
        "0.1.0 (aaaaaaaaaaaa)")
    assert _code_text({"trajflow_version": "0.1.0", "code_revision": f"{b}+changes.0123456789ab",
                       "training_code_revisions": ["unrecorded", a]}) == (
        "0.1.0 (trained by unrecorded, aaaaaaaaaaaa; evaluated by bbbbbbbbbbbb+changes.0123456789ab)")
