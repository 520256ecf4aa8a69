"""TrajFlow and its baselines in pure torch: normalisation, autoencoder, conditional flow, context encoders.

Nothing here knows about files other than :mod:`.checkpoint`; the data side hands over a :class:`SceneBatch`.

    >>> model = build_model(ModelConfig(name="trajflow"), DataSpec(n_past=8, n_future=12))
    >>> loss = model.stage_loss("autoencoder", batch)           # stage 1, then "flow"
    >>> trajectories, log_lik = model.sample(batch, n=20)       # (B, 20, 12, 2) world coords, (B, 20)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: public name -> the submodule that defines it; submodules load on first use, so that importing
#: ``trajflow_pipeline.model.config`` (the CLI does, for --help) does not load torch
_EXPORTS = {
    **dict.fromkeys(("AGENT_TYPES", "NUM_AGENT_TYPES", "SceneBatch"), "batch"),
    **dict.fromkeys(("FORMAT_VERSION", "MODEL_FILE", "load_model", "load_training_state", "read_model_metadata",
                     "save_model", "save_training_state"), "checkpoint"),
    **dict.fromkeys(("MODEL_NAMES", "DataSpec", "ModelConfig", "RunConfig", "TrainConfig", "apply_overrides",
                     "load_config"), "config"),
    **dict.fromkeys(("MODEL_CLASSES", "ConstantVelocity", "FloMo", "Samples", "TrajectoryModel", "TrajFlow",
                     "TrajFlowNoAE", "build_model"), "models"),
    **dict.fromkeys(("fit_threads_to_idle_cpus", "resolve_device", "tune_cpu_allocator"), "runtime"),
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


if TYPE_CHECKING:
    from .batch import AGENT_TYPES, NUM_AGENT_TYPES, SceneBatch
    from .checkpoint import (FORMAT_VERSION, MODEL_FILE, load_model, load_training_state, read_model_metadata,
                             save_model, save_training_state)
    from .config import MODEL_NAMES, DataSpec, ModelConfig, RunConfig, TrainConfig, apply_overrides, load_config
    from .models import (MODEL_CLASSES, ConstantVelocity, FloMo, Samples, TrajectoryModel, TrajFlow, TrajFlowNoAE,
                         build_model)
    from .runtime import fit_threads_to_idle_cpus, resolve_device, tune_cpu_allocator

__all__ = [
    "AGENT_TYPES", "NUM_AGENT_TYPES", "SceneBatch",
    "FORMAT_VERSION", "MODEL_FILE", "load_model", "load_training_state", "read_model_metadata", "save_model",
    "save_training_state",
    "MODEL_NAMES", "DataSpec", "ModelConfig", "RunConfig", "TrainConfig", "apply_overrides", "load_config",
    "MODEL_CLASSES", "ConstantVelocity", "FloMo", "Samples", "TrajectoryModel", "TrajFlow", "TrajFlowNoAE",
    "build_model",
    "fit_threads_to_idle_cpus", "resolve_device", "tune_cpu_allocator",
]
