"""Publish an experiment's results into docs/results/<name>: the report, the config, the aggregate metric rows and
the trained models of its finished runs (what this repository commits; the draws and checkpoints stay out).

    python docs/results/publish.py runs/paper/eth_ucy docs/results/eth_ucy

Runs `trajflow report EXP -o OUT`, then writes beside the report:
- `config.toml`: the experiment's config, as the experiment saved it;
- `metrics.parquet`: the aggregate rows (`aggregate = true`) of the experiment's metrics, the numbers the report
  tables show (the per-agent rows are megabytes and are rewritten by the experiment);
- `models/<run>/`: `run.json`, `config.toml`, `train_log.parquet` and `final/` of every finished run, so that
  each number can be recomputed with `trajflow eval` without training again (see `models/README.md`).
The models directory is rebuilt from the finished runs each time; `models/README.md` is kept as it is.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import polars as pl

from trajflow_pipeline.stages.report import report
from trajflow_pipeline.util.atomic import atomic_directory

#: what of a run directory is published: its description, config, training log and final weights
RUN_FILES = ("run.json", "config.toml", "train_log.parquet")
FINAL_FILES = ("model.json", "model.safetensors")


def publish_run(run: Path, target: Path) -> None:
    """Copy what is published of the finished run `run` (RUN_FILES and final/) into the new directory `target`."""
    (target / "final").mkdir(parents=True)
    for name in RUN_FILES:
        shutil.copy2(run / name, target / name)
    for name in FINAL_FILES:
        shutil.copy2(run / "final" / name, target / "final" / name)


def publish_models(experiment: Path, models: Path) -> list[str]:
    """Rebuild `models/` from the experiment's finished runs (experiment.json `runs`); returns their names."""
    finished = json.loads((experiment / "experiment.json").read_text())["runs"]
    with atomic_directory(models) as staging:
        for relative in finished:
            publish_run(experiment / relative, staging / Path(relative).name)
        if (models / "README.md").is_file():
            shutil.copy2(models / "README.md", staging / "README.md")
    return [Path(r).name for r in finished]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", type=Path, help="experiment directory (trajflow experiment -o)")
    parser.add_argument("out", type=Path, help="results directory, e.g. docs/results/eth_ucy")
    args = parser.parse_args()
    report([args.experiment], args.out, quiet=True)
    shutil.copy2(args.experiment / "config.toml", args.out / "config.toml")
    aggregate = pl.read_parquet(args.experiment / "metrics.parquet").filter(pl.col("aggregate"))
    aggregate.write_parquet(args.out / "metrics.parquet")
    runs = publish_models(args.experiment, args.out / "models")
    print(f"published {args.out}: report, config, {aggregate.height} aggregate metric rows, {len(runs)} models")


if __name__ == "__main__":
    main()
