"""What training keeps between calls: the training log's columns, a stage's early-stopping bookkeeping and the
resumable training state (state.pt, end-<stage>.pt), checked before a run continues from it."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl
from torch import Tensor, nn

from ..errors import DataError, TrajflowError
from ..model.checkpoint import check_weights, load_training_state
from ..model.config import RunConfig
from ..model.models import TrajectoryModel

LOG_SCHEMA = {"epoch": pl.Int64, "stage": pl.String, "train_loss": pl.Float64, "val_loss": pl.Float64,
              "lr": pl.Float64, "seconds": pl.Float64, "skipped_steps": pl.Int64, "samples_per_s": pl.Float64,
              "val_nll": pl.Float64}

#: What a training state (state.pt, end-<stage>.pt) holds: each key and the types its value may have.
STATE_FIELDS: dict[str, tuple[type, ...]] = {
    "model": (str,), "config": (str,), "stage_index": (int,), "epoch": (int,), "best_val": (float, int),
    "best_epoch": (int,), "bad_epochs": (int,), "weights": (dict,), "best_weights": (dict, type(None)),
    "optimizer": (dict, type(None)), "scheduler": (dict, type(None)), "log": (list,), "best": (dict,),
    "skipped_total": (int,), "started": (str,), "selected_nll": (float, int), "selected_epoch": (int,),
}
#: Keys of STATE_FIELDS that states written before them lack (their defaults are read in `progress_from`).
_STATE_OPTIONAL = ("selected_nll", "selected_epoch")


@dataclass
class StageProgress:
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


def progress_from(state: dict[str, Any]) -> StageProgress:
    """The stage bookkeeping stored in a training state."""
    return StageProgress(epoch=int(state["epoch"]), best_val=float(state["best_val"]),
                         best_epoch=int(state["best_epoch"]), bad_epochs=int(state["bad_epochs"]),
                         best_weights=state["best_weights"], optimizer=state["optimizer"],
                         scheduler=state["scheduler"], selected_nll=float(state.get("selected_nll", math.inf)),
                         selected_epoch=int(state.get("selected_epoch", 0)))


def should_stop(progress: StageProgress, min_epochs: int, patience: int) -> bool:
    """Early stopping: after `min_epochs`, `patience` epochs without a better validation loss (0 disables)."""
    return patience > 0 and progress.epoch >= min_epochs and progress.bad_epochs >= patience


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
