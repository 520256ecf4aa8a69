"""`trajflow status EXP`: where each run of an experiment stands, for experiments that take hours or days.

`trajflow status RUN` does the same for one run of `trajflow train -o RUN`. Such a run holds no claim, so while it
is not finished it shows as "training or interrupted".

It reads only what training and evaluation leave behind (``run.json``, ``config.toml``, ``train_log.parquet``,
``eval/eval.json``) and the operating system's table of file locks (``/proc/locks``) to see which runs a live
process has claimed. It never takes a claim itself, so asking cannot make a worker skip a run. Where the lock table
cannot be read (not Linux), or the experiment lies on a network file system (where a process on another machine
may hold a claim that this machine's table does not list), a run that is not finished and not claimed here shows as
"training or interrupted". A run whose files cannot be read shows as "unreadable" with the reason.

For the stage being trained it gives the epoch, the stage's budget (min / max epochs, as the experiment's config now
sets them: a raised budget shows before the run follows it), the best epoch so far and the early-stopping patience
left, the recent seconds per epoch, and the range of time the stage can still take: at least until the minimum
epochs and the patience are used up, at most until its maximum. When an unfinished run's last logged stage has
ended, the stage after it is shown, at epoch 0.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from ..data import list_folds
from ..errors import DataError, TrajflowError, UsageError
from ..model.config import GRADIENT_STAGES, RunConfig, load_config
from ..metrics.rome_cache import saved_fits
from ..model.models import MODEL_CLASSES
from ..rundir import (CONFIG_FILE, EVAL_DIR, EVAL_FILE, LOG_FILE, METRICS_FILE, ROME_CACHE_DIR, RUN_FILE,
                      is_evaluated, read_run_config, read_run_info)
from ..training import budget_raise
from ..util import input_files
from .data_stages import StageState, data_status
from .experiment import plan_order, run_done, run_name, run_overrides, trained_on_other_data
from .experiment_config import SAVED_CONFIG, ExperimentConfig, load_saved_experiment

#: epochs whose median time gives the recent seconds per epoch
_RECENT_EPOCHS = 5


@dataclass(frozen=True)
class StageProgress:
    """The stage a run is training (or trained last) and how far along it is, judged as training's early stopping
    judges it: after `min_epochs`, `patience` epochs without a lower validation loss than the best end the stage."""

    stage: str
    #: epochs this stage has trained (0: it is the next to start)
    epoch: int
    min_epochs: int | None = None
    max_epochs: int | None = None
    #: the epoch of the lowest finite validation loss so far (None: none yet; early stopping then counts from 0)
    best_epoch: int | None = None
    patience: int | None = None
    seconds_per_epoch: float | None = None
    #: the epoch whose weights a finished run kept (run.json; differs from best_epoch under val_nll selection)
    kept_epoch: int | None = None

    @property
    def stopped(self) -> bool:
        """Whether training has ended this stage: its maximum reached, or early stopping (closed-form stages end
        after their one pass)."""
        if self.max_epochs is None or self.min_epochs is None:
            return self.epoch >= 1
        return self.epoch >= self.max_epochs or bool(
            self.patience and self.epoch >= self.min_epochs and self.epoch - (self.best_epoch or 0) >= self.patience)

    @property
    def patience_left(self) -> int | None:
        """Epochs without a better validation loss that early stopping still allows (None: no patience)."""
        if not self.patience or self.max_epochs is None:
            return None
        return max(0, self.patience - (self.epoch - (self.best_epoch or 0)))

    @property
    def epochs_left(self) -> tuple[int, int] | None:
        """(fewest, most) epochs the stage may still train: early stopping can end it once the minimum epochs are
        done and the patience is used up; the maximum ends it in any case. None for closed-form stages."""
        if self.max_epochs is None or self.min_epochs is None:
            return None
        if self.stopped:
            return 0, 0
        most = self.max_epochs - self.epoch
        if not self.patience:
            return most, most
        stop_at = max(self.min_epochs, (self.best_epoch or 0) + self.patience)
        return min(most, stop_at - self.epoch), most


@dataclass(frozen=True)
class RunStatus:
    """One planned run of an experiment: its state, its progress and the time it has taken."""

    name: str
    model: str
    fold: str | None
    seed: int
    #: planned, training, interrupted, training or interrupted, evaluating, trained, continuing, budget raised,
    #: temperature changed (the experiment changed the settings of the stage after the flow: it is fitted again),
    #: data changed (trained on data a data stage has changed since: it is trained again), done, or unreadable
    #: (see `problem`)
    state: str
    #: claimed by a live process now (None: cannot tell from here, see the module docstring)
    busy: bool | None
    progress: StageProgress | None
    train_seconds: float
    eval_seconds: float | None
    metrics: dict[str, float]
    #: why the run's files could not be read (state "unreadable")
    problem: str | None = None
    #: (saved, all) ROME fits of an evaluation in progress or interrupted (None: none)
    fits_saved: tuple[int, int] | None = None


@dataclass(frozen=True)
class ExperimentStatus:
    """Every planned run of the experiment in `path`, in plan order."""

    name: str
    path: Path
    runs: list[RunStatus]
    note: str | None = None
    #: "experiment", or "run" for the status of one run directory
    kind: str = "experiment"
    #: the experiment's data stages (ingest, augmentations) and whether each is current
    data: list[StageState] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite metric values as null), with each stage's remaining epoch range."""
        runs = []
        for run in self.runs:
            entry = asdict(run)
            entry["metrics"] = {k: (v if math.isfinite(v) else None) for k, v in run.metrics.items()}
            if run.progress is not None:
                entry["progress"] |= {"epochs_left": run.progress.epochs_left,
                                      "patience_left": run.progress.patience_left}
            runs.append(entry)
        return {"name": self.name, "kind": self.kind, "path": str(self.path), "note": self.note,
                "data": [stage.to_dict() for stage in self.data], "runs": runs}


def experiment_status(out: str | Path) -> ExperimentStatus:
    """The status of every run the experiment in `out` (made by `trajflow experiment ... -o out`) plans."""
    out = Path(out)
    if (out / RUN_FILE).is_file():
        return _single_run_status(out)
    if not (out / SAVED_CONFIG).is_file():
        raise UsageError(f"{out}: not an experiment directory (no {SAVED_CONFIG}; `trajflow experiment CONFIG -o "
                         f"{out}` makes one)")
    config = load_saved_experiment(out)
    plan, note = _planned(out, config)
    claims = _Claims(out / "runs")
    data = _data_dir(out, config)
    runs = [_run_status(out, config, model, fold, seed, claims, data) for model, fold, seed in plan]
    return ExperimentStatus(name=config.name, path=out, runs=runs, note=note, data=data_status(config))


def _single_run_status(run_dir: Path) -> ExperimentStatus:
    """The status of the one run in `run_dir` (a `trajflow train -o` directory), under its own saved config."""
    try:
        info = read_run_info(run_dir) or {}
        saved = read_run_config(run_dir)
        if not info.get("model") and saved is None:
            raise DataError(f"neither {RUN_FILE} nor {CONFIG_FILE} says which model this run trains", run_dir)
        model = str(info.get("model") or saved.model.name)
        fold, seed = info.get("fold"), info.get("seed")
        run = _inspect_run(run_dir, None, model, fold if isinstance(fold, str) else None,
                           seed if isinstance(seed, int) and not isinstance(seed, bool) else 0, None)
    except TrajflowError as error:
        run = RunStatus(name=run_dir.name, model="?", fold=None, seed=0, state="unreadable", busy=None,
                        progress=None, train_seconds=0.0, eval_seconds=None, metrics={}, problem=str(error))
    return ExperimentStatus(name=run_dir.name, path=run_dir, runs=[run], kind="run")


def _planned(out: Path, config: ExperimentConfig) -> tuple[list[tuple[str, str | None, int]], str | None]:
    """(model, fold, seed) of every run in plan order, and a note when the folds had to be guessed.

    The folds come from the config, else from the dataset (as the experiment found them), else from the index the
    experiment writes (experiment.json), else from the run directories that exist."""
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
    return plan_order(config.models, folds, config.seeds), note


def _index(out: Path) -> dict[str, Any]:
    """The experiment's index (experiment.json) as far as it is readable; {} before the first run is done."""
    try:
        index = json.loads(input_files.read_text(out / "experiment.json"))
    except (TrajflowError, OSError, ValueError):
        return {}
    return index if isinstance(index, dict) else {}


def _data_dir(out: Path, config: ExperimentConfig) -> Path | None:
    """The experiment's dataset: where its index says it was, else the config's path (relative to here)."""
    indexed = _index(out).get("data")
    for candidate in (indexed if isinstance(indexed, str) else None, config.data_path):
        if candidate and (Path(candidate) / "dataset.json").is_file():
            return Path(candidate)
    return None


def _index_runs(out: Path) -> list[str]:
    """The run names the experiment's index plans (empty when it has no index yet)."""
    planned = _index(out).get("planned")
    return [Path(entry).name for entry in planned if isinstance(entry, str)] if isinstance(planned, list) else []


def _folds_from_names(names: list[str], config: ExperimentConfig) -> list[str | None]:
    """The folds in run names `<model>-<fold>-s<seed>` of the config's models and seeds, in first-seen order."""
    folds: list[str | None] = []
    affixes = [(f"{m}-", f"-s{s}") for m in sorted(config.models, key=len, reverse=True) for s in config.seeds]
    for name in names:
        for prefix, suffix in affixes:
            if name.startswith(prefix) and name.endswith(suffix) and len(name) > len(prefix) + len(suffix):
                fold = name[len(prefix):-len(suffix)]
                if (None if fold == "all" else fold) not in folds:
                    folds.append(None if fold == "all" else fold)
                break
    return folds or [None]


#: file systems on which another machine may hold a run's claim, which this machine's lock table does not show
_NETWORK_FILE_SYSTEMS = frozenset({
    "nfs", "nfs4", "cifs", "smb3", "smbfs", "lustre", "gpfs", "ceph", "fuse.cephfs", "beegfs", "glusterfs",
    "fuse.glusterfs", "ocfs2", "gfs2", "9p", "afs", "fuse.sshfs", "panfs", "wekafs"})


class _Claims:
    """Which runs of one experiment a live process has claimed, read from the OS lock table (see the module doc)."""

    def __init__(self, runs_dir: Path) -> None:
        self.locked = _locked_inodes()
        self.shared = _file_system_type(runs_dir) in _NETWORK_FILE_SYSTEMS

    def held(self, lock_path: Path) -> bool | None:
        """True when a process of this machine holds the claim; False when none does, anywhere; None when this
        cannot be known (no lock table, or a network file system where another machine may hold it)."""
        if self.locked is None:
            return None
        try:
            inode = lock_path.stat().st_ino
        except FileNotFoundError:
            return None if self.shared else False
        # By inode alone: the lock table's device numbers are the superblock's, which stat() does not always
        # report (btrfs subvolumes, overlay mounts).
        if inode in self.locked:
            return True
        return None if self.shared else False


def parse_lock_table(text: str) -> set[int]:
    """Inodes of the files that a lock is held on, from the text of /proc/locks (waiting requests, marked '->',
    hold nothing)."""
    inodes = set()
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 6 or "->" in fields[:2]:
            continue
        parts = fields[5].split(":")
        if len(parts) == 3 and parts[2].isdigit():
            inodes.add(int(parts[2]))
    return inodes


def _locked_inodes() -> set[int] | None:
    """Inodes with a lock held on this machine; None where /proc/locks cannot be read (not Linux)."""
    try:
        return parse_lock_table(Path("/proc/locks").read_text())
    except OSError:
        return None


def _file_system_type(path: Path) -> str | None:
    """The type of the file system holding `path` (the longest matching mount point of /proc/self/mounts)."""
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return None
    target = str(path.resolve())
    best, kind = -1, None
    for line in mounts:
        fields = line.split()
        if len(fields) < 3:
            continue
        mount = fields[1].replace("\\040", " ")
        inside = target == mount or target.startswith(mount.rstrip("/") + "/")
        if inside and len(mount) > best:
            best, kind = len(mount), fields[2]
    return kind


def _run_status(out: Path, config: ExperimentConfig, model: str, fold: str | None, seed: int,
                claims: _Claims, data: Path | None = None) -> RunStatus:
    """One run's status (against the dataset `data` as it is now, when known); a run whose files cannot be read is
    shown as "unreadable" with the reason, not an error that hides every other run."""
    name = run_name(model, fold, seed)
    busy = claims.held(out / "runs" / f".{name}.lock")
    try:
        return _inspect_run(out / "runs" / name, config, model, fold, seed, busy, data)
    except TrajflowError as error:
        return RunStatus(name=name, model=model, fold=fold, seed=seed, state="unreadable", busy=busy, progress=None,
                         train_seconds=0.0, eval_seconds=None, metrics={}, problem=str(error))


#: states of a run whose training has not finished
_UNFINISHED = ("training", "interrupted", "training or interrupted")


def _inspect_run(run_dir: Path, config: ExperimentConfig | None, model: str, fold: str | None, seed: int,
                 busy: bool | None, data: Path | None = None) -> RunStatus:
    """The state of the run in `run_dir` from its files and its claim (`busy`), its progress and its times, under
    the experiment `config` (None: a run of its own, under its saved config), on the dataset `data` when known."""
    info = read_run_info(run_dir)
    overrides = run_overrides(config, model, run_dir) if config is not None else []
    if info is None:
        state = "training" if busy else "planned"
    elif data is not None and not busy and trained_on_other_data(run_dir, data):
        state = "data changed"
    elif info.get("status") != "finished":
        state = "training" if busy else ("training or interrupted" if busy is None else "interrupted")
    elif not is_evaluated(run_dir):
        state = "evaluating" if busy else "trained"
    elif not run_done(run_dir, overrides):
        state = "continuing" if busy else ("budget raised" if _budget_raised(run_dir, overrides) else
                                           "temperature changed")
    else:
        state = "done"
    log = _read_log(run_dir / LOG_FILE)
    progress = None
    if log is not None and log.height:
        saved = read_run_config(run_dir)
        # The budget the run follows: a live training keeps the one it started with (its config.toml); otherwise
        # the experiment's config decides what comes next, a raised budget included.
        if busy and state == "training" and saved is not None:
            budget = saved
        else:
            budget = load_config(overrides=[*overrides, f"model.name={model}"], base=saved)
        progress = _progress(log, budget, info if state not in _UNFINISHED else None)
        if state in _UNFINISHED and progress.stopped:
            progress = _next_stage(progress, budget, model)
    evaluation = _read_json(run_dir / EVAL_DIR / EVAL_FILE) if state == "done" else None
    eval_seconds = evaluation.get("seconds") if evaluation else None
    return RunStatus(
        name=run_dir.name, model=model, fold=fold, seed=seed, state=state, busy=busy, progress=progress,
        train_seconds=float(log.get_column("seconds").sum()) if log is not None and log.height else 0.0,
        eval_seconds=float(eval_seconds) if isinstance(eval_seconds, (int, float)) else None,
        metrics=_aggregates(run_dir) if state == "done" else {},
        fits_saved=saved_fits(run_dir / ROME_CACHE_DIR) if state in ("trained", "evaluating") else None,
    )


def _budget_raised(run_dir: Path, overrides: list[str]) -> bool:
    """Whether the experiment's config raises the epoch budgets of the finished run in `run_dir` (else what it
    changes is the stage after the flow)."""
    saved = read_run_config(run_dir)
    return saved is not None and bool(budget_raise(saved, load_config(overrides=overrides, base=saved)))


def _read_json(path: Path) -> dict[str, Any] | None:
    """A JSON object file, None when it is missing; anything else is a DataError naming it."""
    if not path.exists():
        return None
    try:
        value = json.loads(input_files.read_text(path))
    except (OSError, ValueError) as error:
        raise DataError(f"unreadable ({error})", path) from None
    if not isinstance(value, dict):
        raise DataError(f"expected a JSON object, found {type(value).__name__}", path)
    return value


def _read_log(path: Path) -> pl.DataFrame | None:
    """The run's training log (None before its first epoch)."""
    if not path.is_file():
        return None
    try:
        return input_files.read_parquet(path, columns=["epoch", "stage", "val_loss", "seconds"])
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable training log ({error})", path) from None


def _budget(stage: str, config: RunConfig) -> dict[str, int]:
    """min_epochs, max_epochs and patience of a gradient stage ({} for a closed-form one)."""
    if stage not in GRADIENT_STAGES:
        return {}
    schedule = config.train.schedule(stage)
    return {"min_epochs": int(schedule.min_epochs), "max_epochs": int(schedule.max_epochs),
            "patience": int(schedule.patience)}


def _progress(log: pl.DataFrame, config: RunConfig, info: dict[str, Any] | None) -> StageProgress:
    """The last stage in the log: its epochs since it (last) started, its best epoch under `config`'s budget, and,
    from a finished run's `info` (run.json), the epoch it kept."""
    stages = log.get_column("stage")
    stage = str(stages[-1])
    current = log.slice(int((stages != stages.shift(1)).fill_null(True).arg_true()[-1]))
    # a closed-form stage (a baseline's fit, the temperature stage) has no epochs to time
    recent = current.tail(_RECENT_EPOCHS).get_column("seconds").median() if stage in GRADIENT_STAGES else None
    finite = current.filter(pl.col("val_loss").is_not_null() & pl.col("val_loss").is_finite())
    best = int(finite.sort("val_loss", maintain_order=True).get_column("epoch")[0]) if finite.height else None
    kept = ((info or {}).get("best") or {}).get(stage) if isinstance((info or {}).get("best"), dict) else None
    return StageProgress(stage=stage, epoch=int(current.get_column("epoch")[-1]), best_epoch=best,
                         seconds_per_epoch=float(recent) if isinstance(recent, (int, float)) else None,
                         kept_epoch=int(kept["epoch"]) if isinstance(kept, dict) and "epoch" in kept else None,
                         **_budget(stage, config))


def _next_stage(done: StageProgress, config: RunConfig, model: str) -> StageProgress:
    """The stage an unfinished run trains after `done` ended (`done` itself when it was the last)."""
    stages = MODEL_CLASSES[model].stages_for(config.model) if model in MODEL_CLASSES else ()
    if done.stage not in stages or stages.index(done.stage) + 1 >= len(stages):
        return done
    following = stages[stages.index(done.stage) + 1]
    return StageProgress(stage=following, epoch=0, **_budget(following, config))


def _aggregates(run_dir: Path) -> dict[str, float]:
    """The evaluated run's aggregate metrics (metric -> mean)."""
    path = run_dir / EVAL_DIR / METRICS_FILE
    try:
        table = input_files.read_parquet(path, columns=["metric", "value", "aggregate"]).filter(pl.col("aggregate"))
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable metrics ({error})", path) from None
    return {str(metric): float(value) for metric, value in table.select("metric", "value").iter_rows()
            if value is not None}
