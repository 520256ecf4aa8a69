"""Per fold (seed means) and over folds (fold means of seed means), the aggregate metrics of published ETH/UCY
folders side by side, and per run the difference of the second from the first.

    python docs/results/eth_ucy_sample_threshold/compare.py docs/results/eth_ucy_ours_temperature \\
        docs/results/eth_ucy_sample_threshold
"""

from __future__ import annotations

import sys
from pathlib import Path

import polars as pl

METRICS = ["min_ade", "min_fde", "min_ade_joint", "min_fde_joint", "nll", "nll_joint"]


def aggregate_rows(folder: Path) -> pl.DataFrame:
    """One row per run (run, fold, seed) with a column per metric, from the folder's metrics.parquet."""
    rows = pl.read_parquet(folder / "metrics.parquet").filter(pl.col("aggregate") & pl.col("metric").is_in(METRICS))
    return rows.pivot("metric", index=["run", "fold", "seed"], values="value").select("run", "fold", "seed", *METRICS)


def fold_means(runs: pl.DataFrame) -> pl.DataFrame:
    """Seed means per fold, then a row "mean" of those over the folds."""
    folds = runs.group_by("fold").agg(pl.len().alias("seeds"), *[pl.col(m).mean() for m in METRICS]).sort("fold")
    overall = folds.select(pl.lit("mean").alias("fold"), pl.col("seeds").sum(), *[pl.col(m).mean() for m in METRICS])
    return pl.concat([folds, overall.cast(folds.schema)])


def main(first: Path, second: Path) -> None:
    a, b = aggregate_rows(first), aggregate_rows(second)
    with pl.Config(tbl_rows=40, tbl_cols=12, float_precision=3, tbl_width_chars=160):
        for name, runs in ((first.name, a), (second.name, b)):
            print(name)
            print(fold_means(runs))
        pairs = a.join(b, on=["run", "fold", "seed"], suffix="_b").sort("fold", "seed")
        print(f"{second.name} minus {first.name}, per run")
        print(pairs.select("run", *[(pl.col(f"{m}_b") - pl.col(m)).alias(m) for m in METRICS]))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
