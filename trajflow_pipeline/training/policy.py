"""When a run may go on, and from where: resume checks, raised epoch budgets and starting from another run's
autoencoder (what each promises: `trajflow train` in docs/usage.md)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import polars as pl
import torch
from torch import Tensor

from ..errors import DataError, TrajflowError, UsageError
from ..model.checkpoint import MODEL_FILE, load_model, load_training_state
from ..model.config import EXECUTION_KEYS, RunConfig, load_config, toml_value
from ..model.models import MODEL_CLASSES, FlowModel, TrajectoryModel, build_model
from ..rundir import (CONFIG_FILE, FINAL_DIR, LOG_FILE, RUN_REQUIRED, STAGE_END_FILE, STATE_FILE, is_trained,
                      read_run_config, read_run_info)
from ..schemas import data_mismatch
from ..util import input_files
from .data import TrainingData
from .state import LOG_SCHEMA, check_state, progress_from, should_stop, state_config

#: Training settings that act on the flow stage alone: a run may start from the autoencoder of a run that differs
#: from it only in these (and in EXECUTION_KEYS: the device, compile_flow).
FLOW_STAGE_KEYS = ("flow_lr", "flow_weight_decay", "flow_batch_size", "flow_lr_decay", "flow_max_epochs",
                   "flow_min_epochs", "flow_patience", "flow_select", "flow_select_every", "flow_select_problems",
                   "flow_select_samples", "flow_select_max_pooled")
#: Model settings the autoencoder stage never reads: those of the flow and of the encoders of its context (the
#: target's past, the social GNN). Each component's initial weights come from its own random stream
#: (`component_stream`), so runs that differ only in these train the same autoencoder, and one may take the other's.
AUTOENCODER_FREE_MODEL_KEYS = ("flow_layers", "flow_bins", "flow_tail_bound", "flow_hidden", "flow_standardize",
                               "flow_temperature", "flow_temperature_grid", "flow_temperature_problems",
                               "past_embed", "past_hidden", "past_layers", "past_out", "gnn_layers", "gnn_width",
                               "gnn_aggregate")
#: The state-dict prefixes of the components those settings shape: a run that takes another's autoencoder takes
#: every other tensor (the autoencoder's weights, the data constants) from it and these from its own initialisation
#: (with the fitted sampling temperature of model.flow_temperature_grid, which comes after the flow).
_FLOW_SIDE_PREFIXES = ("flow.", "context.", "fitted_temperature")
#: Settings a resumed run may raise (its epoch budgets: how long a stage may go on), with the gradient stage each
#: one limits. None of them changes an epoch before the stage stops, which is what makes a raise exact.
BUDGET_KEYS = {"ae_max_epochs": "autoencoder", "flow_max_epochs": "flow", "ae_patience": "autoencoder",
               "flow_patience": "flow"}
#: Model settings of the closed-form stage "temperature" after the flow (FlowModel.TEMPERATURE): no stage before
#: it reads them, so a run may change them when it resumes, finished or not. A run past that stage goes back to the
#: end of its flow (its final flow: the stage changes no weight of it) and fits the stage anew, or drops it when the
#: grid is emptied (`refit_state`); a finished run needs no training state for that, its final model will do.
REFIT_MODEL_KEYS = ("flow_temperature_grid", "flow_temperature_problems", "speed_normalize_sample_threshold")
#: Of those, the ones that drawing reads (model.speed_normalize_sample_threshold: no training stage reads it, the
#: temperature stage and evaluation do): with model.speed_normalize on, a change re-finishes every finished run,
#: with or without the temperature stage, so that its final model and evaluation follow it.
DRAWING_MODEL_KEYS = ("speed_normalize_sample_threshold",)
#: The budget keys as users write them, for messages.
RAISABLE = " / ".join(f"train.{key}" for key in BUDGET_KEYS)
#: What a resumed run may change, for messages.
CHANGEABLE = f"{RAISABLE} may be raised, model.{' / model.'.join(REFIT_MODEL_KEYS)} changed"


# ---------------------------------------------------------------------------------------------------- epoch budgets

def budget_raise(old: RunConfig, new: RunConfig) -> dict[str, tuple[int, int]] | None:
    """The epoch budgets `new` raises over `old` ({key: (old, new)}), or None when the two configs differ in
    anything else (EXECUTION_KEYS and the REFIT_MODEL_KEYS of the stage after the flow aside: see `refit_change`)
    or lower a budget; {} when they are the same run."""
    old_train, new_train = old.train, new.train.with_execution_of(old.train)
    unchanged = replace(new_train, **{key: getattr(old_train, key) for key in BUDGET_KEYS})
    if replace(new.model, **{key: getattr(old.model, key) for key in REFIT_MODEL_KEYS}) != old.model \
            or unchanged != old_train:
        return None
    raised = {key: (getattr(old_train, key), getattr(new_train, key)) for key in BUDGET_KEYS
              if getattr(new_train, key) != getattr(old_train, key)}
    lowered = any(budget_size(key, after) < budget_size(key, before) for key, (before, after) in raised.items())
    return None if lowered else raised


def budget_size(key: str, value: int) -> float:
    """How long the budget `key` = `value` lets a stage go on, for ordering budgets: a patience of 0 disables early
    stopping, so it is larger than any other."""
    return math.inf if key.endswith("_patience") and value == 0 else float(value)


def refit_change(old: RunConfig, new: RunConfig) -> dict[str, tuple[Any, Any]]:
    """The settings of the stage after the flow (REFIT_MODEL_KEYS) that `new` changes over `old`, as
    {"model.key": (old, new)}."""
    return {f"model.{key}": (getattr(old.model, key), getattr(new.model, key)) for key in REFIT_MODEL_KEYS
            if getattr(old.model, key) != getattr(new.model, key)}


def refit_matters(old: RunConfig, new: RunConfig) -> bool:
    """Whether `new`'s settings of the stage after the flow change what a run of `old` ends with: they differ and
    the model has that stage under one of them, or they change its draws (:func:`changes_draws`); a grid for a
    model without it, or a new problem count with no grid either way, changes nothing."""
    changes = refit_change(old, new)
    stages_for = MODEL_CLASSES[new.model.name].stages_for
    return bool(changes) and (FlowModel.TEMPERATURE in (*stages_for(old.model), *stages_for(new.model))
                              or changes_draws(new, changes))


def changes_draws(config: RunConfig, changes: dict[str, tuple[Any, Any]]) -> bool:
    """Whether `changes` (:func:`refit_change`'s) hold a setting that drawing reads (DRAWING_MODEL_KEYS) and that
    acts in `config`'s model (model.speed_normalize on)."""
    return config.model.speed_normalize and any(f"model.{key}" in changes for key in DRAWING_MODEL_KEYS)


def describe_refit(changes: dict[str, tuple[Any, Any]]) -> str:
    """`refit_change`'s changes for a message, values as a config file writes them."""
    return ", ".join(f"{key} {toml_value(old)} -> {toml_value(new)}" for key, (old, new) in changes.items())


def refit_state(path: Path, state: dict[str, Any], config: RunConfig, model: TrajectoryModel
                ) -> tuple[dict[str, Any], bool]:
    """The training state `state` (read from `path`) made to fit `config`'s settings of the stage after the flow
    (REFIT_MODEL_KEYS) and `model`, built from `config`: its fitted temperature (a buffer, in the weights and the
    best weights) as `model` has it, unfitted; a state past the stage "temperature" taken back to its start, the
    stage's log rows and record left out, or, with the grid emptied, to the end of the stages. The state carries
    `config`'s values of those settings. Returns it and whether a finished run must be finished anew (it went
    back, it has a stage left now, or its draws change: :func:`changes_draws`); a state whose config matches
    `config` there is returned as it is."""
    trained = state_config(path, state)
    changes = refit_change(trained, config)
    if not changes:
        return state, False
    buffer = model.state_dict().get("fitted_temperature")

    def aligned(weights: Any) -> Any:
        if not isinstance(weights, dict):
            return weights  # check_state refuses it, naming the file
        kept = {name: tensor for name, tensor in weights.items() if name != "fitted_temperature"}
        return kept if buffer is None else {**kept, "fitted_temperature": torch.full_like(buffer, math.nan)}

    old_stages = type(model).stages_for(trained.model)
    reached = int(state["stage_index"]) if isinstance(state.get("stage_index"), int) else 0
    went_back = FlowModel.TEMPERATURE in old_stages and reached > old_stages.index(FlowModel.TEMPERATURE)
    carried = replace(trained, model=replace(trained.model, **{key: getattr(config.model, key)
                                                               for key in REFIT_MODEL_KEYS}))
    state = {**state, "config": carried.to_json(), "weights": aligned(state.get("weights")),
             "best_weights": aligned(state.get("best_weights"))}
    if went_back and isinstance(state.get("log"), list) and isinstance(state.get("best"), dict):
        state.update(stage_index=old_stages.index(FlowModel.TEMPERATURE),
                     log=[row for row in state["log"]
                          if not isinstance(row, dict) or row.get("stage") != FlowModel.TEMPERATURE],
                     best={stage: record for stage, record in state["best"].items()
                           if stage != FlowModel.TEMPERATURE})
    # a run that had done all its stages and now has one left (or must write its final model without one, or
    # with a setting its draws read)
    finished = reached >= len(old_stages)
    redo = went_back or (finished and int(state.get("stage_index", 0)) < len(model.stages)) \
        or (finished and changes_draws(config, changes))
    return state, redo


def finished_state(run_dir: Path) -> dict[str, Any]:
    """The training state after the last stage of the finished run `run_dir` kept without its checkpoints (a
    published model): its final model's weights, its log and run.json's records. What it lacks (optimizer, best
    weights of a stage) no stage reads once the gradient stages are over, so it serves to refit the stage after the
    flow (`refit_state`), and nothing that would train again."""
    config = read_run_config(run_dir)
    if config is None:
        raise UsageError(f"{run_dir}: no {CONFIG_FILE} beside its final model")
    model = load_model(run_dir / FINAL_DIR)
    info = run_info(run_dir)
    log_path = run_dir / LOG_FILE
    if not log_path.is_file():
        raise UsageError(f"{run_dir}: a final model without its training log ({LOG_FILE})")
    log = _log_rows(log_path)
    return {"model": model.name, "config": config.to_json(), "stage_index": len(model.stages), "epoch": 0,
            "best_val": math.inf, "best_epoch": 0, "bad_epochs": 0,
            "weights": {name: tensor.detach().clone() for name, tensor in model.state_dict().items()},
            "best_weights": None, "selected_nll": math.inf, "selected_epoch": 0, "optimizer": None,
            "scheduler": None, "log": log.to_dicts(), "best": dict(info.get("best") or {}),
            "skipped_total": int(log.get_column("skipped_steps").sum()), "started": str(info.get("started", "")),
            "code_revisions": info.get("code_revisions"), "machines": info.get("machines")}


def _log_rows(log_path: Path) -> pl.DataFrame:
    """A run's training log with LOG_SCHEMA's columns (val_nll, absent from older logs, as nulls)."""
    log = input_files.read_parquet(log_path)
    missing = sorted(set(LOG_SCHEMA) - set(log.columns) - {"val_nll"})
    if missing:
        raise DataError(f"not a training log: no column {missing[0]!r}", log_path)
    if "val_nll" not in log.columns:
        log = log.with_columns(val_nll=pl.lit(None, dtype=pl.Float64))
    return log.select(list(LOG_SCHEMA)).cast(LOG_SCHEMA)


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
    if raised and is_trained(run_dir) and not (run_dir / STATE_FILE).is_file():
        return (f"{run_dir}: its training state ({STATE_FILE}) is not kept (a published copy keeps only the final "
                "model), so it cannot continue with a larger budget")
    log_path = run_dir / LOG_FILE
    log = input_files.read_parquet(log_path) if log_path.is_file() else pl.DataFrame(schema=LOG_SCHEMA)
    stages = log.get_column("stage").to_list()
    for key, (old_value, _) in raised.items():
        stage = BUDGET_KEYS[key]
        later = any(s != stage for s in stages[stages.index(stage):]) if stage in stages else False
        finished = later or (stage == "flow" and is_trained(run_dir))
        # a raised limit matters only to a stage that reached it; more patience, to one that stopped below its limit
        epochs = stages.count(stage)
        matters = (epochs >= old_value if key.endswith("_max_epochs")
                   else epochs < requested.train.schedule(stage).max_epochs)
        if finished and matters and not (run_dir / STAGE_END_FILE.format(stage=stage)).is_file():
            return (f"{run_dir}: its {stage} stage finished before trajflow kept stage-end states, so it cannot "
                    f"continue with a larger train.{key}")
    return None


def first_difference(a: RunConfig, b: RunConfig) -> str:
    """The first setting in which two configs differ, as "section.key: a vs b"."""
    left, right = a.to_dict(), b.to_dict()
    for section in left:
        for key in left[section]:
            if left[section][key] != right[section][key]:
                return f"{section}.{key}: {left[section][key]!r} vs {right[section][key]!r}"
    return "unknown difference"


@dataclass
class Resumption:
    """How a resumed run goes on from its checkpoint (:func:`follow_budget`)."""

    #: the config it goes on with
    config: RunConfig
    #: the training state to go on from (when `finished`: to save as the run's state)
    state: dict[str, Any]
    #: a finished stage was reopened by a raised budget, or the stage after the flow is to be fitted anew
    reopened: bool = False
    #: the state and the config must be saved before training goes on
    save: bool = False
    #: the run is finished and stays as it is once its state and config are saved
    finished: bool = False


def follow_budget(run_dir: Path, config: RunConfig, model: TrajectoryModel, state: dict[str, Any],
                  say: Callable[[str], None]) -> Resumption:
    """Reconcile the checkpoint `state` (as read, unchecked) with the run's `config` when their epoch budgets or
    the settings of the stage after the flow differ.

    A config that raises the budgets of the checkpoint's moves the run to them (`_reopen`). A checkpoint that
    raises the config's is an earlier raise whose config.toml was not yet written: the run goes on with it. Other
    settings of the stage after the flow make the state fit them (`refit_state`); a run past that stage goes back
    to its start and is finished anew. Any other difference is an error."""
    changes = refit_change(state_config(run_dir / STATE_FILE, state), config)
    state, refitted = refit_state(run_dir / STATE_FILE, state, config, model)
    check_state(run_dir / STATE_FILE, state, model)
    if changes:
        what = ("the run is finished anew on its final flow (the stage after the flow fitted again where it has "
                "one)" if refitted
                else "recorded for the stage after the flow, which this run has not reached or does not have")
        say(f"{describe_refit(changes)}: {what}")
    trained = state_config(run_dir / STATE_FILE, state)
    trained = replace(trained, train=trained.train.with_execution_of(config.train))
    if trained == config:
        if not refitted and int(state["stage_index"]) >= len(model.stages) and is_trained(run_dir):
            # nothing left to train or fit (new execution settings, or a grid for no stage): only recorded
            return Resumption(config, state, finished=True)
        return Resumption(config, state, reopened=refitted, save=bool(changes))
    if budget_raise(config, trained):
        say("continuing the larger budget an interrupted call gave this run")
        return Resumption(trained, state, save=True)
    if budget_raise(trained, config) is None:
        raise TrajflowError(f"{run_dir / STATE_FILE}: checkpoint does not match {CONFIG_FILE}")
    start, reopened = _reopen(run_dir, config, model, state, trained, say)
    start = {**start, "config": config.to_json()}
    if not (reopened or refitted) and int(start["stage_index"]) >= len(model.stages) and is_trained(run_dir):
        return Resumption(config, start, finished=True)
    return Resumption(config, start, reopened=reopened or refitted, save=True)


def _reopen(run_dir: Path, config: RunConfig, model: TrajectoryModel, state: dict[str, Any], trained: RunConfig,
            say: Callable[[str], None]) -> tuple[dict[str, Any], bool]:
    """The state to continue from under the raised budgets of `config` over `trained`: the end state of the first
    finished stage whose budget was raised and that the new budget would not have stopped at its last epoch, and
    True; else `state` and False. Stages after a reopened one are trained again from their start."""
    log_stages = [row["stage"] for row in state["log"]]
    for index, stage in enumerate(model.stages[:int(state["stage_index"])]):
        raised = [key for key, limited in BUDGET_KEYS.items()
                  if limited == stage and budget_size(key, getattr(config.train, key))
                  > budget_size(key, getattr(trained.train, key))]
        if not raised:
            continue
        old, new = trained.train.schedule(stage), config.train.schedule(stage)
        change = ", ".join(f"train.{key} {getattr(trained.train, key)} -> {getattr(config.train, key)}"
                           for key in raised)
        epochs = log_stages.count(stage)
        limit_only = all(key.endswith("_max_epochs") for key in raised)
        if (limit_only and epochs < old.max_epochs) or epochs >= new.max_epochs:
            say(f"{stage} ran {epochs} of {old.max_epochs} epochs: {change} changes nothing there")
            continue
        end_path = run_dir / STAGE_END_FILE.format(stage=stage)
        if not end_path.is_file():
            raise UsageError(f"{run_dir}: its {stage} stage finished before trajflow kept stage-end states "
                             f"({end_path.name} is missing), so it cannot continue with {change}; train into a "
                             f"new directory")
        end, _ = refit_state(end_path, load_training_state(end_path, expected_model=model.name), config, model)
        check_state(end_path, end, model)
        progress = progress_from(end)
        if progress.epoch >= new.max_epochs or should_stop(progress, new.min_epochs, new.patience):
            say(f"{stage} would have stopped at its last epoch ({epochs}) with {change} too: nothing changes there")
            continue
        later = model.stages[index + 1:]
        say(f"continuing {stage} after epoch {epochs} ({change})"
            + (f"; then {', '.join(later)} from the start" if later else ""))
        return end, True
    return state, False


# ----------------------------------------------------------------------------------------------------------- resume

def run_info(run_dir: Path) -> dict[str, Any]:
    """The run's run.json, checked, with every key training writes at its start (:func:`~..rundir.read_run_info`;
    {} when it has none yet)."""
    return read_run_info(run_dir, required=RUN_REQUIRED) or {}


def resume_fold(run_dir: Path, fold: str | None) -> str | None:
    """The fold a resumed run continues on: the one it was started for (so ``--resume`` needs no ``--fold``);
    a different `fold` is refused, since the run's weights were fitted to the other fold's training data."""
    recorded = run_info(run_dir).get("fold")
    if recorded is None:
        return fold
    if fold is not None and str(fold) != str(recorded):
        raise UsageError(f"{run_dir} was started for fold {recorded!r}, not {fold!r}; resume it without --fold "
                         "(or with its own), or train into a new directory")
    return str(recorded)


def check_same_data(run_dir: Path, data: TrainingData, resume: bool) -> None:
    """On resume, refuse data other than the run started on (other dataset, or its manifest changed)."""
    if not resume:
        return
    mismatch = data_mismatch(run_info(run_dir).get("fingerprint", {}), data.fingerprint)
    if mismatch:
        raise UsageError(f"{run_dir} was trained on other data ({mismatch})")


# ------------------------------------------------------------------------------------------ autoencoder from a run

def started_from(run_dir: Path, resume: bool, source: Path) -> bool:
    """Whether `run_dir` already holds a resumable run taken from `source`'s autoencoder (so resume it as is).
    A resumable run from anything else is refused: its autoencoder is not `source`'s."""
    if not (resume and (run_dir / STATE_FILE).is_file()):
        return False
    recorded = run_info(run_dir).get("autoencoder_from") or {}
    if recorded.get("run") != str(source.resolve()):
        raise UsageError(f"{run_dir} already holds a run that did not start from {source}'s autoencoder; resume it "
                         "without --autoencoder-from, or train into a new directory")
    return True


def source_record(run_dir: Path, source: Path | None, start: dict[str, Any] | None) -> dict[str, Any] | None:
    """What run.json says about the run whose autoencoder this one took: from `start` for a new run, else what
    the run's own run.json already says (None for a run that trained its own)."""
    if start is not None and source is not None:
        epochs = sum(1 for row in start["log"] if row["stage"] == "autoencoder")
        return {"run": str(source.resolve()), "autoencoder_epochs": epochs,
                "autoencoder_best_epoch": int(start["best_epoch"])}
    return run_info(run_dir).get("autoencoder_from")


def autoencoder_start(source: Path, config: RunConfig, data: TrainingData, fold: str | None) -> dict[str, Any]:
    """The training state a new run with `config` starts from when it takes the autoencoder of the run in `source`:
    that run's state at the end of its autoencoder stage (its ``checkpoints/end-autoencoder.pt``, or, for a run
    kept without checkpoints such as a published model, rebuilt from its final model, log and run.json), carrying
    `config`, with the flow and context encoders as `config` initialises them. Refused (UsageError naming the
    difference) unless `source` trained the same model on the same data and fold with the same settings, flow
    training settings and AUTOENCODER_FREE_MODEL_KEYS aside, so that its autoencoder is the one `config` would
    train."""
    end_path = source / STAGE_END_FILE.format(stage="autoencoder")
    if end_path.is_file():
        state = load_training_state(end_path)
        where = end_path
    elif is_trained(source):
        state, where = _state_from_final(source), source / FINAL_DIR / MODEL_FILE
    else:
        raise UsageError(f"{source}: no finished autoencoder stage to start from ({end_path.name} is missing and "
                         "there is no finished final model)")
    info = run_info(source)
    check_same_data(source, data, resume=True)
    if info.get("fold") != fold:
        raise UsageError(f"{source} was trained for fold {info.get('fold')!r}, this run is for {fold!r}")
    if state.get("model") != config.model.name:
        raise UsageError(f"{where}: a {state.get('model')!r} run; this run trains {config.model.name!r}")
    trained = state_config(where, state)
    flow_settings = {key: getattr(config.train, key) for key in (*FLOW_STAGE_KEYS, *EXECUTION_KEYS)}
    flow_model = {key: getattr(config.model, key) for key in AUTOENCODER_FREE_MODEL_KEYS}
    comparable = replace(trained, train=replace(trained.train, **flow_settings),
                         model=replace(trained.model, **flow_model))
    if comparable != config:
        raise UsageError(f"{source} trained its autoencoder with other settings "
                         f"({first_difference(comparable, config)}); only train.flow_* settings and the flow's and "
                         "context encoders' model settings may differ")
    check_state(where, state, build_model(trained.model, data.spec))
    fresh = _initial_weights(config, data)
    return {**state, "config": config.to_json(), "weights": _autoencoder_into(fresh, state["weights"]),
            "best_weights": (None if state["best_weights"] is None
                             else _autoencoder_into(fresh, state["best_weights"]))}


def _state_from_final(source: Path) -> dict[str, Any]:
    """The end-of-autoencoder training state of a finished run kept without its checkpoints: its state after the
    last stage (:func:`finished_state`) taken back to the autoencoder's end, with the autoencoder's best weights
    from the final model (the flow stage never changes them), its epochs from the log, its best epoch from
    run.json. What it lacks (the last epoch's weights, the optimizer) the stage, being over, never reads."""
    if read_run_config(source) is None:
        raise UsageError(f"{source}: no {CONFIG_FILE} beside its final model, so its autoencoder's settings are "
                         "unknown")
    best = (run_info(source).get("best") or {}).get("autoencoder")
    if not (source / LOG_FILE).is_file() or not isinstance(best, dict) or not {"epoch", "val_loss"} <= set(best):
        raise UsageError(f"{source}: a final model without its training log or run.json's best autoencoder epoch; "
                         "its autoencoder stage cannot be taken")
    state = finished_state(source)
    log = [row for row in state["log"] if row["stage"] == "autoencoder"]
    epochs, best_epoch = len(log), int(best["epoch"])
    return {**state, "stage_index": 0, "epoch": epochs, "best_val": float(best["val_loss"]),
            "best_epoch": best_epoch, "bad_epochs": epochs - best_epoch, "best_weights": state["weights"],
            "log": log, "best": {"autoencoder": best}, "skipped_total": sum(row["skipped_steps"] for row in log)}


def _initial_weights(config: RunConfig, data: TrainingData) -> dict[str, Tensor]:
    """The weights a fresh run of `config` starts with (Session.run builds its model so), torch's global random
    state left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.train.seed)
        return build_model(config.model, data.spec, seed=config.train.seed).state_dict()


def _autoencoder_into(fresh: dict[str, Tensor], source: dict[str, Tensor]) -> dict[str, Tensor]:
    """`fresh` with every tensor but the flow's and the context encoders' taken from `source`."""
    return {name: (tensor if name.startswith(_FLOW_SIDE_PREFIXES) else source[name]).clone()
            for name, tensor in fresh.items()}
