"""Reading a run directory written by `trajflow train`: its run.json and config.toml, checked, and the final model.

Every command that reads a run's own files (train --resume / --autoencoder-from, eval, status, experiment) reads
them here, so a damaged file is the same one-line DataError naming it wherever it is met.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..errors import DataError, TrajflowError, UsageError
from ..model.checkpoint import MODEL_FILE, load_model
from ..model.config import RunConfig, load_config
from ..model.models import TrajectoryModel
from ..util import input_files

CONFIG_FILE = "config.toml"
RUN_FILE = "run.json"
FINAL_DIR = "final"

#: The run.json keys trajflow reads and the JSON type each value must have (when present and not null).
RUN_FIELDS: dict[str, type] = {
    "model": str, "dataset": str, "fold": str, "seed": int, "status": str, "data_dir": str, "fingerprint": dict,
    "best": dict, "started": str, "finished": str, "code_revisions": list, "machines": list,
    "rank_weight_digests": list, "autoencoder_from": dict,
}
#: The run.json keys every run holds from its start (a run.json without one is damaged).
RUN_REQUIRED = ("model", "dataset", "seed", "status", "data_dir", "fingerprint")
#: run.json keys whose values are lists of strings.
_STRING_LISTS = ("code_revisions", "machines", "rank_weight_digests")
_JSON_TYPES = {str: "a string", int: "an integer", dict: "an object", list: "a list", float: "a number",
               bool: "true/false", type(None): "null"}


def read_run_info(run_dir: str | Path, required: tuple[str, ...] = ()) -> dict[str, Any] | None:
    """The run's run.json as a dict (None when it has none yet), with the values trajflow reads checked for their
    type and the `required` keys present: anything else (not UTF-8, not JSON, not an object, a wrong type) is a
    DataError naming the file."""
    path = Path(run_dir) / RUN_FILE
    if not path.exists():
        return None
    try:
        info = json.loads(input_files.read_text(path))
    except ValueError as error:
        raise DataError(f"unreadable run description: not valid JSON ({error})", path) from None
    except OSError as error:
        raise DataError(f"unreadable run description ({error.strerror or error})", path) from None
    if not isinstance(info, dict):
        raise DataError("unreadable run description: expected a JSON object, found "
                        f"{_JSON_TYPES.get(type(info), type(info).__name__)}", path)
    missing = [key for key in required if info.get(key) is None]
    if missing:
        raise DataError(f"incomplete run description (no {missing[0]!r})", path)
    for key, kind in RUN_FIELDS.items():
        value = info.get(key)
        if value is not None and (not isinstance(value, kind) or (kind is int and isinstance(value, bool))):
            raise DataError(f"{key!r} must be {_JSON_TYPES[kind]}, got {_short(value)}", path)
    for key in _STRING_LISTS:
        if not all(isinstance(item, str) for item in info.get(key) or ()):
            raise DataError(f"{key!r} must be a list of strings, got {_short(info[key])}", path)
    source = info.get("autoencoder_from")
    if source is not None and not isinstance(source.get("run"), str):
        raise DataError(f"'autoencoder_from' must name its run (a string 'run'), got {_short(source)}", path)
    return info


def read_run_config(run_dir: str | Path) -> RunConfig | None:
    """The run's saved config.toml (None when it has none): one that is not UTF-8 TOML, holds an unknown key or a
    value of the wrong type or out of bounds is a DataError naming the file (a damaged run, not a bad option)."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        return None
    try:
        return load_config(path)
    except UsageError as error:  # its message already starts with the file (and line, where it applies)
        raise DataError(str(error)) from None
    except OSError as error:
        raise DataError(f"unreadable ({error.strerror or error})", path) from None


def _short(value: Any) -> str:
    """A JSON value for a message, cut to a readable length."""
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


@dataclass(frozen=True)
class RunInfo:
    """A finished training run: identity, training data, resolved config and where its model lies."""

    path: Path
    model: str
    dataset: str
    fold: str | None
    seed: int
    data_path: Path
    fingerprint: dict[str, str] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    #: digest of the final weights (run.json; None for runs trained before trajflow recorded it)
    weights_digest: str | None = None
    #: the code revisions and the machines that trained it, oldest first (run.json; None where not recorded)
    code_revisions: tuple[str, ...] | None = None
    machines: tuple[str, ...] | None = None

    @property
    def name(self) -> str:
        return self.path.resolve().name

    @property
    def model_file(self) -> Path:
        """The final model's weights file."""
        return self.path / FINAL_DIR / MODEL_FILE

    def load_model(self, device: torch.device | str = "cpu") -> TrajectoryModel:
        """The final model of the run, checked to be of the run's model family."""
        return load_model(self.path / FINAL_DIR, expected_model=self.model, device=device)


def weights_digest(info: dict[str, Any]) -> str | None:
    """The digest of a finished run's final weights from its run.json (None when it was not recorded)."""
    digests = info.get("rank_weight_digests")
    return str(digests[0]) if isinstance(digests, list) and digests else None


def open_run(run_dir: str | Path) -> RunInfo:
    """Read a run directory's run.json and config; refuse runs that have no final model yet."""
    path = Path(run_dir)
    if not path.is_dir():
        raise TrajflowError(f"{path}: run directory not found")
    info = read_run_info(path, required=RUN_REQUIRED)
    if info is None:
        raise TrajflowError(f"{path}: not a trajflow run ({RUN_FILE} is missing); train one with `trajflow train`")
    if info.get("status") != "finished" or not (path / FINAL_DIR).is_dir():
        raise TrajflowError(f"{path}: the run has no final model (training did not finish); "
                            "continue it with `trajflow train ... --resume`")
    config = read_run_config(path)
    return RunInfo(path=path, model=info["model"], dataset=info["dataset"], fold=info.get("fold"), seed=info["seed"],
                   data_path=Path(info["data_dir"]), fingerprint=dict(info.get("fingerprint") or {}),
                   config=config.to_dict() if config is not None else {}, weights_digest=weights_digest(info),
                   code_revisions=_strings(info.get("code_revisions")), machines=_strings(info.get("machines")))


def _strings(value: Any) -> tuple[str, ...] | None:
    """A run.json list as a tuple of strings (None when absent)."""
    return tuple(map(str, value)) if isinstance(value, list) else None
