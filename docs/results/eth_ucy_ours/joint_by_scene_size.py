"""Where a fold's joint NLL comes from: the per-scene joint NLL rows of published runs, by scene size (the figures
in README.md).

    python docs/results/eth_ucy_ours/joint_by_scene_size.py docs/results/eth_ucy_ours/models/trajflow-univ-s{0,1,2}

A scene is a group of agents predicted together (one `nll_joint` row; its `agent_index` is the group's first
agent, so group sizes follow from consecutive rows). For each run it prints the mean joint NLL per size bin, each
bin's share of the fold's mean (the bin's sum over all scenes), and how the scene's joint NLL relates to the sum of
its agents' indep NLLs (`nll` rows): their correlation over scenes and the median gap.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import polars as pl

#: upper bounds of the scene-size bins (agents)
SIZE_BINS = [1, 5, 10, 20, 40, 60]


def scenes(run: Path) -> pl.DataFrame:
    """Per scene of a published run: its first agent, size, joint NLL and the sum of its agents' indep NLLs."""
    path = run / "eval" / "metrics.parquet"
    if not path.is_file():
        raise SystemExit(f"error: {path}: no published evaluation")
    rows = pl.read_parquet(path).filter(~pl.col("aggregate"))
    indep = rows.filter(pl.col("metric") == "nll").select("agent_index", indep="value").sort("agent_index")
    joint = rows.filter(pl.col("metric") == "nll_joint").select("agent_index", joint="value").sort("agent_index")
    if indep.is_empty() or joint.is_empty():
        raise SystemExit(f"error: {path}: no per-agent nll or per-scene nll_joint rows")
    joint = joint.with_columns(size=pl.col("agent_index").shift(-1, fill_value=indep.height) - pl.col("agent_index"))
    members = indep.join_asof(joint.select("agent_index", first=pl.col("agent_index")), on="agent_index")
    sums = members.group_by("first").agg(indep_sum=pl.col("indep").sum())
    return joint.join(sums, left_on="agent_index", right_on="first")


def size_bin(size: pl.Expr) -> pl.Expr:
    """The label of SIZE_BINS' bin a scene size falls in ("11-20" agents; "61+" past the last bound)."""
    label = pl.lit(f"{SIZE_BINS[-1] + 1}+")
    for low, high in reversed(list(zip([0, *SIZE_BINS[:-1]], SIZE_BINS))):
        label = pl.when(size <= high).then(pl.lit(f"{low + 1}-{high}")).otherwise(label)
    return label


def summary(run: Path) -> tuple[pl.DataFrame, str]:
    """The run's per-bin table (scenes, agents, mean joint NLL, share of the fold's mean) and a one-line note."""
    table = scenes(run)
    n = table.height
    bins = (table.with_columns(bin=size_bin(pl.col("size")))
            .group_by("bin").agg(scenes=pl.len(), agents=pl.col("size").sum(), mean_joint=pl.col("joint").mean(),
                                 share_of_fold_mean=pl.col("joint").sum() / n, smallest=pl.col("size").min())
            .sort("smallest").drop("smallest"))
    corr = table.select(pl.corr("joint", "indep_sum")).item()
    gap = (table["joint"] - table["indep_sum"]).median()
    note = (f"{run.name}: fold mean {table['joint'].mean():.2f} over {n} scenes; corr(joint, sum of indep) "
            f"{corr:.2f}; median joint minus sum of indep {gap:+.1f}")
    return bins, note


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="published run folders (models/<run>)")
    args = parser.parse_args()
    with pl.Config(tbl_rows=20, float_precision=1):
        for run in args.runs:
            bins, note = summary(run)
            print(note)
            print(bins)


if __name__ == "__main__":
    main()
