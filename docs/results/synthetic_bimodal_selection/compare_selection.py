"""Compare the two ways of keeping flow weights on the same trainings: for every finished run of an experiment
trained with train.flow_select=val_nll, evaluate (in a copy of the run) the weights the default, val_loss,
would have kept (checkpoints/lowest-val-loss-flow.safetensors), then tabulate both runs' aggregate metrics.

    python docs/results/synthetic_bimodal_selection/compare_selection.py EXP OUT   # writes OUT/selection.parquet
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import polars as pl

from trajflow_pipeline.stages.evaluate import EVAL_DIR, evaluate
from trajflow_pipeline.stages.experiment import load_experiment


def main(exp: Path, out: Path) -> None:
    config = load_experiment(exp / "config.toml")
    data = Path(json.loads((exp / "experiment.json").read_text())["data"])
    rows = []
    for run in sorted((exp / "runs").iterdir()):
        by_loss = run / "checkpoints" / "lowest-val-loss-flow.safetensors"
        if not run.is_dir() or not (run / EVAL_DIR / "metrics.parquet").exists() or not by_loss.exists():
            continue
        copy = out / "runs" / run.name
        if not (copy / EVAL_DIR / "metrics.parquet").exists():
            shutil.rmtree(copy, ignore_errors=True)
            shutil.copytree(run, copy, ignore=shutil.ignore_patterns(EVAL_DIR))
            shutil.copyfile(by_loss, copy / "final" / "model.safetensors")
            evaluate(copy, data=data, options=config.eval_options, quiet=True)
        best = json.loads((run / "run.json").read_text())["best"]["flow"]
        for selection, directory in (("val_nll", run), ("val_loss", copy)):
            metrics = pl.read_parquet(directory / EVAL_DIR / "metrics.parquet").filter(pl.col("aggregate"))
            rows.append({"run": run.name, "selection": selection,
                         "epoch": best["epoch"] if selection == "val_nll" else best["lowest_val_loss_epoch"],
                         **dict(zip(metrics.get_column("metric"), metrics.get_column("value")))})
    table = pl.DataFrame(rows)
    table.write_parquet(out / "selection.parquet")
    with pl.Config(tbl_rows=100, tbl_cols=20):
        print(table.select("run", "selection", "epoch", "min_ade", "min_fde", "nll", "jsd"))
        print(table.group_by("selection").agg(pl.len(), pl.col("min_ade", "min_fde", "nll", "jsd").mean(),
                                              pl.col("jsd").std().alias("jsd_std")))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
