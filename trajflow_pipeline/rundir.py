"""The run directory `trajflow train` writes and `trajflow eval` adds to: the one module that names its files, reads
and writes run.json and config.toml, and says what state a run is in (trained, evaluated).

Layout::

    RUN/config.toml                 the resolved configuration ([model], [train]) the run trains and resumes with
    RUN/run.json                    model, dataset, fold, seed, data fingerprint, trajflow version, split sizes,
                                    best epochs, skipped steps, status ("training" / "finished"), provenance
    RUN/train_log.parquet           epoch, stage, train_loss, val_loss, lr, seconds, skipped_steps, samples_per_s
    RUN/checkpoints/state.pt        the last epoch's full training state (--resume continues from it)
    RUN/checkpoints/end-<stage>.pt  the state at the last epoch of each finished gradient stage (what a larger
                                    epoch budget continues that stage from)
    RUN/checkpoints/best-<stage>.safetensors, lowest-val-loss-<stage>.safetensors   a stage's best weights so far
    RUN/checkpoints/compiled-kernels.bin   the kernels torch.compile made for the run's compiled steps (a cache:
                                    a resume loads them instead of generating them again; damaged, it is ignored)
    RUN/final/model.safetensors     the trained model (and model.json); final/ appears when training finished
    RUN/eval/                       eval.json, metrics.parquet, predictions.parquet, ground_truth.parquet
    RUN/eval-cache/, RUN/.eval.lock an evaluation in progress: its saved ROME fits, its claim

Every command that reads a run's own files reads them here, so a damaged file is the same one-line DataError
naming it wherever it is met.

A copy of a run that keeps only :func:`continuation_files` goes on where the run stands on another machine: an
evaluated copy without its draws still counts as evaluated (:func:`is_evaluated` reads eval.json and
metrics.parquet only), a trained one is evaluated and not trained again, and one in training resumes from its last
checkpoint (docs/results/publish.py publishes and restores such copies).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .errors import DataError, TrajflowError, UsageError
from .model.checkpoint import MODEL_FILE, load_model
from .model.config import RunConfig, load_config
from .model.models import TrajectoryModel
from .util import input_files
from .util.atomic import atomic_write_bytes, atomic_write_text

CONFIG_FILE = "config.toml"
RUN_FILE = "run.json"
#: the training log; older runs (and other tools) may hold it as CSV
LOG_FILE = "train_log.parquet"
LOG_FILES = ("train_log.csv", LOG_FILE)
CHECKPOINT_DIR = "checkpoints"
STATE_FILE = f"{CHECKPOINT_DIR}/state.pt"
#: The training state at the last epoch of a finished gradient stage, formatted with the stage name.
STAGE_END_FILE = f"{CHECKPOINT_DIR}/end-{{stage}}.pt"
#: The best weights of a stage so far by the run's selection rule, and by the validation loss alone.
BEST_FILE = f"{CHECKPOINT_DIR}/best-{{stage}}.safetensors"
LOWEST_VAL_LOSS_FILE = f"{CHECKPOINT_DIR}/lowest-val-loss-{{stage}}.safetensors"
#: The kernels of the run's compiled training steps (:func:`write_compiled_kernels`).
COMPILED_KERNELS_FILE = f"{CHECKPOINT_DIR}/compiled-kernels.bin"
#: Its first line; the second is JSON: the torch version that compiled the kernels and the SHA-256 of the rest.
_KERNELS_HEADER = b"trajflow compiled kernels 1\n"
FINAL_DIR = "final"
#: what final/ holds besides the weights: the best epochs and the weights' digest, for people
MODEL_INFO_FILE = "model.json"
EVAL_DIR = "eval"
EVAL_FILE = "eval.json"
METRICS_FILE = "metrics.parquet"
PREDICTIONS_FILE = "predictions.parquet"
GROUND_TRUTH_FILE = "ground_truth.parquet"
#: the ROME fits an evaluation in progress has saved (resumable), removed when it is written
ROME_CACHE_DIR = "eval-cache"
#: held by the one evaluation of a run that may run at a time
EVAL_LOCK = ".eval.lock"
#: what only a run holds (trained or not yet evaluated): tells a run from other folders
RUN_MARKERS = (*LOG_FILES, FINAL_DIR, RUN_FILE, CONFIG_FILE, "config.json", CHECKPOINT_DIR)
#: run.json's format: the key set trajflow reads (RUN_FIELDS) and writes; files written before it was recorded
#: are version 1 too
RUN_FORMAT_VERSION = 1

#: The run.json keys trajflow reads and the JSON type each value must have (when present and not null).
RUN_FIELDS: dict[str, type] = {
    "model": str, "dataset": str, "fold": str, "seed": int, "status": str, "data_dir": str, "fingerprint": dict,
    "best": dict, "started": str, "finished": str, "code_revisions": list, "machines": list,
    "rank_weight_digests": list, "autoencoder_from": dict, "format_version": int,
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


def write_run_info(run_dir: str | Path, info: dict[str, Any]) -> None:
    """Write run.json (atomically), stamped with :data:`RUN_FORMAT_VERSION`."""
    atomic_write_text(Path(run_dir) / RUN_FILE,
                      json.dumps({"format_version": RUN_FORMAT_VERSION, **info}, indent=2, default=str) + "\n")


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


def write_compiled_kernels(run_dir: str | Path, kernels: bytes) -> None:
    """Keep the kernels of the run's compiled steps (:func:`~.model.compiled.compiled_kernels`, atomically), stamped
    with the torch version that made them and their digest."""
    stamp = json.dumps({"torch": torch.__version__, "sha256": hashlib.sha256(kernels).hexdigest()})
    atomic_write_bytes(Path(run_dir) / COMPILED_KERNELS_FILE, _KERNELS_HEADER + stamp.encode() + b"\n" + kernels)


def read_compiled_kernels(run_dir: str | Path) -> tuple[bytes | None, str | None]:
    """The run's kept kernels (None when it has none) and, when the file is there but cannot be used, why not in
    one line: it is a cache, so a damaged or foreign file never stops a run (it compiles from scratch and the file
    is replaced), and torch's own loader, which logs a traceback on damaged bytes, only ever sees checked ones."""
    path = Path(run_dir) / COMPILED_KERNELS_FILE
    if not path.is_file():
        return None, None
    try:
        blob = path.read_bytes()
    except OSError as error:
        return None, f"{path}: unreadable ({error.strerror or error}); compiling from scratch"
    stamp_line, _, kernels = blob[len(_KERNELS_HEADER):].partition(b"\n")
    try:
        stamp = json.loads(stamp_line) if blob.startswith(_KERNELS_HEADER) else None
    except ValueError:
        stamp = None
    if not isinstance(stamp, dict) or stamp.get("sha256") != hashlib.sha256(kernels).hexdigest():
        return None, f"{path}: damaged (not the kernels trajflow wrote); compiling from scratch"
    if stamp.get("torch") != torch.__version__:
        return None, f"{path}: compiled by torch {stamp.get('torch')}, this is {torch.__version__}; compiling anew"
    return kernels, None


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


def is_trained(run_dir: str | Path) -> bool:
    """Whether the run has a final model that is current (run.json says finished; older runs without run.json
    count by their final model alone)."""
    run_dir = Path(run_dir)
    if not (run_dir / FINAL_DIR / MODEL_FILE).is_file():
        return False
    info = read_run_info(run_dir)
    return info is None or info.get("status") == "finished"


def is_evaluated(run_dir: str | Path) -> bool:
    """Trained, and evaluated on its current final model (a run whose budget was raised is neither until its new
    model is trained and evaluated)."""
    run_dir = Path(run_dir)
    if not (run_dir / EVAL_DIR / METRICS_FILE).exists():
        return False
    info = read_run_info(run_dir)
    try:
        evaluation = json.loads(input_files.read_text(run_dir / EVAL_DIR / EVAL_FILE))
    except (TrajflowError, OSError, ValueError):
        return False
    if info is None or info.get("status") != "finished" or not isinstance(evaluation, dict):
        return False
    evaluated, current = evaluation.get("model_digest"), weights_digest(info)
    if evaluated is not None and current is not None:
        return evaluated == current
    # Evaluations from before digests were recorded: current unless made before the model was finished.
    try:
        return dt.datetime.fromisoformat(evaluation["date"]) >= dt.datetime.fromisoformat(info["finished"])
    except (KeyError, TypeError, ValueError):
        return True


#: what describes a run: run.json, the config it trains and resumes with, its training log (either format)
DESCRIPTION_FILES = (RUN_FILE, CONFIG_FILE, *LOG_FILES)
#: the trained model: its weights and their metadata for people
FINAL_FILES = (f"{FINAL_DIR}/{MODEL_FILE}", f"{FINAL_DIR}/{MODEL_INFO_FILE}")
#: what an evaluation leaves besides its draws: what produced the numbers, and the numbers
EVALUATION_RECORD = (f"{EVAL_DIR}/{EVAL_FILE}", f"{EVAL_DIR}/{METRICS_FILE}")


def continuation_files(run_dir: str | Path) -> tuple[str, ...]:
    """The files of the run (paths relative to it, those present) that a copy needs to go on from where the run
    stands without repeating finished work, leaving out what is large or can be remade (the draws, the best and
    stage-end weights, saved ROME fits): an evaluated run's description, final model and evaluation record; a
    trained one's description and final model (the copy is evaluated, not trained again); a run in training its
    description and last training state (the copy resumes after that epoch). () when the run has nothing to go on
    from (no checkpoint yet: it would start again anyway)."""
    run_dir = Path(run_dir)
    if is_evaluated(run_dir):
        wanted = (*DESCRIPTION_FILES, *FINAL_FILES, *EVALUATION_RECORD)
    elif is_trained(run_dir):
        wanted = (*DESCRIPTION_FILES, *FINAL_FILES)
    elif (run_dir / STATE_FILE).is_file() and (run_dir / CONFIG_FILE).is_file():
        wanted = (*DESCRIPTION_FILES, STATE_FILE)
    else:
        return ()
    return tuple(name for name in wanted if (run_dir / name).is_file())


def final_model_identity(run_dir: str | Path) -> tuple[Any, Any] | None:
    """What identifies the run's final model: when it was finished and its weights' digest (run.json)."""
    info = read_run_info(run_dir)
    return None if info is None else (info.get("finished"), weights_digest(info))


def looks_like_run(path: str | Path) -> bool:
    """A directory that holds training outputs (but possibly no evaluation yet)."""
    path = Path(path)
    return any((path / marker).exists() for marker in RUN_MARKERS) or (path / EVAL_DIR).exists()
