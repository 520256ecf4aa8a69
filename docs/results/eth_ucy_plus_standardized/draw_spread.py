"""How wide and how well centred the draws of published runs are on their test location (README.md, "Wider
draws, not sharper").

    python docs/results/eth_ucy_plus_standardized/draw_spread.py zara1-s2 docs/results/eth_ucy_ours \
        docs/results/eth_ucy_plus_standardized docs/results/eth_ucy_plus_standardized_tail15

For each published folder it copies `models/trajflow-FOLD-SEED` (without its evaluation) to a temporary folder,
draws the test futures again with `trajflow eval`'s defaults (100 draws, seed 0; minADE / minFDE only, no ROME
fit) and prints, at the last predicted step: the spread (the mean distance of the 100 draws from their centroid),
the centroid's distance from the ground truth, and minFDE over the first 20 draws, as means over the test agents,
overall and by thirds of the agents' ground-truth travel over the horizon (shortest to longest).

With `--temperature T` (repeatable) it draws with the flow's base N(0, T^2 I) instead, by writing
`model.flow_temperature = T` into the copy's model: a diagnostic of how much of a gap the draws' width explains.
It is chosen here on the test location, so it is never a method, and it is refused for runs whose temperature
was fitted (`model.flow_temperature_grid`).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
from pathlib import Path

import polars as pl

from trajflow_pipeline.model.checkpoint import load_model, read_model_metadata, save_model
from trajflow_pipeline.rundir import EVAL_DIR, FINAL_DIR, GROUND_TRUTH_FILE, PREDICTIONS_FILE
from trajflow_pipeline.stages.evaluate import EvalOptions, evaluate

K = 20


def distance(x: str, y: str, to_x: str, to_y: str) -> pl.Expr:
    """Euclidean distance between the points of columns (x, y) and (to_x, to_y)."""
    return ((pl.col(x) - pl.col(to_x)) ** 2 + (pl.col(y) - pl.col(to_y)) ** 2).sqrt()


def final_step_figures(eval_dir: Path) -> pl.DataFrame:
    """One row per test agent: spread, centroid error and minFDE_K of its draws at the last step, and its travel."""
    draws = pl.scan_parquet(eval_dir / PREDICTIONS_FILE)
    truth = pl.scan_parquet(eval_dir / GROUND_TRUTH_FILE)
    last = draws.select(pl.col("step").max()).collect().item()
    final = draws.filter(pl.col("step") == last)
    truth_end = truth.filter(pl.col("step") == last).select("sample_id", gx="x", gy="y")
    truth_start = truth.filter(pl.col("step") == 0).select("sample_id", sx="x", sy="y")
    return (final.join(truth_end, on="sample_id")
            .with_columns(cx=pl.col("x").mean().over("sample_id"), cy=pl.col("y").mean().over("sample_id"))
            .group_by("sample_id")
            .agg(spread=distance("x", "y", "cx", "cy").mean(),
                 centroid_error=distance("cx", "cy", "gx", "gy").first(),
                 min_fde=distance("x", "y", "gx", "gy").filter(pl.col("draw") < K).min(),
                 gx=pl.col("gx").first(), gy=pl.col("gy").first())
            .join(truth_start, on="sample_id")
            .with_columns(travel=distance("gx", "gy", "sx", "sy"))
            .select("sample_id", "spread", "centroid_error", "min_fde", "travel")
            .collect())


def summary(per_agent: pl.DataFrame) -> str:
    """Means overall and by thirds of travel, as one line."""
    figures = ("spread", "centroid_error", "min_fde")
    thirds = (per_agent.with_columns(third=(pl.col("travel").rank("ordinal") * 3 // (per_agent.height + 1)))
              .group_by("third").agg(pl.col(figures).mean()).sort("third"))
    overall = per_agent.select(pl.col(figures).mean()).row(0)
    by_third = "; ".join(f"{r[1]:.3f} / {r[2]:.3f} / {r[3]:.3f}" for r in thirds.iter_rows())
    return (f"{per_agent.height} agents, spread / centroid error / minFDE_{K}: {overall[0]:.3f} / {overall[1]:.3f} / "
            f"{overall[2]:.3f} m; by thirds of travel: {by_third}")


def set_temperature(run: Path, temperature: float) -> None:
    """Rewrite the run's final model with `model.flow_temperature = temperature` (the same weights)."""
    final = run / FINAL_DIR
    model = load_model(final)
    if model.config.flow_temperature_grid:
        raise SystemExit(f"error: {run}: its temperature was fitted (model.flow_temperature_grid); "
                         "--temperature is for runs without that stage")
    model.config = dataclasses.replace(model.config, flow_temperature=temperature)
    save_model(model, final, extra=read_model_metadata(final)["extra"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("fold_seed", help="FOLD-SEED of the run, e.g. zara1-s2")
    parser.add_argument("folders", nargs="+", type=Path, help="published folders holding models/trajflow-FOLD-SEED")
    parser.add_argument("--data", type=Path, default=None, help="the dataset (default: the run's)")
    parser.add_argument("--temperature", type=float, action="append", default=None,
                        help="draw with this base temperature instead of the run's (repeatable; a diagnostic)")
    args = parser.parse_args()
    run = f"trajflow-{args.fold_seed}"
    for folder in args.folders:
        source = folder / "models" / run
        if not source.is_dir():
            raise SystemExit(f"error: {source}: no published run {run} in {folder}")
        for temperature in args.temperature or [None]:
            with tempfile.TemporaryDirectory() as scratch:
                copy = Path(scratch) / run
                shutil.copytree(source, copy, ignore=shutil.ignore_patterns(EVAL_DIR))
                if temperature is not None:
                    set_temperature(copy, temperature)
                eval_dir = evaluate(copy, data=args.data, options=EvalOptions(metrics=("min_ade", "min_fde")),
                                    quiet=True)
                label = folder.name if temperature is None else f"{folder.name}, T = {temperature}"
                print(f"{label}: {summary(final_step_figures(eval_dir))}")


if __name__ == "__main__":
    main()
