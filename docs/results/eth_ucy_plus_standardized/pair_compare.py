"""Twin runs of two published experiments, agent by agent and scene by scene (the tables in README.md).

    python docs/results/eth_ucy_plus_standardized/pair_compare.py \
        docs/results/eth_ucy_ours docs/results/eth_ucy_plus_standardized univ-s1 univ-s2 zara1-s2 zara2-s2

For each FOLD-SEED it reads `models/trajflow-FOLD-SEED/eval/metrics.parquet` of both folders (published
evaluations keep the per-agent `nll` and per-scene `nll_joint` rows) and prints, for B minus A (negative: B
better), the share of agents / scenes where B is better, the median and the 10 % / 90 % quantiles of the
difference, the means, and each side's worst value. A pair says something about B's settings only if both runs
share everything else, the autoencoder included (README.md: same seed, same code, same CPU).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import polars as pl

#: metric -> the key that identifies one row of it within a run (an agent's problem, or a scene's group)
PER_ROW_KEYS = {"nll": "sample_id", "nll_joint": "group_key"}


def per_row(folder: Path, run: str, metric: str) -> pl.DataFrame:
    """The non-aggregate rows of one metric of a published run, keyed by problem or group and agent."""
    path = folder / "models" / run / "eval" / "metrics.parquet"
    if not path.is_file():
        raise SystemExit(f"error: {path}: no published evaluation of {run} in {folder}")
    key = PER_ROW_KEYS[metric]
    return (pl.read_parquet(path)
            .filter(~pl.col("aggregate") & (pl.col("metric") == metric))
            .select(key, "agent_index", "value"))


def compare(a: Path, b: Path, fold_seed: str) -> list[str]:
    """One line per metric: how B's rows differ from A's on the twin run `trajflow-FOLD-SEED`."""
    run = f"trajflow-{fold_seed}"
    lines = []
    for metric, key in PER_ROW_KEYS.items():
        joined = (per_row(a, run, metric).rename({"value": "a"})
                  .join(per_row(b, run, metric).rename({"value": "b"}), on=[key, "agent_index"], how="inner")
                  .with_columns(diff=pl.col("b") - pl.col("a")))
        if joined.is_empty():
            raise SystemExit(f"error: {run}: no {metric} rows in common between {a} and {b}")
        s = joined.select(
            n=pl.len(), better=(pl.col("diff") < 0).mean(), median=pl.col("diff").median(),
            q10=pl.col("diff").quantile(0.1), q90=pl.col("diff").quantile(0.9),
            mean_a=pl.col("a").mean(), mean_b=pl.col("b").mean(), max_a=pl.col("a").max(), max_b=pl.col("b").max(),
        ).row(0, named=True)
        lines.append(f"{fold_seed} {metric}: {s['n']} rows, B better on {s['better']:.0%}, diff median "
                     f"{s['median']:+.2f}, q10 {s['q10']:+.1f}, q90 {s['q90']:+.1f}; mean A {s['mean_a']:.2f} "
                     f"B {s['mean_b']:.2f}; worst A {s['max_a']:.0f} B {s['max_b']:.0f}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path, help="published folder A (e.g. docs/results/eth_ucy_ours)")
    parser.add_argument("b", type=Path, help="published folder B, the changed settings")
    parser.add_argument("pairs", nargs="+", help="FOLD-SEED of twin runs, e.g. univ-s1")
    args = parser.parse_args()
    for fold_seed in args.pairs:
        print(*compare(args.a, args.b, fold_seed), sep="\n")


if __name__ == "__main__":
    main()
