"""An experiment config file (TOML): what `trajflow experiment` runs, parsed and checked, every problem one
UsageError naming the file and key::

    name = "synthetic_bimodal_quick"
    [data]
    path = "data/synthetic_bimodal"      # dataset directory (relative paths: to the current directory)
    ingest = "synthetic-bimodal"         # optional: how to create it when missing (synthetic-bimodal, eth-ucy)
    raw = "../shared/data/eth_ucy"       # raw input of that ingest, when it needs one
    samples = 3000                       # options of that ingest (synthetic-bimodal: samples, seed)
    [protocol]
    models = ["trajflow", "trajflow-no-ae", "flomo", "cv"]
    folds = "all"                        # "all", a list of folds, or omitted for datasets without folds
    seeds = [0, 1, 2]
    [train]
    set = ["train.flow_max_epochs=20"]   # `--set` overrides for every model
    [models.trajflow]
    set = ["train.ae_max_epochs=30"]     # extra overrides for one model
    [eval]
    samples = 100
    k = 20
    extended_horizon = true              # also *_ext metrics over each sample's n_future_max (rounD)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import UsageError
from ..ingest.registry import NAMES, get_ingest
from ..model.config import MODEL_NAMES, load_config
from .evaluate import EvalOptions
from ..util import input_files
from ..util.bounds import check_seed

#: the registered ingests (ingest/registry.py) an experiment config may name: their options are plain TOML values
INGESTS = ("synthetic-bimodal", "eth-ucy")
_TOP_KEYS = {"name", "description", "data", "protocol", "train", "models", "eval"}


@dataclass(frozen=True)
class ExperimentConfig:
    """A parsed experiment config: which data, which runs, which overrides, how to evaluate."""

    name: str
    data_path: Path
    ingest: str | None = None
    ingest_options: dict[str, Any] = field(default_factory=dict)
    models: tuple[str, ...] = ("trajflow",)
    folds: tuple[str, ...] | str | None = None
    seeds: tuple[int, ...] = (0,)
    train_overrides: tuple[str, ...] = ()
    model_overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)
    eval_options: EvalOptions = EvalOptions()
    source: dict[str, Any] = field(default_factory=dict)


def option_value(default: Any, value: Any, key: str) -> Any:
    """A [data] option as its ingest takes it: of its default's type (samples = 3000.0 -> 3000); a value that is
    not one is a UsageError naming the key."""
    if not isinstance(default, (int, float, str)) or isinstance(default, bool):
        return value
    try:
        if isinstance(value, (list, dict, bool)) or (isinstance(default, int) and float(value) != int(value)):
            raise ValueError(value)
        return type(default)(value)
    except (TypeError, ValueError):
        raise UsageError(f"experiment config: [data] {key} must be {type(default).__name__}, got {value!r}") \
            from None


def _ingest_options(name: str | None) -> tuple[str, ...]:
    """The [data] keys of ingest `name` besides path and ingest: raw (when it reads raw input) and its options."""
    if name is None:
        return ()
    adapter = get_ingest(name)
    return (*(("raw",) if adapter.raw is not None else ()), *adapter.options)


def _table(section: dict[str, Any], key: str, path: Path, name: str | None = None) -> dict[str, Any]:
    """A sub-table of the config (empty when absent); anything but a table is an error naming it."""
    value = section.get(key, {})
    if not isinstance(value, dict):
        raise UsageError(f"{path}: [{name or key}] must be a table, not {type(value).__name__}")
    return value


def _list(value: Any, key: str, path: Path) -> list[Any]:
    """A list value; a single scalar counts as a one-element list (folds = "hotel")."""
    if isinstance(value, (str, int, float)):
        return [value]
    if not isinstance(value, list):
        raise UsageError(f"{path}: {key} must be a list, not {type(value).__name__}")
    return value


def _strings(value: Any, key: str, path: Path) -> list[str]:
    return [str(v) for v in _list(value, key, path)]


def _unknown(section: dict[str, Any], allowed: set[str], where: str, path: Path) -> None:
    extra = sorted(set(section) - allowed)
    if extra:
        raise UsageError(f"{path}: unknown key(s) {', '.join(extra)} in {where}; allowed: {', '.join(sorted(allowed))}")


def load_experiment(path: str | Path) -> ExperimentConfig:
    """Read and check an experiment config file (unknown keys are errors that name them)."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: experiment config not found")
    try:
        raw = tomllib.loads(input_files.read_text(path))
    except tomllib.TOMLDecodeError as error:
        raise UsageError(f"{path}: not valid TOML ({error})") from None
    _unknown(raw, _TOP_KEYS, "the top level", path)
    data, protocol = _table(raw, "data", path), _table(raw, "protocol", path)
    _unknown(protocol, {"models", "folds", "seeds"}, "[protocol]", path)
    _unknown(_table(raw, "train", path), {"set"}, "[train]", path)
    eval_section = _table(raw, "eval", path)
    _unknown(eval_section, {"samples", "k", "workers", "batch_size", "metrics", "seed", "max_pooled", "steps",
                            "extended_horizon", "rome_kde"}, "[eval]", path)
    if "path" not in data:
        raise UsageError(f"{path}: [data] needs a path")
    ingest = data.get("ingest")
    if ingest is not None and ingest not in INGESTS:
        raise UsageError(f"{path}: [data] ingest must be one of {', '.join(INGESTS)}, got {ingest!r} (registered "
                         f"ingests: {', '.join(NAMES)}; make the others with `trajflow ingest NAME`)")
    _unknown(data, {"path", "ingest", *_ingest_options(ingest)}, "[data]", path)
    if "seed" in data:
        check_seed(data["seed"], f"{path}: data.seed")
    models_section = _table(raw, "models", path)
    for name in models_section:
        _unknown(_table(models_section, name, path, f"models.{name}"), {"set"}, f"[models.{name}]", path)
    try:
        folds = protocol.get("folds")
        options = EvalOptions(**{k: tuple(_strings(v, f"eval.{k}", path)) if k == "metrics" else v
                                 for k, v in eval_section.items()})
        options.validate()
        config = ExperimentConfig(
            name=str(raw.get("name", path.stem)),
            data_path=Path(str(data["path"])),
            ingest=ingest,
            ingest_options={k: v for k, v in data.items() if k not in ("path", "ingest")},
            models=tuple(_strings(protocol.get("models", ["trajflow"]), "protocol.models", path)),
            folds=folds if folds is None or folds == "all" else tuple(_strings(folds, "protocol.folds", path)),
            seeds=tuple(check_seed(s, f"{path}: protocol.seeds") for s in _list(protocol.get("seeds", [0]),
                                                                                "protocol.seeds", path)),
            train_overrides=tuple(_strings(raw.get("train", {}).get("set", []), "train.set", path)),
            model_overrides={name: tuple(_strings(section.get("set", []), f"models.{name}.set", path))
                             for name, section in models_section.items()},
            eval_options=options,
            source=raw,
        )
    except (TypeError, ValueError) as error:
        raise UsageError(f"{path}: a value has the wrong type ({error})") from None
    _check_models(config, path)
    return config


def _check_models(config: ExperimentConfig, path: Path) -> None:
    """Models must exist and every override must name a real config key, before hours of training start."""
    unknown = [m for m in (*config.models, *config.model_overrides) if m not in MODEL_NAMES]
    if unknown:
        raise UsageError(f"{path}: unknown model(s) {', '.join(unknown)}; choose from {', '.join(MODEL_NAMES)}")
    for model in config.models:
        try:
            load_config(overrides=[*config.train_overrides, *config.model_overrides.get(model, ()),
                                   f"model.name={model}"])
        except UsageError as error:
            raise UsageError(f"{path}: {error}") from None
