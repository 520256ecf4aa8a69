"""Benchmark our ROME shortcuts: seconds per fit with them and with the library as it is, and proof of same numbers.

    python bench/rome_shortcuts.py [--run RUN] [--fits 200] [--rounds 3]

A fit here is what evaluation does per agent: ROME on an agent's drawn futures (samples x 2T flattened positions),
scored at its ground truth and at its own draws. The draws come from an evaluated run (`RUN/eval/predictions.parquet`
and `ground_truth.parquet`, the first `--fits` agents) or, without `--run`, from the synthetic three-mode problems
of bench/eval.py. Each round fits every task twice, alternating the order of the two ways (so that load from other
programs on a shared machine hits both alike): through `fit_and_score` (every shortcut of
trajflow_pipeline.metrics.rome_shortcuts on) and through ROME itself (one BLAS thread and the same seed, as a fit runs
there, nothing else changed). It checks that every log-density is bit-identical and prints the median seconds per
fit of each way and their ratio.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl

from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval import synthetic_problems  # noqa: E402  (bench/eval.py, beside this script)


def run_tasks(run: Path, count: int) -> list[RomeTask]:
    """Per agent of an evaluated run (the first `count` sample ids): its draws and its ground-truth future."""
    predictions = pl.scan_parquet(run / "eval" / "predictions.parquet")
    ids = predictions.select(pl.col("sample_id").unique().sort().head(count)).collect().to_series()
    draws = (predictions.filter(pl.col("sample_id").is_in(ids.implode())).sort("sample_id", "draw", "step")
             .collect())
    truth = (pl.scan_parquet(run / "eval" / "ground_truth.parquet")
             .filter(pl.col("sample_id").is_in(ids.implode()) & (pl.col("step") > 0)).sort("sample_id", "step")
             .collect())
    steps = truth.filter(pl.col("sample_id") == ids[0]).height
    pred = draws.select("x", "y").to_numpy().reshape(len(ids), -1, steps * 2)
    gt = truth.select("x", "y").to_numpy().reshape(len(ids), 1, steps * 2)
    return [RomeTask(fit=pred[i], queries=(gt[i], pred[i]), label=f"sample {ids[i]}") for i in range(len(ids))]


def synthetic_tasks(count: int) -> list[RomeTask]:
    """The synthetic problems of bench/eval.py: 100 draws of 12 steps per agent."""
    pred, gt = synthetic_problems(count, 100, 12)
    flat_pred, flat_gt = pred.reshape(count, 100, -1), gt.reshape(count, 1, -1)
    return [RomeTask(fit=flat_pred[i], queries=(flat_gt[i], flat_pred[i])) for i in range(count)]


def library_fit(task: RomeTask, seed: int) -> tuple[np.ndarray, ...]:
    """ROME as it is, with one BLAS thread and numpy's global RNG seeded as `fit_and_score` seeds it."""
    from rome.ROME import ROME
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        np.random.seed(seed % (2**32))
        model = ROME(min_std=task.min_std).fit(np.ascontiguousarray(task.fit, dtype=np.float64))
        return tuple(np.asarray(model.score_samples(q), dtype=np.float64) for q in task.queries)


def main() -> None:
    """Parse arguments, time both ways in alternating rounds, check equality, print medians and the ratio."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="an evaluated run whose draws to fit (default: synthetic draws)")
    parser.add_argument("--fits", type=int, default=200, help="tasks per round (default 200)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds (default 3)")
    args = parser.parse_args()
    tasks = run_tasks(args.run, args.fits) if args.run else synthetic_tasks(args.fits)
    source = f"{args.run}" if args.run else "synthetic three-mode draws"
    print(f"{len(tasks)} fits of {tasks[0].fit.shape[0]} x {tasks[0].fit.shape[1]} points from {source}, "
          f"{args.rounds} round(s)")
    fit_and_score(tasks[0], 0), library_fit(tasks[0], 0)  # imports and first-call costs outside the timing
    seconds: dict[str, list[float]] = {"shortcuts": [], "library": []}
    ways = {"shortcuts": fit_and_score, "library": library_fit}
    for round_index in range(args.rounds):
        order = ["shortcuts", "library"] if round_index % 2 == 0 else ["library", "shortcuts"]
        results = {}
        for way in order:
            start = time.perf_counter()
            results[way] = [ways[way](task, seed) for seed, task in enumerate(tasks)]
            seconds[way].append((time.perf_counter() - start) / len(tasks))
        for ours, theirs, task in zip(results["shortcuts"], results["library"], tasks):
            if not all(np.array_equal(a, b) for a, b in zip(ours, theirs)):
                raise SystemExit(f"DIFFERENT log-densities for {task.label}: the shortcuts changed a fit")
    fast, slow = statistics.median(seconds["shortcuts"]), statistics.median(seconds["library"])
    print(f"identical log-densities in every round; median s per fit: shortcuts {fast:.4f}, library {slow:.4f}, "
          f"ratio {slow / fast:.2f}x")


if __name__ == "__main__":
    main()
