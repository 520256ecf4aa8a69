"""The problems a run trains and validates on: the train split and the val split, or a seeded hold-out of train."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import data as data_module
from ..errors import DataError
from ..model.batch import SceneBatch
from ..model.config import DataSpec, RunConfig


@dataclass
class TrainingData:
    """The training and validation problems and what the model must know about them."""

    train: SceneBatch
    val: SceneBatch
    #: (n_val,) identical-input group of each validation problem (pools draws for the sample-based NLL)
    val_groups: np.ndarray
    spec: DataSpec
    fingerprint: dict[str, str]
    validation: str
    dataset_dir: Path


def load_data(dataset_dir: str | Path, fold: str | None, config: RunConfig) -> TrainingData:
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
    return TrainingData(train_batch, val_batch, val_groups, spec, dict(train_problems.fingerprint), validation,
                        Path(dataset_dir))


def _load_validation(dataset_dir: str | Path, fold: str | None) -> Any:
    """The val split's problems, or None when the protocol leaves it empty."""
    try:
        return data_module.load_problems(dataset_dir, fold=fold, split="val")
    except DataError as error:
        if "has no samples" in str(error):
            return None
        raise
