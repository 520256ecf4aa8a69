"""Model files and training-state files that load without unpickling arbitrary objects.

* A *model file* (``model.safetensors``) holds the weights as safetensors and, in the safetensors metadata, the
  model family, its :class:`ModelConfig`, the :class:`DataSpec`, the log-likelihood space and the format version
  as JSON strings. :func:`load_model` rebuilds the model from that alone.
* A *training-state file* (``state.pt``) holds everything needed to resume training (weights, optimiser and
  scheduler state, early-stopping bookkeeping, the training log) as plain containers of tensors and numbers,
  written with ``torch.save`` and read back with ``torch.load(weights_only=True)``.

Both are written atomically (temporary file, fsync, rename): a killed run leaves the previous file intact. A file
of another model family or of another major format version, or weights that do not fit the architecture the file
describes, are refused with a one-line :class:`DataError` naming the file.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import save as safetensors_save

from .. import __version__
from ..errors import DataError, TrajflowError
from ..util.atomic import atomic_write_bytes
from .config import DataSpec, RunConfig
from .models import TrajectoryModel, build_model
from .runtime import tune_cpu_allocator

MODEL_FORMAT = "trajflow-model"
STATE_FORMAT = "trajflow-train-state"
#: major.minor; a different major version cannot be read.
FORMAT_VERSION = "1.0"
MODEL_FILE = "model.safetensors"


def save_model(model: TrajectoryModel, path: str | Path, extra: dict[str, Any] | None = None) -> Path:
    """Write `model` to `path` (a ``.safetensors`` file, or a directory that receives ``model.safetensors``)."""
    path = _model_path(Path(path))
    tensors = {name: value.detach().to("cpu").contiguous() for name, value in model.state_dict().items()}
    metadata = {
        "format": MODEL_FORMAT,
        "format_version": FORMAT_VERSION,
        "model": model.name,
        "log_lik_space": model.log_lik_space,
        "config": json.dumps(RunConfig(model=model.config).to_dict()["model"], sort_keys=True),
        "spec": json.dumps(model.spec.to_dict(), sort_keys=True),
        "trajflow_version": __version__,
        "extra": json.dumps(extra or {}, sort_keys=True),
    }
    atomic_write_bytes(path, safetensors_save(tensors, metadata=metadata))
    return path


def read_model_metadata(path: str | Path) -> dict[str, Any]:
    """The decoded metadata of a model file (model, config, spec, versions, extra) without building the model."""
    path = _model_path(Path(path))
    metadata, _ = _read_safetensors(path, tensors=False)
    return _decode_metadata(path, metadata)


def load_model(path: str | Path, expected_model: str | None = None,
               device: str | torch.device = "cpu") -> TrajectoryModel:
    """Rebuild a model from a model file (or a folder holding ``model.safetensors``, such as a run's final/), in
    eval mode.

    Raises :class:`DataError` naming the file when it is missing, unreadable, of another format version, of
    another model family than `expected_model`, or does not match the architecture its config describes.
    """
    tune_cpu_allocator()
    path = _model_path(Path(path))
    metadata, tensors = _read_safetensors(path, tensors=True)
    meta = _decode_metadata(path, metadata)
    if expected_model is not None and meta["model"] != expected_model:
        raise DataError(f"checkpoint is a {meta['model']!r} model, not {expected_model!r}", path)
    try:
        model = build_model(meta["config"], meta["spec"])
    except (RuntimeError, ValueError, KeyError, TypeError, TrajflowError) as exc:
        raise DataError(f"checkpoint metadata describes no buildable {meta['model']!r} model ({_short(exc)})",
                        path) from None
    check_weights(path, tensors, model)
    model.load_state_dict(tensors, strict=True)
    return model.to(device).eval()


def check_weights(path: str | Path, weights: Any, model: torch.nn.Module, what: str = "weights") -> None:
    """Refuse (DataError naming `path`) `weights` that are not the tensors `model` holds: not a table of tensors,
    a missing or an unexpected name, or a tensor of another shape, as in a damaged file or one written for another
    architecture than its config describes. `what` names the part of the file in the message."""
    if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
        raise DataError(f"{what} are not a table of tensors", path)
    expected = model.state_dict()
    differs = f"{what} do not match the architecture the config describes"
    for names, kind in ((sorted(set(expected) - set(weights)), "no tensor"),
                        (sorted(set(weights) - set(expected)), "unexpected tensor")):
        if names:
            more = f" (and {len(names) - 1} more)" if len(names) > 1 else ""
            raise DataError(f"{differs}: {kind} {names[0]!r}{more}", path)
    for name, tensor in expected.items():
        if weights[name].shape != tensor.shape:
            raise DataError(f"{differs}: tensor {name!r} has shape {list(weights[name].shape)}, not "
                            f"{list(tensor.shape)}", path)


def save_training_state(path: str | Path, state: dict[str, Any]) -> None:
    """Atomically write a resumable training state (plain containers of tensors / numbers / strings)."""
    payload = {"format": STATE_FORMAT, "format_version": FORMAT_VERSION, **state}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_training_state(path: str | Path, expected_model: str | None = None) -> dict[str, Any]:
    """Read a training state written by :func:`save_training_state` with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise DataError("training state not found", path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to parse means a corrupt or foreign file
        raise DataError(f"not a readable trajflow training state ({_short(exc)})", path) from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise DataError("not a trajflow training state", path)
    _check_version(path, str(state.get("format_version", "")))
    if expected_model is not None and state.get("model") != expected_model:
        raise DataError(f"training state is for a {state.get('model')!r} model, not {expected_model!r}", path)
    return state


def _model_path(path: Path) -> Path:
    """A model file, or the model file inside a directory."""
    return path / MODEL_FILE if path.is_dir() or path.suffix == "" else path


def _read_safetensors(path: Path, tensors: bool) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    if not path.is_file():
        raise DataError("checkpoint not found", path)
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
            values = {name: handle.get_tensor(name) for name in handle.keys()} if tensors else {}
    except Exception as exc:  # noqa: BLE001 - safetensors raises several types for corrupt files
        raise DataError(f"not a readable trajflow checkpoint ({_short(exc)})", path) from None
    return metadata, values


def _decode_metadata(path: Path, metadata: dict[str, str]) -> dict[str, Any]:
    if metadata.get("format") != MODEL_FORMAT:
        raise DataError("not a trajflow model checkpoint", path)
    _check_version(path, metadata.get("format_version", ""))
    try:
        config = RunConfig.from_dict({"model": json.loads(metadata["config"])}, source=str(path)).model
        spec = DataSpec.from_dict(json.loads(metadata["spec"]))
        extra = json.loads(metadata.get("extra", "{}"))
    except (KeyError, ValueError, TypeError, TrajflowError) as exc:
        raise DataError(f"checkpoint metadata is damaged ({_short(exc)})", path) from None
    if config.name != metadata.get("model"):
        raise DataError(f"checkpoint metadata is inconsistent (model {metadata.get('model')!r})", path)
    return {"model": metadata["model"], "config": config, "spec": spec, "extra": extra,
            "log_lik_space": metadata.get("log_lik_space", ""), "format_version": metadata["format_version"],
            "trajflow_version": metadata.get("trajflow_version", "")}


def _check_version(path: Path, version: str) -> None:
    major = version.split(".")[0]
    if major != FORMAT_VERSION.split(".")[0]:
        raise DataError(f"checkpoint format version {version or '?'} is not supported "
                        f"(this trajflow reads {FORMAT_VERSION.split('.')[0]}.x)", path)


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def model_digest(model: torch.nn.Module) -> str:
    """sha256 over a model's state (each entry's name and bytes, in name order): run.json records it of the final
    weights, and evaluation checks the weights it loads against it and records it of what it evaluated."""
    digest = hashlib.sha256()
    for name, value in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(value.detach().to("cpu").contiguous().numpy().tobytes())
    return digest.hexdigest()
