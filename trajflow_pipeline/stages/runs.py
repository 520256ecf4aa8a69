"""Opening a run directory written by `trajflow train`: what was trained, on what, and the final model."""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..errors import TrajflowError
from ..model.checkpoint import load_model
from ..model.models import TrajectoryModel
from .train import CONFIG_FILE, FINAL_DIR, RUN_FILE


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
    info_path = path / RUN_FILE
    if not path.is_dir():
        raise TrajflowError(f"{path}: run directory not found")
    if not info_path.exists():
        raise TrajflowError(f"{path}: not a trajflow run ({RUN_FILE} is missing); train one with `trajflow train`")
    try:
        info = json.loads(info_path.read_text())
    except json.JSONDecodeError as error:
        raise TrajflowError(f"{info_path}: unreadable ({error})") from None
    if info.get("status") != "finished" or not (path / FINAL_DIR).is_dir():
        raise TrajflowError(f"{path}: the run has no final model (training did not finish); "
                            "continue it with `trajflow train ... --resume`")
    config: dict[str, Any] = {}
    if (path / CONFIG_FILE).exists():
        try:
            config = tomllib.loads((path / CONFIG_FILE).read_text())
        except tomllib.TOMLDecodeError as error:
            raise TrajflowError(f"{path / CONFIG_FILE}: unreadable ({error})") from None
    try:
        return RunInfo(path=path, model=str(info["model"]), dataset=str(info["dataset"]), fold=info.get("fold"),
                       seed=int(info["seed"]), data_path=Path(info["data_dir"]),
                       fingerprint=dict(info.get("fingerprint", {})), config=config,
                       weights_digest=weights_digest(info),
                       code_revisions=_strings(info.get("code_revisions")), machines=_strings(info.get("machines")))
    except (KeyError, TypeError, ValueError) as error:
        raise TrajflowError(f"{info_path}: incomplete run description ({error})") from None


def _strings(value: Any) -> tuple[str, ...] | None:
    """A run.json list as a tuple of strings (None when absent)."""
    return tuple(map(str, value)) if isinstance(value, list) else None
