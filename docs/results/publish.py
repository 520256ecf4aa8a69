"""Publish an experiment's results into docs/results/<name> (what this repository commits), and turn such a folder
back into an experiment directory on another machine, so that the experiment goes on without repeating finished
work.

    python docs/results/publish.py runs/paper/eth_ucy docs/results/eth_ucy
    python docs/results/publish.py --every 15 runs/paper/eth_ucy docs/results/eth_ucy &
    python docs/results/publish.py --restore docs/results/eth_ucy runs/paper/eth_ucy

Publishing runs `trajflow report EXP -o OUT` (once a run is finished, and again only when the finished runs or
their evaluations changed: a restored experiment's runs have no draws, and a new report would lose the figures
drawn from them), then writes beside the report:
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
  would start again anyway) are left out. A last-epoch state larger than the largest file this repository takes
  (`--max-file-mib`, 2 MiB: a state in the flow stage holds the weights, the best weights and Adam's two moments,
  ~3.5 MB for ETH/UCY's TrajFlow) is published in two files, `checkpoints/state.pt` without the optimizer's state
  and `checkpoints/state-optimizer.pt` with it, which `--restore` joins again (a resume of the first alone is
  refused). Where even those are too large, the run's latest stage-end state that fits takes its place
  (`checkpoints/end-<stage>.pt`, saved as `checkpoints/state.pt`, with the training log cut to its epochs): the
  copy resumes at the end of that stage, bit-identical to the run there, and trains the later stages again. When
  no state fits, the last one is published all the same and the summary line says it is over the limit.
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
import torch

from trajflow_pipeline.errors import TrajflowError
from trajflow_pipeline.model.checkpoint import load_training_state, save_training_state
from trajflow_pipeline.report.collect import report_rows
from trajflow_pipeline.rundir import (CHECKPOINT_DIR, CONFIG_FILE, EVAL_DIR, EVAL_FILE, EVALUATION_RECORD, LOG_FILE,
                                      METRICS_FILE, STAGE_END_FILE, STATE_FILE, continuation_files)
from trajflow_pipeline.stages.experiment import INDEX_FILE
from trajflow_pipeline.stages.experiment_config import SAVED_OVERRIDES
from trajflow_pipeline.stages.report import report
from trajflow_pipeline.training.state import LOG_SCHEMA
from trajflow_pipeline.util import input_files
from trajflow_pipeline.util.atomic import atomic_directory, atomic_file, atomic_write_bytes, atomic_write_text

#: the published folders of runs: the finished ones, and what continues the others
MODELS_DIR = "models"
UNFINISHED_DIR = "unfinished"
#: the experiment directory's folder of runs
RUNS_DIR = "runs"
#: a run's metrics table, relative to the run
RUN_METRICS = f"{EVAL_DIR}/{METRICS_FILE}"
#: the largest file this repository takes, in bytes (--max-file-mib)
MAX_FILE_BYTES = 2 * 1024 * 1024
#: a published resume state too large for one file keeps its optimizer's state (Adam's moments) here
OPTIMIZER_PART = f"{CHECKPOINT_DIR}/state-optimizer.pt"


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


def resume_state_within(run: Path, limit: int) -> Path | None:
    """The latest training state of the run in training `run` that is at most `limit` bytes: its last epoch's
    state, else the end state of its latest finished stage that fits (the most epochs in its log); None when none
    fits."""
    if (run / STATE_FILE).stat().st_size <= limit:
        return run / STATE_FILE
    ends = [path for path in run.glob(STAGE_END_FILE.format(stage="*")) if path.stat().st_size <= limit]
    trained = {path: len(load_training_state(path)["log"]) for path in ends}
    return max(ends, key=trained.__getitem__, default=None)


def write_state_apart(state_path: Path, target: Path, limit: int) -> bool:
    """Write the training state in `state_path` into the copy `target` as two files of at most `limit` bytes each:
    `checkpoints/state.pt` without the optimizer's state (in its place a marker that any resume refuses) and
    OPTIMIZER_PART with it; :func:`join_state` puts them back together, tensor for tensor. False, and nothing
    left behind, when either part is larger."""
    state = load_training_state(state_path)
    head, part = target / STATE_FILE, target / OPTIMIZER_PART
    head.parent.mkdir(parents=True, exist_ok=True)
    save_training_state(head, {**state, "optimizer": {"published_apart": OPTIMIZER_PART}})
    torch.save({"optimizer": state["optimizer"]}, part)
    if head.stat().st_size <= limit and part.stat().st_size <= limit:
        return True
    head.unlink()
    part.unlink()
    return False


def join_state(run: Path) -> None:
    """Put a state that was published in two files (:func:`write_state_apart`) back into the run's one state.pt."""
    state = load_training_state(run / STATE_FILE)
    try:
        part = torch.load(run / OPTIMIZER_PART, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any failure to parse means a damaged or foreign file
        raise ValueError(f"{run / OPTIMIZER_PART}: not a readable optimizer state ({error})") from None
    if not isinstance(part, dict) or not isinstance(part.get("optimizer"), dict):
        raise ValueError(f"{run / OPTIMIZER_PART}: not an optimizer state published by this script")
    save_training_state(run / STATE_FILE, {**state, "optimizer": part["optimizer"]})
    (run / OPTIMIZER_PART).unlink()


def copy_run_in_training(run: Path, target: Path, names: Sequence[str], limit: int) -> tuple[int, str]:
    """Copy what continues the run in training `run` into the new directory `target`, each file at most `limit`
    bytes where it can be: the last epoch's state as it is or in two files (:func:`write_state_apart`), else the
    end state of the latest finished stage that fits (:func:`resume_state_within`) as the copy's state.pt, with the
    training log cut to the epochs it holds. Returns the bytes written and what was left out ("" when nothing
    was)."""
    if (run / STATE_FILE).stat().st_size > limit:
        copy_run(run, target, [name for name in names if name != STATE_FILE])
        if write_state_apart(run / STATE_FILE, target, limit):
            return (sum(path.stat().st_size for path in target.rglob("*") if path.is_file()),
                    f"its state in two files, {STATE_FILE} and {OPTIMIZER_PART}")
        shutil.rmtree(target)
    state = resume_state_within(run, limit)
    if state is None:
        size = (run / STATE_FILE).stat().st_size
        return copy_run(run, target, names), f"its state is {size:,} bytes, over the {limit:,}-byte limit"
    if state == run / STATE_FILE:
        return copy_run(run, target, names), ""
    kept = [name for name in names if name not in (STATE_FILE, LOG_FILE)]
    copy_run(run, target, kept)
    (target / STATE_FILE).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(state, target / STATE_FILE)
    pl.DataFrame(load_training_state(state)["log"], schema=LOG_SCHEMA).write_parquet(target / LOG_FILE)
    dropped = input_files.read_parquet(run / LOG_FILE).height - input_files.read_parquet(target / LOG_FILE).height
    return (sum(path.stat().st_size for path in target.rglob("*") if path.is_file()),
            f"resumes from {state.name}, {dropped} later epochs left out: {STATE_FILE} is "
            f"{(run / STATE_FILE).stat().st_size:,} bytes")


def publish_runs(experiment: Path, out: Path, limit: int = MAX_FILE_BYTES
                 ) -> tuple[dict[str, int], dict[str, int], dict[str, str]]:
    """Rebuild `out/models/` from the experiment's finished runs (experiment.json `runs`, evaluated) and
    `out/unfinished/` from its other planned runs that have something to go on from, resume states within `limit`
    bytes where they can be (:func:`copy_run_in_training`); the bytes published per run, finished and unfinished,
    and what was left out of the unfinished ones, per run."""
    index = json.loads(input_files.read_text(experiment / INDEX_FILE))
    listed = set(index["runs"])
    finished: dict[str, int] = {}
    unfinished: dict[str, int] = {}
    notes: dict[str, str] = {}
    with atomic_directory(out / MODELS_DIR) as models, atomic_directory(out / UNFINISHED_DIR) as others:
        for relative in index.get("planned") or index["runs"]:
            run = experiment / relative
            names = continuation_files(run) if run.is_dir() else ()
            if relative in listed and set(EVALUATION_RECORD) <= set(names):
                finished[run.name] = copy_run(run, models / run.name, names)
            elif STATE_FILE in names:
                unfinished[run.name], note = copy_run_in_training(run, others / run.name, names, limit)
                if note:
                    notes[run.name] = note
            elif names:
                unfinished[run.name] = copy_run(run, others / run.name, names)
        if (out / MODELS_DIR / "README.md").is_file():
            shutil.copy2(out / MODELS_DIR / "README.md", models / "README.md")
    if not unfinished:
        shutil.rmtree(out / UNFINISHED_DIR)
    return finished, unfinished, notes


def report_current(experiment: Path, out: Path, runs: Sequence[str]) -> bool:
    """Whether `out` already holds the report of exactly the finished `runs` of `experiment` as they are evaluated
    now: its report.md, an index listing the same runs, and each run's published evaluation record the same as the
    run's own. Writing it again would change only its date, and after a restore (runs without their draws) would
    drop the figures drawn from draws."""
    if not (out / "report.md").is_file() or not (out / INDEX_FILE).is_file():
        return False
    if json.loads(input_files.read_text(out / INDEX_FILE)).get("runs") != list(runs):
        return False
    record = f"{EVAL_DIR}/{EVAL_FILE}"
    published = [out / MODELS_DIR / Path(run).name / record for run in runs]
    return all(copy.is_file() and copy.read_bytes() == (experiment / run / record).read_bytes()
               for copy, run in zip(published, runs))


def publish(experiment: Path, out: Path, limit: int = MAX_FILE_BYTES) -> str:
    """Publish the experiment in `experiment` into `out` (see the module docstring); a one-line summary."""
    index = json.loads(input_files.read_text(experiment / INDEX_FILE))
    rows = 0
    unchanged = bool(index["runs"]) and report_current(experiment, out, index["runs"])
    if index["runs"] and not unchanged:
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
    finished, unfinished, notes = publish_runs(experiment, out, limit)
    sizes = ", ".join(f"{name} {size:,}" + (f" ({notes[name]})" if name in notes else "")
                      for name, size in unfinished.items())
    made = "report (as it was: the same finished runs), " if unchanged else "report, "
    return (f"published {out}: " + (made if index["runs"] else "no report (no run is finished), ")
            + f"config, index, {rows} aggregate metric rows, {len(finished)} finished runs "
            f"({sum(finished.values()):,} bytes), {len(unfinished)} unfinished runs ({sum(unfinished.values()):,} "
            f"bytes{': ' + sizes if unfinished else ''})")


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
            if (run / OPTIMIZER_PART).is_file():
                join_state(staging / RUNS_DIR / run.name)
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


def publish_every(experiment: Path, out: Path, minutes: float, limit: int = MAX_FILE_BYTES, *,
                  sleep=time.sleep) -> None:
    """Publish `experiment` into `out` now and every `minutes` minutes until all its planned runs are finished (the
    last round publishes them); a failed round is reported on one line and retried at the next."""
    while True:
        finished = all_finished(experiment)
        try:
            line = publish(experiment, out, limit)
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
    parser.add_argument("--max-file-mib", type=float, default=MAX_FILE_BYTES / 2**20, metavar="MIB",
                        help="the largest file to publish, in MiB (default: %(default)g); a larger resume state is "
                             "published in two files, or else replaced by the run's latest stage-end state that "
                             "fits")
    args = parser.parse_args()
    if args.every is not None and (args.restore or not args.every > 0):
        parser.error("--every takes a positive number of minutes, and does not go with --restore")
    if not args.max_file_mib > 0:
        parser.error("--max-file-mib takes a positive number")
    limit = int(args.max_file_mib * 2**20)
    try:
        if args.every is not None:
            publish_every(args.source, args.target, args.every, limit)
            return
        print(restore(args.source, args.target) if args.restore else publish(args.source, args.target, limit))
    except (ValueError, OSError, TrajflowError) as error:
        parser.error(str(error))


if __name__ == "__main__":
    main()
