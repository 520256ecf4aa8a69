"""Typed configuration of a model and of its training, with the TrajFlow paper's values as defaults.

A run is described by a :class:`RunConfig` with two sections, ``[model]`` (:class:`ModelConfig`: architecture and
the model family) and ``[train]`` (:class:`TrainConfig`: optimisers, early stopping, seed, device). Both load from
TOML (``tomllib``) and from ``--set section.key=value`` overrides; an unknown key is a :class:`UsageError` that names
it, so a typo never silently falls back to a default. Facts that come from the data (past / future length, whether
the dataset has maps) are not configuration: they live in :class:`DataSpec`, which a checkpoint stores beside the
config so that a model can be rebuilt without the dataset.
"""

from __future__ import annotations

import json
import tomllib
import typing
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from ..errors import UsageError

#: Model families selectable with ``--model``; see :mod:`trajflow_pipeline.model.models`.
MODEL_NAMES: tuple[str, ...] = ("trajflow", "trajflow-no-ae", "flomo", "cv")


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of one model family. Defaults are the paper's / the reference implementation's values.

    The FloMo values (``flomo_*``) are those the FloMo reference code uses for pedestrian data (ETH/UCY):
    noise std beta = 0.2 on near-zero scaled displacements (|y| < 0.01), gamma = 0.02 on all others, and a
    training-time scaling augmentation s ~ N(1, 0.5) truncated to [0.3, 1.7] (its vehicle settings are
    beta = gamma = 0.002, s ~ N(1, 0.2) truncated to [0.8, 1.2]; set them with ``--set`` for rounD / nuScenes).
    """

    name: str = "trajflow"
    #: Future displacements are multiplied by alpha before the flow / autoencoder sees them.
    alpha: float = 10.0
    # RNN autoencoder (trajflow only): Linear(2->embed)+ReLU -> GRU(embed, hidden, layers) -> Linear(hidden->latent).
    ae_embed: int = 20
    ae_hidden: int = 20
    ae_layers: int = 3
    latent_dim: int = 20
    # Conditional coupling flow with rational-quadratic splines.
    flow_layers: int = 10
    flow_bins: int = 8
    flow_tail_bound: float = 15.0
    flow_hidden: tuple[int, ...] = (32, 32, 32, 32, 32)
    #: Not in the paper: standardize the flow's input per feature (training mean / std, fitted in a closed-form
    #: stage "standardize" before the flow trains), so that flow_tail_bound is in standard deviations and the
    #: splines' bins cover the data whatever its units (see ConditionalSplineFlow).
    flow_standardize: bool = False
    # Past encoder of the target: Linear(2->embed)+ReLU -> GRU(embed, hidden, layers) -> Linear(hidden->out).
    past_embed: int = 16
    past_hidden: int = 16
    past_layers: int = 3
    past_out: int = 64
    # Social GNN over all agents present at t0.
    use_social: bool = True
    gnn_layers: int = 4
    gnn_width: int = 32
    #: How a node combines its incoming messages: "sum" (the paper) or "mean" (not in the paper: the context of a
    #: crowd then stays in the range of the smaller groups a model was trained on; see SocialGNN).
    gnn_aggregate: str = "sum"
    # CNN over a heading-aligned grey-scale map crop; only built when the dataset has maps.
    use_map: bool = True
    map_height: int = 156
    map_width: int = 257
    map_out: int = 64
    # FloMo training-time noise injection and scaling augmentation (model "flomo" only).
    flomo_beta: float = 0.2
    flomo_gamma: float = 0.02
    flomo_zero_threshold: float = 0.01
    flomo_scale_std: float = 0.5
    flomo_scale_min: float = 0.3
    flomo_scale_max: float = 1.7

    def validate(self) -> None:
        """Reject combinations the architecture cannot build, with a message naming the key."""
        if self.name not in MODEL_NAMES:
            raise UsageError(f"unknown model {self.name!r}; choose one of {', '.join(MODEL_NAMES)}")
        if self.alpha <= 0:
            raise UsageError("model.alpha must be positive")
        if self.latent_dim != self.ae_hidden:
            raise UsageError("model.latent_dim must equal model.ae_hidden: the decoder's hidden state is the latent "
                             "tiled over the GRU layers")
        if self.latent_dim < 2:
            raise UsageError("model.latent_dim must be at least 2 (a coupling layer splits the features in two)")
        for key in ("ae_embed", "ae_layers", "flow_layers", "flow_bins", "past_embed", "past_hidden",
                    "past_layers", "past_out", "gnn_layers", "gnn_width", "map_out"):
            if getattr(self, key) < 1:
                raise UsageError(f"model.{key} must be at least 1")
        if self.gnn_aggregate not in GNN_AGGREGATES:
            raise UsageError(f"model.gnn_aggregate must be one of {', '.join(GNN_AGGREGATES)}, not "
                             f"{self.gnn_aggregate!r}")
        if self.flow_bins < 2:
            raise UsageError("model.flow_bins must be at least 2")
        if self.map_height < 41 or self.map_width < 41:
            raise UsageError("model.map_height and model.map_width must be at least 41 pixels (3 stride-4 convs)")
        if self.flow_tail_bound <= 0:
            raise UsageError("model.flow_tail_bound must be positive")
        if not self.flow_hidden or any(h < 1 for h in self.flow_hidden):
            raise UsageError("model.flow_hidden must be a non-empty list of positive widths")
        if not 0 < self.flomo_scale_min <= 1 <= self.flomo_scale_max:
            raise UsageError("model.flomo_scale_min <= 1 <= model.flomo_scale_max is required")
        if self.flomo_beta < 0 or self.flomo_gamma < 0 or self.flomo_scale_std < 0:
            raise UsageError("model.flomo_beta, flomo_gamma and flomo_scale_std must be non-negative")


#: How the social GNN combines a node's incoming messages (ModelConfig.gnn_aggregate).
GNN_AGGREGATES = ("sum", "mean")

#: How a run picks the flow weights it keeps (TrainConfig.flow_select).
FLOW_SELECTIONS = ("val_loss", "val_nll")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation of the two training stages (AE: autoencoder; flow: flow + context encoders).

    Early stopping follows the reference implementation: after ``*_min_epochs`` epochs, a stage stops once
    ``*_patience`` epochs passed without a better validation loss (0 disables early stopping), and the best
    validation weights are kept. ``*_batch_size`` is per process under torchrun.
    """

    seed: int = 0
    #: "auto" (CUDA when available, else CPU), "cpu", "cuda" or "cuda:N".
    device: str = "auto"
    ae_lr: float = 5e-4
    ae_weight_decay: float = 1e-4
    ae_batch_size: int = 128
    ae_max_epochs: int = 5000
    ae_min_epochs: int = 100
    ae_patience: int = 10
    flow_lr: float = 1e-3
    flow_weight_decay: float = 1e-5
    flow_batch_size: int = 128
    flow_lr_decay: float = 0.98
    flow_max_epochs: int = 500
    flow_min_epochs: int = 50
    flow_patience: int = 10
    #: Which flow weights a run keeps. "val_loss" (the reference): those of the epoch with the lowest validation
    #: loss, the flow's NLL in its own space. "val_nll" (ours): those with the lowest evaluation NLL -- ROME
    #: densities of model draws, in metres, pooled over identical inputs, as `trajflow eval` computes it -- on a
    #: fixed subset of `flow_select_problems` validation problems with `flow_select_samples` draws each (at most
    #: `flow_select_max_pooled` per pooled group), checked every `flow_select_every` epochs and at the last one.
    #: Early stopping follows the validation loss either way, so both keep weights of the same training.
    flow_select: str = "val_loss"
    flow_select_every: int = 5
    flow_select_problems: int = 256
    flow_select_samples: int = 100
    flow_select_max_pooled: int = 1000
    #: Fraction of the training problems held out for validation when the dataset has no validation split.
    val_fraction: float = 0.1
    #: Clip the global gradient norm to this value; 0 disables clipping.
    grad_clip: float = 0.0
    #: Batch size used for validation passes (no gradients, so it can be larger).
    eval_batch_size: int = 256

    def validate(self) -> None:
        """Reject values no optimiser can use, with a message naming the key."""
        for key in ("ae_batch_size", "flow_batch_size", "eval_batch_size"):
            if getattr(self, key) < 1:
                raise UsageError(f"train.{key} must be at least 1")
        for key in ("ae_max_epochs", "flow_max_epochs", "ae_min_epochs", "flow_min_epochs", "ae_patience",
                    "flow_patience"):
            if getattr(self, key) < 0:
                raise UsageError(f"train.{key} must be non-negative")
        for key in ("ae_lr", "flow_lr"):
            if getattr(self, key) <= 0:
                raise UsageError(f"train.{key} must be positive")
        if not 0 < self.flow_lr_decay <= 1:
            raise UsageError("train.flow_lr_decay must be in (0, 1]")
        if self.flow_select not in FLOW_SELECTIONS:
            raise UsageError(f"train.flow_select must be one of {', '.join(FLOW_SELECTIONS)}, not {self.flow_select!r}")
        for key in ("flow_select_every", "flow_select_problems"):
            if getattr(self, key) < 1:
                raise UsageError(f"train.{key} must be at least 1")
        for key in ("flow_select_samples", "flow_select_max_pooled"):
            if getattr(self, key) < 2:
                raise UsageError(f"train.{key} must be at least 2 (a density needs two draws)")
        if not 0 < self.val_fraction < 1:
            raise UsageError("train.val_fraction must be in (0, 1)")
        if self.grad_clip < 0:
            raise UsageError("train.grad_clip must be non-negative (0 disables clipping)")
        if self.device != "auto" and self.device != "cpu" and not self.device.startswith("cuda"):
            raise UsageError(f"train.device must be auto, cpu, cuda or cuda:N, not {self.device!r}")


@dataclass(frozen=True)
class RunConfig:
    """The complete resolved configuration of a training run: ``[model]`` and ``[train]``."""

    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def validate(self) -> "RunConfig":
        """Validate both sections and return self, so that construction and checking chain."""
        self.model.validate()
        self.train.validate()
        return self

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (tuples become lists) for JSON / TOML."""
        return {"model": _plain(asdict(self.model)), "train": _plain(asdict(self.train))}

    def to_json(self) -> str:
        """Deterministic JSON (sorted keys)."""
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def to_toml(self) -> str:
        """TOML text that :func:`load_config` reads back to an equal config."""
        return to_toml(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "config") -> "RunConfig":
        """Build from a nested dict; unknown sections or keys raise :class:`UsageError` naming them."""
        unknown = sorted(set(data) - {"model", "train"})
        if unknown:
            raise UsageError(f"{source}: unknown config section {unknown[0]!r} (known: model, train)")
        model = _section(ModelConfig, data.get("model", {}), "model", source)
        train = _section(TrainConfig, data.get("train", {}), "train", source)
        return cls(model=model, train=train)


@dataclass(frozen=True)
class DataSpec:
    """What the model must know about the data it is built for; stored in every checkpoint."""

    n_past: int
    n_future: int
    has_map: bool = False
    dataset: str = ""
    dt: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DataSpec":
        return cls(**{f.name: data[f.name] for f in fields(cls) if f.name in data})


def load_config(path: str | Path | None = None, overrides: typing.Sequence[str] = (),
                base: RunConfig | None = None) -> RunConfig:
    """Resolve a run config: defaults (or `base`), then the TOML file at `path`, then ``key=value`` overrides.

    Override keys are ``section.key`` (``train.flow_lr=3e-4``) or a bare key that exists in exactly one section
    (``flow_lr=3e-4``); values are parsed as TOML values, falling back to a plain string.
    """
    config = base if base is not None else RunConfig()
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UsageError(f"{path}: config file not found") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise UsageError(f"{path}: not valid TOML ({exc})") from None
        merged = config.to_dict()
        unknown = sorted(set(data) - set(merged))
        if unknown:
            raise UsageError(f"{path}: unknown config section {unknown[0]!r} (known: model, train)")
        for section, values in data.items():
            if not isinstance(values, dict):
                raise UsageError(f"{path}: {section!r} must be a table ([{section}])")
            merged[section].update(values)
        config = RunConfig.from_dict(merged, source=str(path))
    return apply_overrides(config, overrides).validate()


def apply_overrides(config: RunConfig, overrides: typing.Sequence[str]) -> RunConfig:
    """Apply ``key=value`` strings to `config` (see :func:`load_config`)."""
    merged = config.to_dict()
    for item in overrides:
        if "=" not in item:
            raise UsageError(f"--set expects key=value, got {item!r}")
        key, raw = (part.strip() for part in item.split("=", 1))
        section, name = _resolve_key(key)
        merged[section][name] = _parse_value(raw)
    return RunConfig.from_dict(merged, source="--set")


def to_toml(data: dict[str, dict[str, Any]]) -> str:
    """Serialise a two-level dict of scalars and lists of scalars as TOML."""
    lines: list[str] = []
    for section, values in data.items():
        if lines:
            lines.append("")
        lines.append(f"[{section}]")
        lines.extend(f"{key} = {_toml_value(value)}" for key, value in values.items())
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _plain(values: dict[str, Any]) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


def _resolve_key(key: str) -> tuple[str, str]:
    known = {"model": {f.name for f in fields(ModelConfig)}, "train": {f.name for f in fields(TrainConfig)}}
    if "." in key:
        section, name = key.split(".", 1)
        if section not in known:
            raise UsageError(f"unknown config section {section!r} in {key!r} (known: model, train)")
        if name not in known[section]:
            raise UsageError(f"unknown config key {key!r}")
        return section, name
    owners = [section for section, names in known.items() if key in names]
    if len(owners) != 1:
        raise UsageError(f"unknown config key {key!r}" if not owners else
                         f"ambiguous config key {key!r}; write {owners[0]}.{key} or {owners[1]}.{key}")
    return owners[0], key


def _parse_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw


def _section(cls: type, values: Any, section: str, source: str) -> Any:
    if not isinstance(values, dict):
        raise UsageError(f"{source}: [{section}] must be a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise UsageError(f"{source}: unknown config key '{section}.{unknown[0]}'")
    kwargs = {key: _coerce(value, hints[key], f"{section}.{key}", source) for key, value in values.items()}
    return replace(cls(), **kwargs)


def _coerce(value: Any, hint: Any, key: str, source: str) -> Any:
    """Check `value` against the field type `hint`; ints widen to float, lists become tuples."""
    origin = typing.get_origin(hint)
    bad = UsageError(f"{source}: config key '{key}' expects {_type_name(hint)}, got {value!r}")
    if hint is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise bad
        return value
    if origin is tuple:
        item = typing.get_args(hint)[0]
        if not isinstance(value, (list, tuple)):
            raise bad
        return tuple(_coerce(v, item, key, source) for v in value)
    raise TypeError(f"unsupported config field type {hint}")


def _type_name(hint: Any) -> str:
    if typing.get_origin(hint) is tuple:
        return f"a list of {typing.get_args(hint)[0].__name__}"
    return {bool: "true/false", int: "an integer", float: "a number", str: "a string"}.get(hint, str(hint))
