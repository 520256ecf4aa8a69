"""`trajflow train DATA -o RUN`: fit a model's training stages on a dataset split, resumably.

Stages come from the model (:mod:`trajflow_pipeline.model.models`): TrajFlow trains its autoencoder first (RMSE on
reconstructed positions, early stopping on the validation split), freezes it, then trains the flow and the
context encoders on the latent NLL with an exponential learning-rate decay; the direct-displacement models train
only the flow stage, and the constant-velocity baseline fits its noise scale in closed form. Each gradient stage
keeps the weights of its best validation epoch. A step whose gradients are not finite is skipped and counted.

``RUN`` is a run directory (:mod:`trajflow_pipeline.rundir`: config.toml, run.json, the training log, checkpoints
and, once training has finished, final/); rank 0 writes, every file atomically.

Larger budgets: ``--resume`` may raise a stage's epoch limit or its early-stopping patience
(``train.ae_max_epochs`` / ``train.flow_max_epochs`` / ``train.ae_patience`` / ``train.flow_patience``; nothing
else). A stage that the larger budget would not have stopped where the old one did continues from its last epoch
(``end-<stage>.pt``) and every later stage is trained again; a stage that would have stopped there anyway (a raised
limit on a stage that stopped early, or more patience than its last epochs needed) is not affected. Neither setting
changes an epoch before the stop, so the continuation is the longer run's own path (a patience of 0, no early
stopping, is the largest). The run's previous final model and evaluation stay on disk until the new model replaces
them, but run.json says "training" meanwhile, so nothing evaluates the old one as the new. Because every epoch's
randomness comes from (seed, stage, epoch), the result is the run a larger budget would have given from the start
(with ``train.flow_select = "val_nll"``, the end state leaves out the sample-based check that only the end of the
stage called for, which a longer run would not have made).

Flow-only runs: ``autoencoder_from=RUN`` (``--autoencoder-from``) starts a new run at the end of RUN's autoencoder
stage (``end-autoencoder.pt``) and trains only the flow. RUN must have the same model, data, fold and settings,
except the flow stage's own training settings (``train.flow_*``); because the autoencoder stage would have been
the same epochs, the new run ends exactly as the same config trained from scratch would, without the hours of
autoencoder training. Flow learning-rate or budget sweeps use this; run.json records the source.

Determinism: the shuffling and every random draw of an epoch come from generators seeded by (seed, stage, epoch,
rank), so a resumed run replays exactly the epochs an uninterrupted one would, and a fixed seed gives the same loss
curve on CPU. Under ``torchrun`` (RANK / WORLD_SIZE set) training runs with DistributedDataParallel: each rank
takes an equal, DistributedSampler-style shard of every epoch's permutation (per-rank batch = the configured batch
size), validation losses are reduced over ranks, and only rank 0 writes.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch
import torch.distributed as torch_dist
from rich.progress import TextColumn
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from .. import __version__
from .. import data as data_module
from ..errors import DataError, TrajflowError, UsageError
from ..model.batch import SceneBatch
from ..model.checkpoint import (MODEL_FILE, check_weights, load_training_state, model_digest, save_model,
                                save_training_state)
from ..model.config import MODEL_NAMES, DataSpec, RunConfig, load_config, with_values
from ..model.models import TrajectoryModel, build_model
from ..model.runtime import resolve_device, tune_cpu_allocator
from ..rundir import (BEST_FILE, CONFIG_FILE, FINAL_DIR, LOG_FILE, LOWEST_VAL_LOSS_FILE, MODEL_INFO_FILE, RUN_REQUIRED,
                      STAGE_END_FILE, STATE_FILE, is_trained, read_run_config, read_run_info, write_run_info)
from ..schemas import data_mismatch
from ..util import input_files
from ..util.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from ..util.progress import make_progress, say
from ..util.provenance import code_revision, machines_after, revisions_after

#: Training settings that act on the flow stage alone: a run may start from the autoencoder of a run that differs
#: from it only in these (and the device).
FLOW_STAGE_KEYS = ("flow_lr", "flow_weight_decay", "flow_batch_size", "flow_lr_decay", "flow_max_epochs",
                   "flow_min_epochs", "flow_patience", "flow_select", "flow_select_every", "flow_select_problems",
                   "flow_select_samples", "flow_select_max_pooled")
#: Settings a resumed run may raise (its epoch budgets: how long a stage may go on), with the gradient stage each
#: one limits. None of them changes an epoch before the stage stops, which is what makes a raise exact.
BUDGET_KEYS = {"ae_max_epochs": "autoencoder", "flow_max_epochs": "flow", "ae_patience": "autoencoder",
               "flow_patience": "flow"}
#: The budget keys as users write them, for messages.
RAISABLE = " / ".join(f"train.{key}" for key in BUDGET_KEYS)
#: The prefix of each gradient stage's settings (train.<prefix>_max_epochs, _min_epochs, _patience).
STAGE_PREFIX = {"autoencoder": "ae", "flow": "flow"}

LOG_SCHEMA = {"epoch": pl.Int64, "stage": pl.String, "train_loss": pl.Float64, "val_loss": pl.Float64,
              "lr": pl.Float64, "seconds": pl.Float64, "skipped_steps": pl.Int64, "samples_per_s": pl.Float64,
              "val_nll": pl.Float64}

#: Called after every completed (and checkpointed) epoch with (stage, epoch); tests use it to simulate a kill.
EpochHook = Callable[[str, int], None]
_epoch_hook: EpochHook | None = None


def train(dataset_dir: str | Path, run_dir: str | Path, *, fold: str | None = None, model: str | None = None,
          config_path: str | Path | None = None, overrides: Sequence[str] = (), seed: int | None = None,
          device: str | None = None, resume: bool = False, quiet: bool = False,
          autoencoder_from: str | Path | None = None) -> Path:
    """Train `model` on the train split of `dataset_dir` (validating on its val split) into `run_dir`.

    `model`, `seed` and `device` override the config (``model.name``, ``train.seed``, ``train.device``); the
    config is the defaults, then `config_path` (TOML), then `overrides` (``section.key=value``). With `resume`, an
    interrupted run continues from its last checkpoint (its saved config is used; options that would change it are
    refused, except raised epoch budgets: see the module docstring) and a finished run is returned as is; a
    directory that holds no run (no config.toml) is a UsageError, not a fresh start. With
    `autoencoder_from`, a new run starts from that run's trained autoencoder and trains the flow only (see the
    module docstring). Returns `run_dir`.
    """
    tune_cpu_allocator()
    code_revision()  # read now: a commit or checkout during training must not be credited with it
    run_dir = Path(run_dir)
    dist = _DistContext.from_env()
    config, previous = _resolve_config(run_dir, config_path, overrides, model, seed, device, resume)
    fold = _resume_fold(run_dir, fold) if resume else fold
    source = Path(autoencoder_from) if autoencoder_from is not None else None
    #: the run to take the autoencoder from now (None: no source, or this run already took it and resumes)
    start_from = source if source is not None and not _started(run_dir, resume, source) else None
    if resume and previous is None and is_trained(run_dir):
        if dist.rank == 0 and not quiet:
            say((f"{run_dir}: already trained, nothing to resume", "dim"))
        return run_dir
    torch_device = resolve_device(config.train.device, dist.local_rank)
    dist.start(torch_device)
    try:
        data = _load_data(dataset_dir, fold, config)
        _check_same_data(run_dir, data, resume)
        start = autoencoder_start(start_from, config, data, fold) if start_from is not None else None
        session = _Session(run_dir=run_dir, config=config, data=data, device=torch_device, dist=dist, quiet=quiet,
                           fold=fold, autoencoder_from=_source_record(run_dir, source, start))
        session.run(resume, start)
    finally:
        dist.stop()
    return run_dir


# --------------------------------------------------------------------------------------------------- configuration

def _resolve_config(run_dir: Path, config_path: str | Path | None, overrides: Sequence[str], model: str | None,
                    seed: int | None, device: str | None, resume: bool) -> tuple[RunConfig, RunConfig | None]:
    """The run's config and, when a resume raises its epoch budgets, the config it was trained with so far (else
    None). On resume the saved config is used; changes other than raised budgets and the device are refused."""
    if model is not None and model not in MODEL_NAMES:
        raise UsageError(f"unknown model {model!r}; choose one of {', '.join(MODEL_NAMES)}")
    if resume and not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run directory to resume; train without --resume to start a run there")
    saved = read_run_config(run_dir) if resume else None
    if resume and saved is None:
        raise UsageError(f"{run_dir} holds no run to resume ({CONFIG_FILE} is missing); train without --resume to "
                         "start one" + (" in a new directory" if any(run_dir.iterdir()) else ""))
    if saved is not None:
        requested = _with_options(load_config(config_path, overrides, base=saved), model, seed, None)
        if requested == saved:
            return _with_options(saved, None, None, device), None
        raised = budget_raise(saved, requested)
        if raised is None:
            key = first_difference(saved, requested)
            raise UsageError(f"{run_dir} was started with a different configuration ({key}); resume it without "
                             f"changing options (only {RAISABLE} may be raised), "
                             f"or train into a new directory")
        return _with_options(requested, None, None, device), saved
    if not resume and run_dir.exists() and any(run_dir.iterdir()):
        raise UsageError(f"{run_dir} already holds a run; pass --resume to continue it or choose a new directory")
    return _with_options(load_config(config_path, overrides), model, seed, device).validate(), None


def budget_raise(old: RunConfig, new: RunConfig) -> dict[str, tuple[int, int]] | None:
    """The epoch budgets `new` raises over `old` ({key: (old, new)}), or None when the two configs differ in
    anything else (the device aside) or lower a budget; {} when they are the same run."""
    old_train, new_train = replace(old.train, device="auto"), replace(new.train, device="auto")
    unchanged = replace(new_train, **{key: getattr(old_train, key) for key in BUDGET_KEYS})
    if old.model != new.model or unchanged != old_train:
        return None
    raised = {key: (getattr(old_train, key), getattr(new_train, key)) for key in BUDGET_KEYS
              if getattr(new_train, key) != getattr(old_train, key)}
    lowered = any(budget_size(key, after) < budget_size(key, before) for key, (before, after) in raised.items())
    return None if lowered else raised


def budget_size(key: str, value: int) -> float:
    """How long the budget `key` = `value` lets a stage go on, for ordering budgets: a patience of 0 disables early
    stopping, so it is larger than any other."""
    return math.inf if key.endswith("_patience") and value == 0 else float(value)


def raise_blocker(run_dir: Path, overrides: Sequence[str]) -> str | None:
    """Why the run in `run_dir` cannot take `overrides` (a config change an experiment asks for), or None when it
    can: the same config, raised budgets it can follow, or no run yet. Read from its files, without loading data
    or weights, so an experiment can check all its runs before it changes anything."""
    saved = read_run_config(run_dir)
    if saved is None:
        return None
    requested = load_config(overrides=overrides, base=saved)
    raised = budget_raise(saved, requested)
    if raised is None:
        return f"{run_dir}: {first_difference(saved, requested)} (only epoch budgets may be raised)"
    log = input_files.read_parquet(run_dir / LOG_FILE) if (run_dir / LOG_FILE).is_file() else pl.DataFrame(schema=LOG_SCHEMA)
    stages = log.get_column("stage").to_list()
    for key, (old_value, _) in raised.items():
        stage = BUDGET_KEYS[key]
        later = any(s != stage for s in stages[stages.index(stage):]) if stage in stages else False
        finished = later or (stage == "flow" and is_trained(run_dir))
        # a raised limit matters only to a stage that reached it; more patience, to one that stopped below its limit
        epochs = stages.count(stage)
        matters = (epochs >= old_value if key.endswith("_max_epochs")
                   else epochs < getattr(requested.train, f"{STAGE_PREFIX[stage]}_max_epochs"))
        if finished and matters and not (run_dir / STAGE_END_FILE.format(stage=stage)).is_file():
            return (f"{run_dir}: its {stage} stage finished before trajflow kept stage-end states, so it cannot "
                    f"continue with a larger train.{key}")
    return None


def _run_info(run_dir: Path) -> dict[str, Any]:
    """The run's run.json, checked, with every key training writes at its start (:func:`~.runs.read_run_info`;
    {} when it has none yet)."""
    return read_run_info(run_dir, required=RUN_REQUIRED) or {}


def _resume_fold(run_dir: Path, fold: str | None) -> str | None:
    """The fold a resumed run continues on: the one it was started for (so ``--resume`` needs no ``--fold``);
    a different `fold` is refused, since the run's weights were fitted to the other fold's training data."""
    recorded = _run_info(run_dir).get("fold")
    if recorded is None:
        return fold
    if fold is not None and str(fold) != str(recorded):
        raise UsageError(f"{run_dir} was started for fold {recorded!r}, not {fold!r}; resume it without --fold "
                         "(or with its own), or train into a new directory")
    return str(recorded)


def _started(run_dir: Path, resume: bool, source: Path) -> bool:
    """Whether `run_dir` already holds a resumable run taken from `source`'s autoencoder (so resume it as is).
    A resumable run from anything else is refused: its autoencoder is not `source`'s."""
    if not (resume and (run_dir / STATE_FILE).is_file()):
        return False
    recorded = _run_info(run_dir).get("autoencoder_from") or {}
    if recorded.get("run") != str(source.resolve()):
        raise UsageError(f"{run_dir} already holds a run that did not start from {source}'s autoencoder; resume it "
                         "without --autoencoder-from, or train into a new directory")
    return True


def _source_record(run_dir: Path, source: Path | None, start: dict[str, Any] | None) -> dict[str, Any] | None:
    """What run.json says about the run whose autoencoder this one took: from `start` for a new run, else what
    the run's own run.json already says (None for a run that trained its own)."""
    if start is not None and source is not None:
        epochs = sum(1 for row in start["log"] if row["stage"] == "autoencoder")
        return {"run": str(source.resolve()), "autoencoder_epochs": epochs,
                "autoencoder_best_epoch": int(start["best_epoch"])}
    return _run_info(run_dir).get("autoencoder_from")


def autoencoder_start(source: Path, config: RunConfig, data: _Data, fold: str | None) -> dict[str, Any]:
    """The training state a new run with `config` starts from when it takes the autoencoder of the run in `source`:
    that run's state at the end of its autoencoder stage, carrying `config`. Refused (UsageError naming the
    difference) unless `source` trained the same model on the same data and fold with the same settings, flow
    training settings aside, so that its autoencoder is the one `config` would train."""
    end_path = source / STAGE_END_FILE.format(stage="autoencoder")
    if not end_path.is_file():
        raise UsageError(f"{source}: no finished autoencoder stage to start from ({end_path.name} is missing)")
    info = _run_info(source)
    _check_same_data(source, data, resume=True)
    if info.get("fold") != fold:
        raise UsageError(f"{source} was trained for fold {info.get('fold')!r}, this run is for {fold!r}")
    state = load_training_state(end_path)
    if state.get("model") != config.model.name:
        raise UsageError(f"{end_path}: a {state.get('model')!r} run; this run trains {config.model.name!r}")
    trained = state_config(end_path, state)
    flow_settings = {key: getattr(config.train, key) for key in (*FLOW_STAGE_KEYS, "device")}
    comparable = replace(trained, train=replace(trained.train, **flow_settings))
    if comparable != config:
        raise UsageError(f"{source} trained its autoencoder with other settings "
                         f"({first_difference(comparable, config)}); only train.flow_* settings may differ")
    check_state(end_path, state, build_model(trained.model, data.spec))
    return {**state, "config": config.to_json()}


#: What a training state (state.pt, end-<stage>.pt) holds: each key and the types its value may have.
STATE_FIELDS: dict[str, tuple[type, ...]] = {
    "model": (str,), "config": (str,), "stage_index": (int,), "epoch": (int,), "best_val": (float, int),
    "best_epoch": (int,), "bad_epochs": (int,), "weights": (dict,), "best_weights": (dict, type(None)),
    "optimizer": (dict, type(None)), "scheduler": (dict, type(None)), "log": (list,), "best": (dict,),
    "skipped_total": (int,), "started": (str,), "selected_nll": (float, int), "selected_epoch": (int,),
}
#: Keys of STATE_FIELDS that states written before them lack (their defaults are read in `_progress_from`).
_STATE_OPTIONAL = ("selected_nll", "selected_epoch")


def read_state(path: Path, model: TrajectoryModel) -> dict[str, Any]:
    """The training state in `path` of a run of `model`, checked (:func:`check_state`) before anything uses it."""
    state = load_training_state(path, expected_model=model.name)
    check_state(path, state, model)
    return state


def check_state(path: Path, state: dict[str, Any], model: TrajectoryModel) -> None:
    """Refuse (DataError naming `path`) a training state that `model`'s run cannot continue from: a key missing or
    of the wrong type, a config that does not parse, a stage the model lacks, weights that do not fit the model, a
    log without stages or an optimizer state for other parameters than its stage trains."""
    for key, kinds in STATE_FIELDS.items():
        if key not in state:
            if key in _STATE_OPTIONAL:
                continue
            raise DataError(f"training state lacks {key!r}", path)
        if not isinstance(state[key], kinds) or isinstance(state[key], bool):
            raise DataError(f"training state: {key!r} is a {type(state[key]).__name__}", path)
    state_config(path, state)
    if not 0 <= state["stage_index"] <= len(model.stages):
        raise DataError(f"training state: stage {state['stage_index']} does not exist (the model has "
                        f"{len(model.stages)})", path)
    check_weights(path, state["weights"], model)
    if state["best_weights"] is not None:
        check_weights(path, state["best_weights"], model, what="best weights")
    if not all(isinstance(row, dict) and isinstance(row.get("stage"), str) for row in state["log"]):
        raise DataError("training state: the training log has rows without a stage", path)
    if state["optimizer"] is not None and state["stage_index"] < len(model.stages):
        _check_optimizer(path, state["optimizer"], model.stage_parameters(model.stages[state["stage_index"]]))


def _check_optimizer(path: Path, saved: dict[str, Any], params: list[nn.Parameter]) -> None:
    """Refuse an optimizer state that is not for `params` (their number, and the shapes of its moment tensors)."""
    groups, moments = saved.get("param_groups"), saved.get("state")
    if not isinstance(groups, list) or not isinstance(moments, dict) or not all(
            isinstance(g, dict) and isinstance(g.get("params"), list) for g in groups):
        raise DataError("training state: the optimizer state is damaged", path)
    ids = [pid for group in groups for pid in group["params"]]
    if len(ids) != len(params):
        raise DataError(f"training state: the optimizer state is for {len(ids)} parameters, the stage trains "
                        f"{len(params)}", path)
    for pid, param in zip(ids, params):
        entry = moments.get(pid, {})
        for name, value in entry.items() if isinstance(entry, dict) else ():
            if isinstance(value, Tensor) and value.dim() > 0 and value.shape != param.shape:
                raise DataError(f"training state: optimizer {name} of parameter {pid} has shape {list(value.shape)},"
                                f" not {list(param.shape)}", path)


def state_config(path: Path, state: dict[str, Any]) -> RunConfig:
    """The config a training state carries (its "config", JSON); a damaged one is a DataError naming `path`."""
    try:
        return RunConfig.from_dict(json.loads(state["config"]))
    except (KeyError, TypeError, ValueError, TrajflowError) as error:
        raise DataError(f"training state: its config is damaged ({error})", path) from None


def _with_options(config: RunConfig, model: str | None, seed: int | None, device: str | None) -> RunConfig:
    """`config` with the options that override it (--model, --seed, --device), each checked as a setting is."""
    for option, key, value in (("--model", "model.name", model), ("--seed", "train.seed", seed),
                               ("--device", "train.device", device)):
        if value is not None:
            config = with_values(config, {key: value}, source=option)
    return config.validate()


def first_difference(a: RunConfig, b: RunConfig) -> str:
    """The first setting in which two configs differ, as "section.key: a vs b"."""
    left, right = a.to_dict(), b.to_dict()
    for section in left:
        for key in left[section]:
            if left[section][key] != right[section][key]:
                return f"{section}.{key}: {left[section][key]!r} vs {right[section][key]!r}"
    return "unknown difference"


# ------------------------------------------------------------------------------------------------------------ data

@dataclass
class _Data:
    """The training and validation problems and what the model must know about them."""

    train: SceneBatch
    val: SceneBatch
    #: (n_val,) identical-input group of each validation problem (pools draws for the sample-based NLL)
    val_groups: np.ndarray
    spec: DataSpec
    fingerprint: dict[str, str]
    validation: str
    dataset_dir: Path


def _load_data(dataset_dir: str | Path, fold: str | None, config: RunConfig) -> _Data:
    """Load train and val problems; without a val split, hold out ``train.val_fraction`` of train (seeded)."""
    train_problems = data_module.load_problems(dataset_dir, fold=fold, split="train")
    if len(train_problems) == 0:
        raise DataError("the training split has no samples", path=dataset_dir)
    # The map encoder is built only when the problems actually carry map crops.
    has_map = bool(train_problems.has_map) and train_problems.batch.map_crop is not None
    spec = DataSpec(n_past=int(train_problems.n_past), n_future=int(train_problems.n_future), has_map=has_map,
                    dataset=str(train_problems.dataset), dt=float(train_problems.dt))
    train_batch = train_problems.batch
    val_problems = _load_validation(dataset_dir, fold)
    if val_problems is not None and len(val_problems) > 0:
        if (val_problems.n_past, val_problems.n_future) != (spec.n_past, spec.n_future):
            raise DataError(f"validation problems have {val_problems.n_past}/{val_problems.n_future} past/future "
                            f"steps, training problems {spec.n_past}/{spec.n_future}", path=dataset_dir)
        val_batch, validation = val_problems.batch, "val split"
        val_groups = np.asarray(val_problems.group_id, dtype=np.int64)
    else:
        if len(train_batch) < 2:
            raise DataError("need at least 2 training problems to hold out a validation set (no val split)",
                            path=dataset_dir)
        order = torch.randperm(len(train_batch), generator=torch.Generator().manual_seed(config.train.seed))
        n_val = min(len(train_batch) - 1, max(1, round(len(train_batch) * config.train.val_fraction)))
        val_batch, train_batch = train_batch.index(order[:n_val]), train_batch.index(order[n_val:])
        val_groups = np.asarray(train_problems.group_id, dtype=np.int64)[order[:n_val].numpy()]
        validation = f"held out {n_val} of the train split (train.val_fraction={config.train.val_fraction})"
    if train_batch.future is None or val_batch.future is None:
        raise DataError("training problems carry no ground-truth future", path=dataset_dir)
    return _Data(train_batch, val_batch, val_groups, spec, dict(train_problems.fingerprint), validation,
                 Path(dataset_dir))


def _load_validation(dataset_dir: str | Path, fold: str | None) -> Any:
    """The val split's problems, or None when the protocol leaves it empty."""
    try:
        return data_module.load_problems(dataset_dir, fold=fold, split="val")
    except DataError as error:
        if "has no samples" in str(error):
            return None
        raise


def _check_same_data(run_dir: Path, data: _Data, resume: bool) -> None:
    """On resume, refuse data other than the run started on (other dataset, or its manifest changed)."""
    if not resume:
        return
    mismatch = data_mismatch(_run_info(run_dir).get("fingerprint", {}), data.fingerprint)
    if mismatch:
        raise UsageError(f"{run_dir} was trained on other data ({mismatch})")


# ------------------------------------------------------------------------------------------------------ distributed

@dataclass
class _DistContext:
    """Rank / world size under torchrun, and whether this call created the process group."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    created: bool = False

    @classmethod
    def from_env(cls) -> "_DistContext":
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        rank = int(os.environ.get("RANK", "0"))
        return cls(rank=rank, world=world, local_rank=int(os.environ.get("LOCAL_RANK", str(rank))))

    @property
    def active(self) -> bool:
        return self.world > 1

    def start(self, device: torch.device) -> None:
        if not self.active:
            return
        if device.type == "cuda":
            torch.cuda.set_device(device)
        if not torch_dist.is_initialized():
            torch_dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
            self.created = True

    def stop(self) -> None:
        if self.created and torch_dist.is_initialized():
            torch_dist.destroy_process_group()
            self.created = False

    def sum(self, values: Sequence[float], device: torch.device) -> list[float]:
        """Element-wise sum over ranks (float64)."""
        tensor = torch.tensor(list(values), dtype=torch.float64, device=device)
        if self.active:
            torch_dist.all_reduce(tensor)
        return tensor.tolist()

    def gather(self, value: Any) -> list[Any]:
        if not self.active:
            return [value]
        out: list[Any] = [None] * self.world
        torch_dist.all_gather_object(out, value)
        return out

    def barrier(self) -> None:
        if self.active:
            torch_dist.barrier()


# --------------------------------------------------------------------------------------------------------- training

class _StageObjective(nn.Module):
    """forward(batch) = the model's loss for one stage; the module DDP wraps so gradients are all-reduced."""

    def __init__(self, model: TrajectoryModel, stage: str) -> None:
        super().__init__()
        self.model = model
        self.stage = stage

    def forward(self, batch: SceneBatch) -> Tensor:
        return self.model.stage_loss(self.stage, batch)


@dataclass
class _StageProgress:
    """Early-stopping bookkeeping of the current stage (part of the resumable state)."""

    epoch: int = 0
    best_val: float = math.inf
    best_epoch: int = 0
    bad_epochs: int = 0
    best_weights: dict[str, Tensor] | None = None
    #: with train.flow_select = "val_nll": the lowest sample-based validation NLL so far and its epoch
    selected_nll: float = math.inf
    selected_epoch: int = 0
    optimizer: dict[str, Any] | None = None
    scheduler: dict[str, Any] | None = None


@dataclass
class _Session:
    """One call of :func:`train`: holds the model, the data and the run directory."""

    run_dir: Path
    config: RunConfig
    data: _Data
    device: torch.device
    dist: _DistContext
    quiet: bool
    fold: str | None
    log: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, dict[str, float]] = field(default_factory=dict)
    skipped_total: int = 0
    started: str = field(default_factory=lambda: dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))
    #: the code revisions and the machines that trained this run, oldest first (see util.provenance)
    code_revisions: list[str] = field(default_factory=list)
    machines: list[str] = field(default_factory=list)
    #: the run whose trained autoencoder this one started from (run.json "autoencoder_from"), if any
    autoencoder_from: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        self.code_revisions = self.code_revisions or revisions_after([])
        self.machines = self.machines or machines_after([], str(self.device))

    @property
    def writer(self) -> bool:
        return self.dist.rank == 0

    def run(self, resume: bool, start: dict[str, Any] | None = None) -> None:
        """Train every stage from the first (or from `start`, a training state to go on from; see
        `autoencoder_start`), or, with `resume`, from the run's last checkpoint."""
        torch.manual_seed(self.config.train.seed)
        self.model = build_model(self.config.model, self.data.spec, seed=self.config.train.seed).to(self.device)
        stage_index, progress = 0, _StageProgress()
        state_path = self.run_dir / STATE_FILE
        if start is not None:
            stage_index, progress = self._restore(start)
            self.started = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
            if self.writer:
                self.run_dir.mkdir(parents=True, exist_ok=True)
                atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
                self._write_run_info("training")
                save_training_state(state_path, start)
        elif resume and state_path.is_file():
            state = read_state(state_path, self.model)
            state, reopened, adopted = self._follow_budget(state)
            if state is None:
                return  # finished, and no stage a raised budget limits was stopped by its old one
            stage_index, progress = self._restore(state)
            if self.writer and adopted:  # run.json first: an interruption now cannot look finished
                if reopened:
                    self._write_run_info("training")
                save_training_state(state_path, state)
                atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            elif self.writer and not is_trained(self.run_dir):  # run.json names the code that continues it
                self._write_run_info("training")
        elif resume and (self.run_dir / FINAL_DIR).exists():
            raise UsageError(f"{self.run_dir}: {STATE_FILE} is missing, so this run cannot be continued or given a "
                             f"larger budget; train into a new directory")
        elif self.writer:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            self._write_run_info("training")
        train_batch = _on_device(self.data.train, self.device)
        val_batch = _on_device(self.data.val, self.device)
        stages = self.model.stages
        with make_progress(self.quiet or not self.writer, TextColumn("{task.fields[status]}", markup=False)) as bars:
            for index in range(stage_index, len(stages)):
                stage = stages[index]
                if stage in self.model.closed_form_stages:
                    self._fit_closed_form(index, stage, train_batch, val_batch)
                else:
                    self._fit_gradient(index, stage, progress, train_batch, val_batch, bars)
                progress = _StageProgress()
                self._checkpoint(index + 1, progress)
        self._finish()

    # -- stages ----------------------------------------------------------------------------------------------------

    def _fit_closed_form(self, index: int, stage: str, train_batch: SceneBatch, val_batch: SceneBatch) -> None:
        start = time.perf_counter()
        self.model.eval()
        with torch.no_grad():
            self.model.fit_stage(stage, train_batch)
            train_loss = _mean_loss(self.model, stage, train_batch, self.config.train.eval_batch_size, self.dist,
                                    self.device)
            val_loss = _mean_loss(self.model, stage, val_batch, self.config.train.eval_batch_size, self.dist,
                                  self.device)
        seconds = time.perf_counter() - start
        self.best[stage] = {"epoch": 1, "val_loss": val_loss}
        self._log_epoch(stage, 1, train_loss, val_loss, 0.0, seconds, 0, len(train_batch) / max(seconds, 1e-9))

    def _fit_gradient(self, index: int, stage: str, progress: _StageProgress, train_batch: SceneBatch,
                      val_batch: SceneBatch, bars: Any) -> None:
        cfg = self.config.train
        ae = stage == "autoencoder"
        lr, weight_decay = (cfg.ae_lr, cfg.ae_weight_decay) if ae else (cfg.flow_lr, cfg.flow_weight_decay)
        batch_size = cfg.ae_batch_size if ae else cfg.flow_batch_size
        max_epochs, min_epochs = (cfg.ae_max_epochs, cfg.ae_min_epochs) if ae else (cfg.flow_max_epochs,
                                                                                       cfg.flow_min_epochs)
        patience = cfg.ae_patience if ae else cfg.flow_patience
        by_sample_nll = stage == "flow" and cfg.flow_select == "val_nll"
        if by_sample_nll:  # a fixed, seeded subset of the validation problems for every check
            select_subset = torch.randperm(len(val_batch), generator=torch.Generator().manual_seed(cfg.seed))
            select_subset = select_subset[:cfg.flow_select_problems].sort().values
        params = self.model.stage_parameters(stage)
        trainable = {id(p) for p in params}
        for p in self.model.parameters():
            p.requires_grad_(id(p) in trainable)
        optimizer = _adamw(params, lr, weight_decay)
        scheduler = None if ae else torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=cfg.flow_lr_decay)
        if progress.optimizer is not None:
            optimizer.load_state_dict(progress.optimizer)
        if scheduler is not None and progress.scheduler:
            scheduler.load_state_dict(progress.scheduler)
        objective: nn.Module = _StageObjective(self.model, stage)
        if self.dist.active:
            # Buffers (flow permutations, masks) never change while training: no per-step broadcast needed.
            objective = DistributedDataParallel(objective, device_ids=[self.device] if self.device.type == "cuda"
                                                else None, broadcast_buffers=False)
        n_train = len(train_batch)
        per_rank = math.ceil(n_train / self.dist.world)
        n_batches = math.ceil(per_rank / batch_size)
        epoch_task = bars.add_task(f"{stage}", total=max_epochs, completed=progress.epoch, status="")
        batch_task = bars.add_task("  batches", total=n_batches, status="")
        stop = progress.epoch >= max_epochs or _should_stop(progress, min_epochs, patience)
        #: the selection before a sample-based check that only the stage's end called for (see below)
        unscheduled: tuple[float, int, dict[str, Tensor] | None] | None = None
        while not stop:
            epoch = progress.epoch + 1
            start = time.perf_counter()
            lr_now = optimizer.param_groups[0]["lr"]
            torch.manual_seed(_derive_seed(cfg.seed, index, epoch, self.dist.rank))
            shard = _epoch_shard(n_train, cfg.seed, index, epoch, self.dist)
            self.model.train()
            total, count, skipped = 0.0, 0, 0
            bars.reset(batch_task, total=n_batches)
            for b in range(n_batches):
                idx = shard[b * batch_size:(b + 1) * batch_size]
                batch = _part(train_batch, idx, self.device)
                loss = objective(batch)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if _finite_gradients(params, cfg.grad_clip):
                    optimizer.step()
                    value = float(loss.detach())
                    total += value * len(idx)
                    count += len(idx)
                else:
                    optimizer.zero_grad(set_to_none=True)
                    skipped += 1
                rate = (b + 1) * batch_size / max(time.perf_counter() - start, 1e-9)
                bars.update(batch_task, advance=1, status=f"loss {total / max(count, 1):.4f}  {rate:,.0f} samples/s")
            train_seconds = time.perf_counter() - start
            # Gradients are all-reduced before the finiteness check, so every rank skipped the same steps.
            total, count = self.dist.sum([total, count], self.device)
            train_loss = total / count if count else math.nan
            val_loss = _mean_loss(self.model, stage, val_batch, cfg.eval_batch_size, self.dist, self.device)
            if scheduler is not None:
                scheduler.step()
            progress.epoch = epoch
            improved = math.isfinite(val_loss) and val_loss < progress.best_val
            if improved:
                progress.best_val, progress.best_epoch, progress.bad_epochs = val_loss, epoch, 0
            else:
                progress.bad_epochs += 1
            stop = epoch >= max_epochs or _should_stop(progress, min_epochs, patience)
            seconds = time.perf_counter() - start
            val_nll, keep = math.nan, improved
            if by_sample_nll:
                keep = False
                if improved and self.writer:  # what "val_loss" would have kept, for comparing the two
                    save_model(self.model, self.run_dir / LOWEST_VAL_LOSS_FILE.format(stage=stage),
                               extra={"stage": stage, "epoch": epoch, "val_loss": val_loss})
                if epoch % cfg.flow_select_every == 0 or stop:
                    if epoch % cfg.flow_select_every:
                        unscheduled = (progress.selected_nll, progress.selected_epoch, progress.best_weights)
                    val_nll = self._sample_nll(val_batch, select_subset, epoch)
                    keep = math.isfinite(val_nll) and val_nll < progress.selected_nll
                    if keep:
                        progress.selected_nll, progress.selected_epoch = val_nll, epoch
            if keep:
                progress.best_weights = _copy_weights(self.model)
                if self.writer:
                    save_model(self.model, self.run_dir / BEST_FILE.format(stage=stage),
                               extra={"stage": stage, "epoch": epoch, "val_loss": val_loss,
                                      **({"val_nll": val_nll} if by_sample_nll else {})})
            self.skipped_total += skipped
            self._log_epoch(stage, epoch, train_loss, val_loss, lr_now, seconds, skipped,
                            self.dist.world * per_rank / max(train_seconds, 1e-9), val_nll)
            progress.optimizer = optimizer.state_dict()
            progress.scheduler = scheduler.state_dict() if scheduler is not None else None
            self._checkpoint(index, progress)
            bars.update(epoch_task, completed=epoch,
                        status=f"train {train_loss:.4f}  val {val_loss:.4f}  best {progress.best_val:.4f}")
            if _epoch_hook is not None:
                _epoch_hook(stage, epoch)
        bars.remove_task(batch_task)
        # The stage's last epoch, before its best weights are loaded: a larger budget continues from here, as if
        # the stage had gone on, so without the check that only the end of the stage called for.
        end = progress
        if unscheduled is not None:
            end = replace(progress, selected_nll=unscheduled[0], selected_epoch=unscheduled[1],
                          best_weights=unscheduled[2])
        self._checkpoint(index, end, STAGE_END_FILE.format(stage=stage))
        if progress.best_weights is not None:
            self.model.load_state_dict(progress.best_weights)
        self.best[stage] = {"epoch": progress.best_epoch, "val_loss": progress.best_val}
        if by_sample_nll and progress.selected_epoch:
            self.best[stage] = {"epoch": progress.selected_epoch, "val_nll": progress.selected_nll,
                                "selected_by": "val_nll", "lowest_val_loss": progress.best_val,
                                "lowest_val_loss_epoch": progress.best_epoch}
        elif by_sample_nll:  # no check gave a finite value: the last weights stay
            self.best[stage] = {"epoch": progress.epoch, "val_loss": progress.best_val,
                                "selected_by": "last epoch (no finite sample-based validation NLL)",
                                "lowest_val_loss": progress.best_val, "lowest_val_loss_epoch": progress.best_epoch}

    def _sample_nll(self, val_batch: SceneBatch, subset: Tensor, epoch: int) -> float:
        """The evaluation's NLL (nats; ROME densities of draws, pooled over identical inputs) on the validation
        problems `subset`, with the same noise at every check so that checks differ only by the weights. Rank 0
        computes it and every rank gets its value, so all ranks keep the same epoch. Draws ROME cannot fit (non-
        finite, or all identical) give NaN, which is never kept, with a warning: the run goes on."""
        from ..metrics import compute_metrics

        value: float | None = None
        if self.dist.rank == 0:
            cfg = self.config.train
            generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
            self.model.eval()
            draws = []
            with torch.no_grad():
                for chunk in subset.split(max(1, cfg.eval_batch_size)):
                    draws.append(self.model.sample(_part(val_batch, chunk, self.device), cfg.flow_select_samples,
                                                   generator=generator)
                                 .trajectories.double().cpu())
            ground_truth = val_batch.future.index_select(0, subset.to(val_batch.future.device)).double().cpu()
            try:
                table = compute_metrics(torch.cat(draws).numpy(), ground_truth.numpy(), metrics=("nll",),
                                        group_id=self.data.val_groups[subset.numpy()],
                                        max_pooled=cfg.flow_select_max_pooled, workers=1, quiet=True)
                value = float(table.filter(pl.col("aggregate")).get_column("value")[0])
            except DataError as error:
                value = math.nan
                if not self.quiet:
                    say(("warning:", "yellow"), f" epoch {epoch}: no sample-based validation NLL ({error}); these "
                        "weights are not kept")
        return float(self.dist.gather(value)[0])

    # -- persistence -----------------------------------------------------------------------------------------------

    def _log_epoch(self, stage: str, epoch: int, train_loss: float, val_loss: float, lr: float, seconds: float,
                   skipped: int, rate: float, val_nll: float = math.nan) -> None:
        self.log.append({"epoch": epoch, "stage": stage, "train_loss": float(train_loss), "val_loss": float(val_loss),
                         "lr": float(lr), "seconds": float(seconds), "skipped_steps": int(skipped),
                         "samples_per_s": float(rate), "val_nll": None if math.isnan(val_nll) else float(val_nll)})
        if self.writer:
            frame = pl.DataFrame(self.log, schema=LOG_SCHEMA)
            buffer = io.BytesIO()
            frame.write_parquet(buffer)
            atomic_write_bytes(self.run_dir / LOG_FILE, buffer.getvalue())

    def _checkpoint(self, stage_index: int, progress: _StageProgress, path: str = STATE_FILE) -> None:
        """Write the resumable training state (stage `stage_index` at `progress`) to `path` in the run."""
        if not self.writer:
            return
        save_training_state(self.run_dir / path, {
            "model": self.model.name,
            "config": self.config.to_json(),
            "stage_index": stage_index,
            "epoch": progress.epoch,
            "best_val": progress.best_val,
            "best_epoch": progress.best_epoch,
            "bad_epochs": progress.bad_epochs,
            "weights": _copy_weights(self.model),
            "best_weights": progress.best_weights,
            "selected_nll": progress.selected_nll,
            "selected_epoch": progress.selected_epoch,
            "optimizer": progress.optimizer,
            "scheduler": progress.scheduler,
            "log": self.log,
            "best": self.best,
            "skipped_total": self.skipped_total,
            "started": self.started,
            "code_revisions": self.code_revisions,
            "machines": self.machines,
        })

    def _follow_budget(self, state: dict[str, Any]) -> tuple[dict[str, Any] | None, bool, bool]:
        """Reconcile the checkpoint with the run's config when their epoch budgets differ: returns the training state
        to go on from (None when the run is finished and stays as it is), whether a finished stage was reopened,
        and whether that state and the config must be saved before training goes on.

        A config that raises the budgets of the checkpoint's moves the run to them (`_reopen`). A checkpoint that
        raises the config's is an earlier raise whose config.toml was not yet written: the run goes on with it.
        Any other difference is an error."""
        trained = state_config(self.run_dir / STATE_FILE, state)
        device = self.config.train.device
        if replace(trained, train=replace(trained.train, device=device)) == self.config:
            return state, False, False
        if budget_raise(self.config, trained):
            self.config = replace(trained, train=replace(trained.train, device=device))
            self._say("continuing the larger budget an interrupted call gave this run")
            return state, False, True
        if budget_raise(trained, self.config) is None:
            raise TrajflowError(f"{self.run_dir / STATE_FILE}: checkpoint does not match {CONFIG_FILE}")
        start, reopened = self._reopen(state, trained)
        start = {**start, "config": self.config.to_json()}
        if not reopened and int(start["stage_index"]) >= len(self.model.stages) and is_trained(self.run_dir):
            if self.writer:
                save_training_state(self.run_dir / STATE_FILE, start)
                atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            return None, False, False
        return start, reopened, True

    def _reopen(self, state: dict[str, Any], trained: RunConfig) -> tuple[dict[str, Any], bool]:
        """The state to continue from under the raised budgets of `config` over `trained`: the end state of the first
        finished stage whose budget was raised and that the new budget would not have stopped at its last epoch, and
        True; else `state` and False. Stages after a reopened one are trained again from their start."""
        log_stages = [row["stage"] for row in state["log"]]
        for index, stage in enumerate(self.model.stages[:int(state["stage_index"])]):
            raised = [key for key, limited in BUDGET_KEYS.items()
                      if limited == stage and budget_size(key, getattr(self.config.train, key))
                      > budget_size(key, getattr(trained.train, key))]
            if not raised:
                continue
            prefix = STAGE_PREFIX[stage]
            old_max = getattr(trained.train, f"{prefix}_max_epochs")
            new_max, new_min, new_patience = (getattr(self.config.train, f"{prefix}_{name}")
                                              for name in ("max_epochs", "min_epochs", "patience"))
            change = ", ".join(f"train.{key} {getattr(trained.train, key)} -> {getattr(self.config.train, key)}"
                               for key in raised)
            epochs = log_stages.count(stage)
            if (raised == [f"{prefix}_max_epochs"] and epochs < old_max) or epochs >= new_max:
                self._say(f"{stage} ran {epochs} of {old_max} epochs: {change} changes nothing there")
                continue
            end_path = self.run_dir / STAGE_END_FILE.format(stage=stage)
            if not end_path.is_file():
                raise UsageError(f"{self.run_dir}: its {stage} stage finished before trajflow kept stage-end states "
                                 f"({end_path.name} is missing), so it cannot continue with {change}; train into a "
                                 f"new directory")
            end = read_state(end_path, self.model)
            progress = _progress_from(end)
            if progress.epoch >= new_max or _should_stop(progress, new_min, new_patience):
                self._say(f"{stage} would have stopped at its last epoch ({epochs}) with {change} too: nothing "
                          "changes there")
                continue
            later = self.model.stages[index + 1:]
            self._say(f"continuing {stage} after epoch {epochs} ({change})"
                      + (f"; then {', '.join(later)} from the start" if later else ""))
            return end, True
        return state, False

    def _say(self, message: str) -> None:
        if self.writer and not self.quiet:
            say((f"{self.run_dir}: {message}", "dim"))

    def _restore(self, state: dict[str, Any]) -> tuple[int, _StageProgress]:
        """Load a training state (already reconciled with the config by `_follow_budget`)."""
        self.model.load_state_dict(state["weights"])
        self.log = list(state["log"])
        self.best = dict(state["best"])
        self.skipped_total = int(state["skipped_total"])
        self.started = str(state["started"])
        self.code_revisions = revisions_after(state.get("code_revisions"))
        self.machines = machines_after(state.get("machines"), str(self.device))
        progress = _progress_from(state)
        if self.writer and not self.quiet:
            say((f"resuming {self.run_dir}: stage {int(state['stage_index']) + 1}, after epoch {progress.epoch}",
                 "dim"))
        return int(state["stage_index"]), progress

    def _finish(self) -> None:
        digest = model_digest(self.model)
        digests = self.dist.gather(digest)
        if self.writer:
            info_extra = {"rank_weight_digests": digests, "ranks_consistent": len(set(digests)) == 1}
            with atomic_directory(self.run_dir / FINAL_DIR) as tmp:
                save_model(self.model, tmp / MODEL_FILE,
                           extra={"dataset": self.data.spec.dataset, "fold": self.fold,
                                  "seed": self.config.train.seed, "fingerprint": self.data.fingerprint})
                (tmp / MODEL_INFO_FILE).write_text(json.dumps(
                    {"model": self.model.name, "log_lik_space": self.model.log_lik_space,
                     "config": self.config.to_dict(), "spec": self.data.spec.to_dict(),
                     "trajflow_version": __version__}, indent=2) + "\n")
            self._write_run_info("finished", info_extra)
            if not self.quiet:
                best = ", ".join(f"{stage} {_kept_by(b)} (epoch {b['epoch']})" for stage, b in self.best.items())
                say(("trained", "green"), f" {self.model.name} -> {self.run_dir / FINAL_DIR}: {best}"
                    + (f"; skipped {self.skipped_total} non-finite steps" if self.skipped_total else ""))
        self.dist.barrier()

    def _write_run_info(self, status: str, extra: dict[str, Any] | None = None) -> None:
        spec = self.data.spec
        info = {
            "model": self.config.model.name, "dataset": spec.dataset, "fold": self.fold,
            "seed": self.config.train.seed, "status": status, "trajflow_version": __version__,
            "data_dir": str(self.data.dataset_dir.resolve()), "fingerprint": self.data.fingerprint,
            "n_past": spec.n_past, "n_future": spec.n_future, "has_map": spec.has_map, "dt": spec.dt,
            "n_train": len(self.data.train), "n_val": len(self.data.val), "validation": self.data.validation,
            "log_lik_space": self.model.log_lik_space, "world_size": self.dist.world, "device": str(self.device),
            "cpu_threads": torch.get_num_threads(), "best": self.best, "skipped_steps": self.skipped_total,
            "started": self.started, "code_revisions": self.code_revisions, "machines": self.machines,
            "final": f"{FINAL_DIR}/{MODEL_FILE}" if status == "finished" else None,
        }
        if self.autoencoder_from is not None:
            info["autoencoder_from"] = self.autoencoder_from
        if status == "finished":
            # to the microsecond: with the weights' digest it tells one training of the final model from the next
            # (a raised budget can end in the second the run first finished, keeping the same weights)
            info["finished"] = dt.datetime.now(dt.timezone.utc).isoformat()
        info.update(extra or {})
        write_run_info(self.run_dir, info)


# ---------------------------------------------------------------------------------------------------------- helpers

def _kept_by(best: dict[str, Any]) -> str:
    """What a stage's kept weights were chosen by, for the summary line: "val 0.1234" or "val_nll -41.2000"."""
    return f"val_nll {best['val_nll']:.4f}" if "val_nll" in best else f"val {best['val_loss']:.4f}"


def _part(batch: SceneBatch, idx: Tensor, device: torch.device) -> SceneBatch:
    """Problems `idx` of `batch`, on `device` (map crops stay on the host until a batch needs them)."""
    part = batch.index(idx.to(batch.past.device))
    return part if part.past.device == device else part.to(device)


def _on_device(batch: SceneBatch, device: torch.device) -> SceneBatch:
    """Keep map crops on the host (too large to preload); move everything else once."""
    if device.type == "cpu" or batch.map_crop is not None:
        return batch
    return batch.to(device)


def _adamw(params: list[nn.Parameter], lr: float, weight_decay: float) -> torch.optim.Optimizer:
    """AdamW, fused into one kernel per step where the device supports it (several times faster on CPU)."""
    try:
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)


def _derive_seed(seed: int, stage_index: int, epoch: int, rank: int) -> int:
    """A reproducible per-(stage, epoch, rank) seed."""
    text = f"{seed}/{stage_index}/{epoch}/{rank}".encode()
    return int.from_bytes(hashlib.sha256(text).digest()[:8], "little") & ((1 << 63) - 1)


def _epoch_shard(n: int, seed: int, stage_index: int, epoch: int, dist: _DistContext) -> Tensor:
    """This rank's indices of the epoch's permutation, padded DistributedSampler-style to equal length."""
    generator = torch.Generator().manual_seed(_derive_seed(seed, stage_index, epoch, -1))
    order = torch.randperm(n, generator=generator)
    per_rank = math.ceil(n / dist.world)
    if per_rank * dist.world > n:
        order = torch.cat((order, order[:per_rank * dist.world - n]))
    return order[dist.rank::dist.world]


def _finite_gradients(params: list[nn.Parameter], clip: float) -> bool:
    """Clip the global gradient norm (when `clip` > 0) and report whether every gradient is finite."""
    grads = [p for p in params if p.grad is not None]
    if not grads:
        return True
    norm = torch.nn.utils.clip_grad_norm_(grads, clip if clip > 0 else math.inf)
    return bool(torch.isfinite(norm))


@torch.no_grad()
def _mean_loss(model: TrajectoryModel, stage: str, batch: SceneBatch, chunk: int, dist: _DistContext,
               device: torch.device) -> float:
    """Size-weighted mean of the stage loss over `batch` (this rank's interleaved share, reduced over ranks)."""
    model.eval()
    n = len(batch)
    mine = torch.arange(dist.rank, n, dist.world)
    total, count = 0.0, 0
    for start in range(0, len(mine), chunk):
        idx = mine[start:start + chunk]
        total += float(model.stage_loss(stage, _part(batch, idx, device))) * len(idx)
        count += len(idx)
    total, count = dist.sum([total, count], device)
    return total / count if count else math.nan


def _progress_from(state: dict[str, Any]) -> _StageProgress:
    """The stage bookkeeping stored in a training state."""
    return _StageProgress(epoch=int(state["epoch"]), best_val=float(state["best_val"]),
                          best_epoch=int(state["best_epoch"]), bad_epochs=int(state["bad_epochs"]),
                          best_weights=state["best_weights"], optimizer=state["optimizer"],
                          scheduler=state["scheduler"], selected_nll=float(state.get("selected_nll", math.inf)),
                          selected_epoch=int(state.get("selected_epoch", 0)))


def _should_stop(progress: _StageProgress, min_epochs: int, patience: int) -> bool:
    """Early stopping: after `min_epochs`, `patience` epochs without a better validation loss (0 disables)."""
    return patience > 0 and progress.epoch >= min_epochs and progress.bad_epochs >= patience


def _copy_weights(model: nn.Module) -> dict[str, Tensor]:
    return {name: value.detach().to("cpu", copy=True) for name, value in model.state_dict().items()}

