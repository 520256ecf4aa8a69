"""`trajflow status EXP`: where each run of an experiment stands, for experiments that take hours or days.

It reads only what training and evaluation leave behind (``run.json``, ``config.toml``, ``train_log.parquet``,
``eval/eval.json``) and the operating system's table of file locks (``/proc/locks``) to see which runs a live
process has claimed. It never takes a claim itself, so asking cannot make a worker skip a run; where the lock table
cannot be read (not Linux) a run that is not finished shows as "training or interrupted".

For the stage being trained it gives the epoch, the stage's budget (min / max epochs), the best epoch so far and
how many epochs the early-stopping patience has left, the recent seconds per epoch, and the range of time the stage
can still take: at least until the minimum epochs and the patience are used up, at most until its maximum.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import polars as pl

from ..data import list_folds
from ..errors import DataError, UsageError
from ..model.config import load_config
from .evaluate import EVAL_DIR
from .experiment import ExperimentConfig, load_experiment, run_done, run_evaluated, run_name, run_overrides
from .train import CONFIG_FILE, LOG_FILE, RUN_FILE

#: the epoch budget keys of each gradient stage (train.<prefix>_min_epochs, _max_epochs, _patience)
_BUDGET_PREFIX = {"autoencoder": "ae", "flow": "flow"}
#: epochs whose median time gives the recent seconds per epoch
_RECENT_EPOCHS = 5


@dataclass(frozen=True)
class StageProgress:
    """The last stage a run trained (or is training) and how far along it is."""

    stage: str
    epoch: int
    min_epochs: int | None = None
    max_epochs: int | None = None
    best_epoch: int | None = None
    patience: int | None = None
    seconds_per_epoch: float | None = None

    @property
    def epochs_left(self) -> tuple[int, int] | None:
        """(fewest, most) epochs the stage may still train: early stopping can end it once the minimum epochs are
        done and the patience is used up; the maximum ends it in any case."""
        if self.max_epochs is None or self.min_epochs is None:
            return None
        most = max(0, self.max_epochs - self.epoch)
        if not self.patience or self.best_epoch is None:
            return most, most
        stop_at = max(self.min_epochs, self.best_epoch + self.patience)
        return min(most, max(0, stop_at - self.epoch)), most


@dataclass(frozen=True)
class RunStatus:
    """One planned run of an experiment: its state, its progress and the time it has taken."""

    name: str
    model: str
    fold: str | None
    seed: int
    #: planned, training, interrupted, evaluating, trained, budget raised, continuing, done
    state: str
    #: claimed by a live process now (None: this platform's lock table cannot be read)
    busy: bool | None
    progress: StageProgress | None
    train_seconds: float
    eval_seconds: float | None
    metrics: dict[str, float]


@dataclass(frozen=True)
class ExperimentStatus:
    """Every planned run of the experiment in `path`, in plan order."""

    name: str
    path: Path
    runs: list[RunStatus]
    note: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the runs with their stage's remaining epoch range."""
        runs = []
        for run in self.runs:
            entry = asdict(run)
            if run.progress is not None:
                entry["progress"]["epochs_left"] = run.progress.epochs_left
            runs.append(entry)
        return {"name": self.name, "path": str(self.path), "note": self.note, "runs": runs}


def experiment_status(out: str | Path) -> ExperimentStatus:
    """The status of every run the experiment in `out` (made by `trajflow experiment ... -o out`) plans."""
    out = Path(out)
    if not (out / "config.toml").is_file():
        raise UsageError(f"{out}: not an experiment directory (no config.toml; `trajflow experiment CONFIG -o {out}` "
                         "makes one)")
    config = load_experiment(out / "config.toml")
    plan, note = _planned(out, config)
    locked = _locked_inodes()
    runs = [_run_status(out, config, model, fold, seed, locked) for model, fold, seed in plan]
    return ExperimentStatus(name=config.name, path=out, runs=runs, note=note)


def _planned(out: Path, config: ExperimentConfig) -> tuple[list[tuple[str, str | None, int]], str | None]:
    """(model, fold, seed) of every run in plan order, and a note when the folds had to be guessed.

    The folds come from the dataset (as the experiment found them), else from the index the experiment writes
    (experiment.json), else from the run directories that exist."""
    folds: list[str | None] | None = None
    note = None
    if config.folds not in (None, "all"):
        folds = list(config.folds)
    else:
        data = _data_dir(out, config)
        if data is not None:
            folds = list(list_folds(data)) or [None]
    if folds is None:
        names = _index_runs(out) or sorted(p.name for p in (out / "runs").glob("*") if p.is_dir())
        folds = _folds_from_names(names, config)
        note = (f"the dataset ({config.data_path}) was not found from here, so the folds are those of the runs "
                "started so far; run this from where the experiment was started to see every planned run")
    return [(m, f, s) for m in config.models for f in folds for s in config.seeds], note


def _data_dir(out: Path, config: ExperimentConfig) -> Path | None:
    """The experiment's dataset: where its index says it was, else the config's path (relative to here)."""
    try:
        indexed = json.loads((out / "experiment.json").read_text()).get("data")
    except (OSError, ValueError):
        indexed = None
    for candidate in (indexed, config.data_path):
        if candidate and (Path(candidate) / "dataset.json").is_file():
            return Path(candidate)
    return None


def _index_runs(out: Path) -> list[str]:
    """The run names the experiment's index plans (empty when it has no index yet)."""
    try:
        planned = json.loads((out / "experiment.json").read_text()).get("planned") or []
    except (OSError, ValueError):
        return []
    return [Path(entry).name for entry in planned]


def _folds_from_names(names: list[str], config: ExperimentConfig) -> list[str | None]:
    """The folds in run names `<model>-<fold>-s<seed>` of the config's models and seeds, in first-seen order."""
    folds: list[str | None] = []
    for name in names:
        for model in sorted(config.models, key=len, reverse=True):
            for seed in config.seeds:
                prefix, suffix = f"{model}-", f"-s{seed}"
                if name.startswith(prefix) and name.endswith(suffix) and len(name) > len(prefix) + len(suffix):
                    fold = name[len(prefix):-len(suffix)]
                    fold_value = None if fold == "all" else fold
                    if fold_value not in folds:
                        folds.append(fold_value)
                    break
            else:
                continue
            break
    return folds or [None]


def _locked_inodes() -> set[tuple[int, int, int]] | None:
    """(major, minor, inode) of every file a process holds a lock on, from /proc/locks; None where unreadable."""
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    locked = set()
    for line in lines:
        fields = line.split()
        if "->" in fields:  # a process waiting for a lock, not holding one
            continue
        for field in fields:
            parts = field.split(":")
            if len(parts) == 3:
                try:
                    locked.add((int(parts[0], 16), int(parts[1], 16), int(parts[2])))
                except ValueError:
                    pass
                break
    return locked


def _claimed(lock_path: Path, locked: set[tuple[int, int, int]] | None) -> bool | None:
    """Whether a live process holds the claim on `lock_path` (None: cannot tell)."""
    if locked is None:
        return None
    try:
        stat = lock_path.stat()
    except FileNotFoundError:
        return False
    return (os.major(stat.st_dev), os.minor(stat.st_dev), stat.st_ino) in locked


def _run_status(out: Path, config: ExperimentConfig, model: str, fold: str | None, seed: int,
                locked: set[tuple[int, int, int]] | None) -> RunStatus:
    name = run_name(model, fold, seed)
    run_dir = out / "runs" / name
    busy = _claimed(out / "runs" / f".{name}.lock", locked)
    info = _read_json(run_dir / RUN_FILE)
    evaluation = _read_json(run_dir / EVAL_DIR / "eval.json")
    log = _read_log(run_dir / LOG_FILE)
    if info is None:
        state = "training" if busy else "planned"
    elif info.get("status") != "finished":
        state = "training" if busy else ("training or interrupted" if busy is None else "interrupted")
    elif not run_evaluated(run_dir):
        state = "evaluating" if busy else "trained"
    elif not run_done(run_dir, run_overrides(config, model)):
        state = "continuing" if busy else "budget raised"
    else:
        state = "done"
    return RunStatus(
        name=name, model=model, fold=fold, seed=seed, state=state, busy=busy,
        progress=_progress(log, run_dir) if log is not None and log.height else None,
        train_seconds=float(log.get_column("seconds").sum()) if log is not None and log.height else 0.0,
        eval_seconds=(float(evaluation["seconds"]) if state == "done" and evaluation
                      and isinstance(evaluation.get("seconds"), (int, float)) else None),
        metrics=_aggregates(run_dir) if state == "done" else {},
    )


def _read_json(path: Path) -> dict[str, Any] | None:
    """A JSON file's object, None when it is missing; a corrupt one is a DataError naming it."""
    try:
        value = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        raise DataError(f"unreadable ({error})", path) from None
    return value if isinstance(value, dict) else None


def _read_log(path: Path) -> pl.DataFrame | None:
    """The run's training log (None before its first epoch)."""
    if not path.is_file():
        return None
    try:
        return pl.read_parquet(path, columns=["epoch", "stage", "val_loss", "seconds"])
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable training log ({error})", path) from None


def _progress(log: pl.DataFrame, run_dir: Path) -> StageProgress:
    """The last stage in the log: its epochs since it (last) started, its best epoch and its budget."""
    stages = log.get_column("stage")
    stage = str(stages[-1])
    changes = (stages != stages.shift(1)).fill_null(True).arg_true()
    current = log.slice(int(changes[-1]))
    epoch = int(current.get_column("epoch")[-1])
    recent = current.tail(_RECENT_EPOCHS).get_column("seconds").median()
    seconds_per_epoch = float(recent) if isinstance(recent, (int, float)) else None
    prefix = _BUDGET_PREFIX.get(stage)
    if prefix is None or not (run_dir / CONFIG_FILE).is_file():
        return StageProgress(stage=stage, epoch=epoch, seconds_per_epoch=seconds_per_epoch)
    train = load_config(run_dir / CONFIG_FILE).train
    validated = current.filter(pl.col("val_loss").is_not_null() & pl.col("val_loss").is_finite())
    best = (int(validated.sort("val_loss", maintain_order=True).get_column("epoch")[0])
            if validated.height else None)
    return StageProgress(stage=stage, epoch=epoch, min_epochs=getattr(train, f"{prefix}_min_epochs"),
                         max_epochs=getattr(train, f"{prefix}_max_epochs"), best_epoch=best,
                         patience=getattr(train, f"{prefix}_patience"), seconds_per_epoch=seconds_per_epoch)


def _aggregates(run_dir: Path) -> dict[str, float]:
    """The evaluated run's aggregate metrics (metric -> mean)."""
    path = run_dir / EVAL_DIR / "metrics.parquet"
    try:
        table = pl.read_parquet(path, columns=["metric", "value", "aggregate"]).filter(pl.col("aggregate"))
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable metrics ({error})", path) from None
    return {str(metric): float(value) for metric, value in table.select("metric", "value").iter_rows()}
