"""An experiment config file (TOML): what `trajflow experiment` runs, parsed and checked, every problem one
UsageError naming the file and key::

    name = "synthetic_bimodal_quick"
    [data]
    path = "data/synthetic_bimodal"      # dataset directory (relative paths: to the current directory)
    ingest = "synthetic-bimodal"         # optional: how to build it (any `trajflow ingest` name); without it
                                         # the dataset at path is used as it is
    raw = "../shared/data/eth_ucy"       # raw input of that ingest, when it reads one
    samples = 3000                       # options of that ingest, as its function names them
    [[augment]]                          # zero or more augmentations, each of the dataset before it
    kind = "scale-rotate"                # forking or scale-rotate (`trajflow augment KIND`)
    copies = 10                          # options of that augmentation
    path = "data/synthetic_scaled"       # optional; default: the source path + _<kind>
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

Runs train on the last data stage's dataset. How the data stages are built, and when again:
:mod:`trajflow_pipeline.stages.data_stages`. ``--set KEY=VALUE`` overrides (``data.raw=PATH``,
``augment.0.copies=50``: dotted keys into the file's tables, list items by index from 0, values in TOML syntax or
else taken as strings) apply on top of the file; an experiment directory keeps the file and its overrides
(:func:`save_experiment_config`).
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import TrajflowError, UsageError
from ..ingest.registry import NAMES, get_ingest
from ..model.config import MODEL_NAMES, load_config
from .augment import AUGMENTATIONS
from .evaluate import EvalOptions
from ..util import input_files
from ..util.atomic import atomic_write_text
from ..util.bounds import check_seed
from ..util.options import keyword_options, option_value, parse_value

#: the ingests an experiment config may name: every registered one (ingest/registry.py)
INGESTS = NAMES
_TOP_KEYS = {"name", "description", "data", "augment", "protocol", "train", "models", "eval"}
#: in an experiment directory: the config file as given, and the --set overrides it ran with
SAVED_CONFIG, SAVED_OVERRIDES = "config.toml", "config_set.json"


@dataclass(frozen=True)
class AugmentStep:
    """One ``[[augment]]`` step: which augmentation, its options as the config gives them, and its output."""

    kind: str
    options: dict[str, Any]
    path: Path


@dataclass(frozen=True)
class ExperimentConfig:
    """A parsed experiment config: which data, which runs, which overrides, how to evaluate."""

    name: str
    #: the dataset the runs train on: the last data stage's (the [data] path without augmentations)
    data_path: Path
    ingest: str | None = None
    #: the [data] options of the ingest as the config gives them, raw among them
    ingest_options: dict[str, Any] = field(default_factory=dict)
    augment: tuple[AugmentStep, ...] = ()
    models: tuple[str, ...] = ("trajflow",)
    folds: tuple[str, ...] | str | None = None
    seeds: tuple[int, ...] = (0,)
    train_overrides: tuple[str, ...] = ()
    model_overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)
    eval_options: EvalOptions = EvalOptions()
    #: the config's tables (with the --set overrides applied)
    source: dict[str, Any] = field(default_factory=dict)
    #: the config file it was read from
    file: Path = Path()

    @property
    def source_path(self) -> Path:
        """The [data] path: the ingest's output, or the dataset used as it is."""
        return Path(str(self.source["data"]["path"]))


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


def load_experiment(path: str | Path, overrides: Sequence[str] = (), *, check_inputs: bool = False
                    ) -> ExperimentConfig:
    """Read and check an experiment config file with `overrides` (``KEY=VALUE``) applied; unknown keys are errors
    that name them. With `check_inputs`, also what the data stages read must exist (the raw input, files named by
    options): the experiment command checks it before any work; status and tests read configs without the data."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: experiment config not found")
    try:
        raw = tomllib.loads(input_files.read_text(path))
    except tomllib.TOMLDecodeError as error:
        raise UsageError(f"{path}: not valid TOML ({error})") from None
    raw = apply_overrides(raw, overrides, path)
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
    _check_ingest(data, path, check_inputs)
    augment = _augment_steps(raw.get("augment", []), Path(str(data["path"])), ingest, path)
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
            data_path=augment[-1].path if augment else Path(str(data["path"])),
            ingest=ingest,
            ingest_options={k: v for k, v in data.items() if k not in ("path", "ingest")},
            augment=augment,
            models=tuple(_strings(protocol.get("models", ["trajflow"]), "protocol.models", path)),
            folds=folds if folds is None or folds == "all" else tuple(_strings(folds, "protocol.folds", path)),
            seeds=tuple(check_seed(s, f"{path}: protocol.seeds") for s in _list(protocol.get("seeds", [0]),
                                                                                "protocol.seeds", path)),
            train_overrides=tuple(_strings(raw.get("train", {}).get("set", []), "train.set", path)),
            model_overrides={name: tuple(_strings(section.get("set", []), f"models.{name}.set", path))
                             for name, section in models_section.items()},
            eval_options=options,
            source=raw,
            file=path,
        )
    except (TypeError, ValueError) as error:
        raise UsageError(f"{path}: a value has the wrong type ({error})") from None
    _check_models(config, path)
    return config


def _check_ingest(data: dict[str, Any], path: Path, check_inputs: bool) -> None:
    """[data]'s ingest, raw input and options: a registered ingest, a raw input where it reads one (that exists,
    with `check_inputs`), options it takes, of the types it takes (file options read only with `check_inputs`)."""
    ingest = data.get("ingest")
    if ingest is None:
        _unknown(data, {"path", "ingest"}, "[data] (without an ingest, the dataset at path is used as it is)", path)
        return
    if ingest not in NAMES:
        raise UsageError(f"{path}: [data] ingest must be one of {', '.join(NAMES)}, got {ingest!r}")
    adapter = get_ingest(ingest)
    options = {k: v for k, v in data.items() if k not in ("path", "ingest", "raw")}
    if adapter.raw is None and "raw" in data:
        raise UsageError(f"{path}: [data] raw: ingest {ingest} generates its data and reads no raw input")
    if adapter.raw is not None:
        if "raw" not in data:
            raise UsageError(f"{path}: [data] ingest = {ingest!r} needs raw = {adapter.raw} (in the file, or "
                             "--set data.raw=PATH)")
        if not isinstance(data["raw"], str):
            raise UsageError(f"{path}: [data] raw must be a path (a string), got {data['raw']!r}")
        if check_inputs and not Path(data["raw"]).exists():
            raise UsageError(f"{path}: [data] raw: {data['raw']} does not exist (from {Path.cwd()}; point at the "
                             "raw data with --set data.raw=PATH)")
    if check_inputs:
        adapter.config_options(options, str(path))
    else:
        adapter.config_options({k: v for k, v in options.items() if k not in adapter.converters}, str(path))
    if "seed" in data:
        check_seed(data["seed"], f"{path}: data.seed")


def _augment_steps(value: Any, source: Path, ingest: str | None, path: Path) -> tuple[AugmentStep, ...]:
    """The ``[[augment]]`` steps: known kinds with options their function takes, each applicable to the data
    before it as far as the config tells (`forking` needs multi-future data: refused after an ingest that never
    makes it), and each written to its own path (default: the dataset before it + ``_<kind>``)."""
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(step, dict) for step in value):
        raise UsageError(f"{path}: augment must be [[augment]] tables, not {type(value).__name__}")
    steps, before, multi_future = [], source, get_ingest(ingest).multi_future if ingest else None
    for index, step in enumerate(value):
        where = f"[[augment]] {index} (augment.{index})"
        kind = step.get("kind")
        if kind not in AUGMENTATIONS:
            raise UsageError(f"{path}: {where} kind must be one of {', '.join(AUGMENTATIONS)}, got {kind!r}")
        spec, function = AUGMENTATIONS[kind]
        options = {k: v for k, v in step.items() if k not in ("kind", "path")}
        _unknown(step, {"kind", "path", *keyword_options(function)}, f"{where} (kind {kind})", path)
        for key, option in options.items():
            try:
                option_value(function, key, option)
            except UsageError as error:
                raise UsageError(f"{path}: {where} {key} {error}") from None
        if "seed" in options:
            check_seed(options["seed"], f"{path}: augment.{index}.seed")
        if spec.needs_groups and multi_future is False:
            raise UsageError(f"{path}: {where} kind = {kind!r} needs multi-future data (groups of several futures of "
                             f"one input), which ingest {ingest} does not make; use scale-rotate")
        out = Path(str(step["path"])) if "path" in step else before.with_name(f"{before.name}_{spec.dataset_suffix}")
        if out in (source, *(s.path for s in steps)):
            raise UsageError(f"{path}: {where} path {out} is already the output of an earlier data stage")
        steps.append(AugmentStep(kind, options, out))
        before = out
    return tuple(steps)


def apply_overrides(raw: dict[str, Any], overrides: Sequence[str], path: Path) -> dict[str, Any]:
    """The config's tables with each ``KEY=VALUE`` of `overrides` set (a copy): KEY a dotted path into the tables
    (``data.raw``, ``augment.0.copies``: list items by index), VALUE in TOML syntax (``50``, ``[1, 2]``,
    ``"x"``) or else a string."""
    result = copy.deepcopy(raw)
    for item in overrides:
        key, sep, text = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise UsageError(f"--set {item!r}: expected KEY=VALUE with a dotted KEY, e.g. data.raw=PATH")
        value = parse_value(text)
        target: Any = result
        for depth, part in enumerate(parts[:-1]):
            target = _item(target, part, item, ".".join(parts[:depth]))
        _item(target, parts[-1], item, ".".join(parts[:-1]), leaf=True)  # a list item that exists, or a table
        if isinstance(target, list):
            target[int(parts[-1])] = value
        else:
            target[parts[-1]] = value
    return result


def _item(container: Any, part: str, item: str, where: str, *, leaf: bool = False) -> Any:
    """`container[part]` on the way of the override `item`: a list item by index, a table's value by key (a table
    made where missing, but not for the `leaf`); anything else a UsageError naming `where`, the dotted key so far."""
    if isinstance(container, list):
        if not part.isdigit() or int(part) >= len(container):
            raise UsageError(f"--set {item!r}: {where} has {len(container)} item(s), no {part!r}")
        return container[int(part)]
    if not isinstance(container, dict):
        raise UsageError(f"--set {item!r}: {where} is not a table")
    return container.get(part) if leaf else container.setdefault(part, {})


def save_experiment_config(out: Path, text: str, overrides: Sequence[str]) -> None:
    """Keep the config file's text and the overrides it runs with in the experiment directory `out`."""
    atomic_write_text(out / SAVED_CONFIG, text)
    atomic_write_text(out / SAVED_OVERRIDES, json.dumps({"set": list(overrides)}, indent=2) + "\n")


def saved_overrides(out: Path) -> list[str]:
    """The --set overrides the experiment in `out` last ran with ([] when it ran without, or before they were
    kept)."""
    file = out / SAVED_OVERRIDES
    if not file.exists():
        return []
    try:
        values = json.loads(input_files.read_text(file))["set"]
    except (TrajflowError, OSError, ValueError, KeyError, TypeError):
        raise UsageError(f"{file}: unreadable (it keeps the --set overrides of the experiment)") from None
    return [str(v) for v in values]


def load_saved_experiment(out: Path) -> ExperimentConfig:
    """The config the experiment in `out` last ran with: its saved file and overrides."""
    return load_experiment(out / SAVED_CONFIG, saved_overrides(out))


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
