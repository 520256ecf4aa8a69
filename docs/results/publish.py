"""Publish an experiment's results into docs/results/<name> (what this repository commits), and turn such a folder
back into an experiment directory on another machine, so that the experiment goes on without repeating finished
work.

    python docs/results/publish.py runs/paper/eth_ucy docs/results/eth_ucy
    python docs/results/publish.py --every 15 runs/paper/eth_ucy docs/results/eth_ucy &
    python docs/results/publish.py --restore docs/results/eth_ucy runs/paper/eth_ucy

Publishing runs `trajflow report EXP -o OUT` (once a run is finished), then writes beside the report:
- `config.toml`: the experiment's config, as the experiment saved it (and `config_set.json`, its `--set`
  overrides, where it ran with some);
- `experiment.json`: the experiment's index (its plan and finished runs), as the experiment wrote it;
- `metrics.parquet`: the aggregate rows (`aggregate = true`) of the experiment's metrics, the numbers the report
  tables show;
- `models/<run>/`: of every finished run, `run.json`, `config.toml`, `train_log.parquet` and `final/`, so that each
  number can be recomputed with `trajflow eval` without training again (see `models/README.md`), and its
  evaluation record: `eval/eval.json` and `eval/metrics.parquet` with the rows a report reads (the aggregates and
  the per-agent NLL rows behind the medians; the other per-agent rows and the draws stay out), which is what makes
  a copy count as evaluated;
- `unfinished/<run>/`: of every planned run that is not finished but has something to go on from, what continues
  it: `run.json`, `config.toml`, `train_log.parquet` and `checkpoints/state.pt` (its last epoch's training state)
  for a run in training, or `final/` for one trained and not yet evaluated. Runs without a checkpoint yet (they
  would start again anyway) are left out.
The `models/` and `unfinished/` folders are rebuilt each time; `models/README.md` is kept as it is.

With `--every MINUTES` it publishes again every MINUTES minutes, beside the experiment that is training, until
every planned run is finished (then once more, and it exits): what a lost machine loses is then at most that many
minutes of training, not everything since the last hand-made publish. A round that fails (a run's files changing
under it) says why in one line and the next round tries again.

Restoring builds EXP (which must not exist or be empty) from a published folder: `EXP/runs/<run>/` from `models/`
and `unfinished/`, and the config, index and metrics, so that `trajflow experiment CONFIG -o EXP` with the same
config (or `EXP/config.toml` itself) skips the finished runs (neither trained nor evaluated again), evaluates the
trained ones and resumes each run in training after its last epoch (bit-identical to the run going on, as
`trajflow train --resume`). `trajflow report EXP` and `trajflow status EXP` work on it at once: the tables are the
same; the figures drawn from draws (examples, density, minADE vs K) leave out the runs whose draws were not
published (the report says which), and `trajflow eval EXP/runs/<run>` draws them again. A folder published before
evaluation records were kept restores its runs as trained: the experiment evaluates them, without training.
Resume states are not kept for finished runs, so a restored finished run cannot be given a larger epoch budget.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import time
from collections.abc import Sequence
from pathlib import Path

import polars as pl

from trajflow_pipeline.errors import TrajflowError
from trajflow_pipeline.report.collect import report_rows
from trajflow_pipeline.rundir import (CONFIG_FILE, EVAL_DIR, EVALUATION_RECORD, METRICS_FILE, STATE_FILE,
                                      continuation_files)
from trajflow_pipeline.stages.experiment import INDEX_FILE
from trajflow_pipeline.stages.experiment_config import SAVED_OVERRIDES
from trajflow_pipeline.stages.report import report
from trajflow_pipeline.util import input_files
from trajflow_pipeline.util.atomic import atomic_directory, atomic_file, atomic_write_bytes, atomic_write_text

#: the published folders of runs: the finished ones, and what continues the others
MODELS_DIR = "models"
UNFINISHED_DIR = "unfinished"
#: the experiment directory's folder of runs
RUNS_DIR = "runs"
#: a run's metrics table, relative to the run
RUN_METRICS = f"{EVAL_DIR}/{METRICS_FILE}"


def copy_run(run: Path, target: Path, names: Sequence[str]) -> int:
    """Copy the files `names` (paths relative to the run `run`) into the new directory `target`, the metrics table
    cut to the rows a report reads; returns the bytes written."""
    for name in names:
        destination = target / name
        destination.parent.mkdir(parents=True, exist_ok=True)
        if name == RUN_METRICS:
            input_files.read_parquet(run / name).filter(report_rows()).write_parquet(destination)
        else:
            shutil.copy2(run / name, destination)
    return sum(path.stat().st_size for path in target.rglob("*") if path.is_file())


def publish_runs(experiment: Path, out: Path) -> tuple[dict[str, int], dict[str, int]]:
    """Rebuild `out/models/` from the experiment's finished runs (experiment.json `runs`, evaluated) and
    `out/unfinished/` from its other planned runs that have something to go on from; the bytes published per run,
    finished and unfinished."""
    index = json.loads(input_files.read_text(experiment / INDEX_FILE))
    listed = set(index["runs"])
    finished: dict[str, int] = {}
    unfinished: dict[str, int] = {}
    with atomic_directory(out / MODELS_DIR) as models, atomic_directory(out / UNFINISHED_DIR) as others:
        for relative in index.get("planned") or index["runs"]:
            run = experiment / relative
            names = continuation_files(run) if run.is_dir() else ()
            if relative in listed and set(EVALUATION_RECORD) <= set(names):
                finished[run.name] = copy_run(run, models / run.name, names)
            elif names:
                unfinished[run.name] = copy_run(run, others / run.name, names)
        if (out / MODELS_DIR / "README.md").is_file():
            shutil.copy2(out / MODELS_DIR / "README.md", models / "README.md")
    if not unfinished:
        shutil.rmtree(out / UNFINISHED_DIR)
    return finished, unfinished


def publish(experiment: Path, out: Path) -> str:
    """Publish the experiment in `experiment` into `out` (see the module docstring); a one-line summary."""
    index = json.loads(input_files.read_text(experiment / INDEX_FILE))
    rows = 0
    if index["runs"]:
        report([experiment], out, quiet=True)
    out.mkdir(parents=True, exist_ok=True)
    if index["runs"]:
        aggregate = input_files.read_parquet(experiment / "metrics.parquet").filter(pl.col("aggregate"))
        with atomic_file(out / "metrics.parquet") as tmp:
            aggregate.write_parquet(tmp)
        rows = aggregate.height
    elif not (out / "report.md").is_file():  # also what lets `trajflow report` write over this folder later
        atomic_write_text(out / "report.md", f"# {index.get('name', experiment.name)}\n\nNo run of this "
                          f"experiment is finished yet; `{UNFINISHED_DIR}/` holds what continues the others "
                          "(see ../README.md).\n")
    for name in (CONFIG_FILE, INDEX_FILE, SAVED_OVERRIDES):  # (the --set overrides only where it ran with some)
        if name != SAVED_OVERRIDES or (experiment / name).is_file():
            atomic_write_bytes(out / name, (experiment / name).read_bytes())
    finished, unfinished = publish_runs(experiment, out)
    return (f"published {out}: " + ("report, " if index["runs"] else "no report (no run is finished), ")
            + f"config, index, {rows} aggregate metric rows, {len(finished)} finished runs "
            f"({sum(finished.values()):,} bytes), {len(unfinished)} unfinished runs ({sum(unfinished.values()):,} "
            f"bytes{': ' + ', '.join(f'{name} {size:,}' for name, size in unfinished.items()) if unfinished else ''})")


def restore(results: Path, experiment: Path) -> str:
    """Build the experiment directory `experiment` (new, or empty) from the published folder `results`; a
    one-line summary. A folder that holds no published experiment, or an `experiment` that holds anything, is
    refused (ValueError) before anything is written."""
    if not (results / CONFIG_FILE).is_file():
        raise ValueError(f"{results}: no {CONFIG_FILE}; not a folder this script published")
    if experiment.exists() and (not experiment.is_dir() or any(experiment.iterdir())):
        raise ValueError(f"{experiment}: exists and is not empty; restore into a new directory")
    runs = [run for folder in (MODELS_DIR, UNFINISHED_DIR) if (results / folder).is_dir()
            for run in sorted((results / folder).iterdir()) if run.is_dir()]
    index = json.loads(input_files.read_text(results / INDEX_FILE)) if (results / INDEX_FILE).is_file() else None
    missing = [r for r in (index or {}).get("runs", ()) if not (results / MODELS_DIR / Path(r).name).is_dir()]
    if missing:
        raise ValueError(f"{results / INDEX_FILE}: lists finished runs that {MODELS_DIR}/ lacks ({', '.join(missing)})")
    with atomic_directory(experiment) as staging:
        shutil.copy2(results / CONFIG_FILE, staging / CONFIG_FILE)
        if (results / SAVED_OVERRIDES).is_file():
            shutil.copy2(results / SAVED_OVERRIDES, staging / SAVED_OVERRIDES)
        for run in runs:
            shutil.copytree(run, staging / RUNS_DIR / run.name)
        if index is not None:
            shutil.copy2(results / INDEX_FILE, staging / INDEX_FILE)
            if index["runs"]:
                metrics = pl.concat([input_files.read_parquet(staging / r / RUN_METRICS) for r in index["runs"]],
                                    how="vertical_relaxed")
                metrics.write_parquet(staging / "metrics.parquet")
    evaluated = sum((run / RUN_METRICS).is_file() for run in runs)
    training = sum((run / STATE_FILE).is_file() for run in runs)
    return (f"restored {experiment}: {evaluated} evaluated runs, {len(runs) - evaluated - training} trained runs to "
            f"evaluate, {training} runs to resume from their checkpoints; continue with `trajflow experiment "
            f"{experiment / CONFIG_FILE} -o {experiment}`")


def all_finished(experiment: Path) -> bool:
    """Whether every planned run of the experiment is finished (its index lists them all as runs)."""
    index = json.loads(input_files.read_text(experiment / INDEX_FILE))
    return set(index.get("planned") or ()) <= set(index["runs"])


def publish_every(experiment: Path, out: Path, minutes: float, *, sleep=time.sleep) -> None:
    """Publish `experiment` into `out` now and every `minutes` minutes until all its planned runs are finished (the
    last round publishes them); a failed round is reported on one line and retried at the next."""
    while True:
        finished = all_finished(experiment)
        try:
            line = publish(experiment, out)
        except (ValueError, OSError, TrajflowError) as error:
            line = f"not published this round ({error}); trying again in {minutes:g} min"
            finished = False
        print(f"{dt.datetime.now().isoformat(timespec='seconds')} {line}", flush=True)
        if finished:
            return
        sleep(60 * minutes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--restore", action="store_true",
                        help="turn the published folder SOURCE back into the experiment directory TARGET")
    parser.add_argument("source", type=Path, help="experiment directory (trajflow experiment -o); with --restore, "
                                                  "a published folder, e.g. docs/results/eth_ucy")
    parser.add_argument("target", type=Path, help="results directory, e.g. docs/results/eth_ucy; with --restore, "
                                                  "the experiment directory to create")
    parser.add_argument("--every", type=float, metavar="MINUTES",
                        help="publish again every MINUTES minutes until every planned run is finished")
    args = parser.parse_args()
    if args.every is not None and (args.restore or not args.every > 0):
        parser.error("--every takes a positive number of minutes, and does not go with --restore")
    try:
        if args.every is not None:
            publish_every(args.source, args.target, args.every)
            return
        print(restore(args.source, args.target) if args.restore else publish(args.source, args.target))
    except (ValueError, OSError, TrajflowError) as error:
        parser.error(str(error))


if __name__ == "__main__":
    main()
