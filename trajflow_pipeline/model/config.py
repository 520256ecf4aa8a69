"""Typed configuration of a model and of its training, with the TrajFlow paper's values as defaults.

A run is described by a :class:`RunConfig` with two sections, ``[model]`` (:class:`ModelConfig`: architecture and
the model family) and ``[train]`` (:class:`TrainConfig`: optimisers, early stopping, seed, device). Both load from
TOML (``tomllib``) and from ``--set section.key=value`` overrides; an unknown key is a :class:`UsageError` that names
it, so a typo never silently falls back to a default. Each numeric field declares the values it accepts next to it
(:func:`~trajflow_pipeline.util.bounds.bounded`: finite, within its range), checked whenever a config is read, so a
NaN learning rate or a negative weight decay is a UsageError naming the key, the value and the file or option.
Facts that come from the data (past / future length, whether the dataset has maps) are not configuration: they live
in :class:`DataSpec`, which a checkpoint stores beside the config so that a model can be rebuilt without the
dataset.
"""

from __future__ import annotations

import json
import tomllib
import typing
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from ..errors import DataError, UsageError
from ..util import input_files
from ..util.bounds import SEED, bounded, check_value
from ..util.options import parse_value

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
    alpha: float = bounded(10.0, gt=0)
    # RNN autoencoder (trajflow only): Linear(2->embed)+ReLU -> GRU(embed, hidden, layers) -> Linear(hidden->latent).
    ae_embed: int = bounded(20, ge=1)
    ae_hidden: int = bounded(20, ge=1)
    ae_layers: int = bounded(3, ge=1)
    #: at least 2: a coupling layer splits the features in two
    latent_dim: int = bounded(20, ge=2)
    # Conditional coupling flow with rational-quadratic splines.
    flow_layers: int = bounded(10, ge=1)
    flow_bins: int = bounded(8, ge=2)
    flow_tail_bound: float = bounded(15.0, gt=0)
    #: widths of the coupling networks' hidden layers (each bound applies to every width)
    flow_hidden: tuple[int, ...] = bounded((32, 32, 32, 32, 32), ge=1)
    #: Not in the paper: standardize the flow's input per feature (training mean / std, fitted in a closed-form
    #: stage "standardize" before the flow trains), so that flow_tail_bound is in standard deviations and the
    #: splines' bins cover the data whatever its units (see ConditionalSplineFlow).
    flow_standardize: bool = False
    #: Not in the paper: the standard deviation of the flow's base distribution when it draws futures (and scores
    #: them: the draws' log-likelihoods are the density with that base); training fits the flow with 1 whatever
    #: this is. Above 1 the draws spread wider around the same modes (see docs/results/eth_ucy_ours_temperature).
    flow_temperature: float = bounded(1.0, gt=0)
    #: Not in the paper: fit that temperature instead of setting it. The closed-form stage "temperature", after the
    #: flow, draws futures for `flow_temperature_problems` fixed validation problems at each of these values and
    #: keeps the one of the lowest evaluation NLL (ROME densities of the draws pooled over identical inputs, with
    #: train.flow_select_samples draws, at most train.flow_select_max_pooled per pool), saved with the weights.
    #: Empty (the default): no such stage; flow_temperature applies.
    flow_temperature_grid: tuple[float, ...] = bounded((), gt=0)
    flow_temperature_problems: int = bounded(2000, ge=1)
    # Past encoder of the target: Linear(2->embed)+ReLU -> GRU(embed, hidden, layers) -> Linear(hidden->out).
    past_embed: int = bounded(16, ge=1)
    past_hidden: int = bounded(16, ge=1)
    past_layers: int = bounded(3, ge=1)
    past_out: int = bounded(64, ge=1)
    # Social GNN over all agents present at t0.
    use_social: bool = True
    gnn_layers: int = bounded(4, ge=1)
    gnn_width: int = bounded(32, ge=1)
    #: How a node combines its incoming messages: "sum" (the paper) or "mean" (not in the paper: the context of a
    #: crowd then stays in the range of the smaller groups a model was trained on; see SocialGNN).
    gnn_aggregate: str = "sum"
    # CNN over a heading-aligned grey-scale map crop; only built when the dataset has maps.
    use_map: bool = True
    #: at least 41 pixels: the map CNN has three stride-4 convolutions
    map_height: int = bounded(156, ge=41)
    map_width: int = bounded(257, ge=41)
    map_out: int = bounded(64, ge=1)
    #: Not in the paper (trajflow and trajflow-no-ae): FloMo's scaling augmentation for the other flow models.
    #: While training (every gradient stage, the autoencoder's too) each problem's scene is scaled about the
    #: target's position at t0 by s ~ N(1, scale_augment_std) truncated to [scale_augment_min, scale_augment_max],
    #: so that a location whose agents move faster or slower than the training locations' (ETH/UCY fold eth:
    #: test steps about 1.75x the training median) is not outside everything the model saw. 0 = off.
    scale_augment_std: float = bounded(0.0, ge=0)
    scale_augment_min: float = bounded(0.3, gt=0, le=1)
    scale_augment_max: float = bounded(1.7, ge=1)
    #: Not in the paper: each problem's scene is scaled, in its target frame, by speed_reference / s, where s is
    #: the mean step length of every agent's observed past at t0 (target and neighbours; normalize.scene_speed)
    #: and speed_reference a quantile of s over the training problems (speed_normalize_quantile, the median by
    #: default; fitted before the first stage and kept with the weights); the factor is clipped to
    #: [speed_normalize_min, speed_normalize_max] and the draws are scaled back. So a location whose agents walk
    #: faster than the training locations' (ETH/UCY fold eth: a median s of 0.84 m against 0.25 m in training) is
    #: seen at the training locations' pace. Every model; not with map crops (they are not scaled) nor with a
    #: scaling augmentation (it would be undone).
    speed_normalize: bool = False
    speed_normalize_min: float = bounded(0.33, gt=0, le=1)
    speed_normalize_max: float = bounded(3.0, ge=1)
    #: Not in the paper either: the quantile of the training problems' s that is speed_reference (0.5: the
    #: median). With speed_normalize_max = 1 only scenes faster than it are scaled (down to it): at the median
    #: that is half of the training problems and most test problems of ETH/UCY's hotel, zara1 and zara2 (76 %,
    #: 96 % and 64 %, paces 1.4-1.7x the median), not only fold eth's (3.4x); a higher quantile leaves them be.
    speed_normalize_quantile: float = bounded(0.5, gt=0, lt=1)
    #: Not in the paper either, and for drawing futures only (sampling, hence evaluation and the temperature
    #: stage; training, its validation loss and log_likelihood keep the rule above): a scene faster than
    #: speed_reference is scaled only when its pace exceeds speed_normalize_sample_threshold x speed_reference,
    #: and drawn at its own pace below that. 1 (the default): every faster scene is scaled, as in training.
    #: Measured on ETH/UCY (docs/results/eth_ucy_sample_threshold/): the median-trained models predict zara1's and
    #: hotel's moderately fast scenes (1.4-1.7x the median) better unscaled, fold eth's (3.4x) better scaled.
    speed_normalize_sample_threshold: float = bounded(1.0, ge=1)
    # FloMo training-time noise injection and scaling augmentation (model "flomo" only).
    flomo_beta: float = bounded(0.2, ge=0)
    flomo_gamma: float = bounded(0.02, ge=0)
    flomo_zero_threshold: float = bounded(0.01, ge=0)
    flomo_scale_std: float = bounded(0.5, ge=0)
    flomo_scale_min: float = bounded(0.3, gt=0, le=1)
    flomo_scale_max: float = bounded(1.7, ge=1)

    def validate(self) -> None:
        """Reject values and combinations the architecture cannot build, with a message naming the key."""
        check_fields(self, "model")
        if self.name not in MODEL_NAMES:
            raise UsageError(f"unknown model {self.name!r}; choose one of {', '.join(MODEL_NAMES)}")
        if self.latent_dim != self.ae_hidden:
            raise UsageError("model.latent_dim must equal model.ae_hidden: the decoder's hidden state is the latent "
                             "tiled over the GRU layers")
        if self.gnn_aggregate not in GNN_AGGREGATES:
            raise UsageError(f"model.gnn_aggregate must be one of {', '.join(GNN_AGGREGATES)}, not "
                             f"{self.gnn_aggregate!r}")
        if self.flow_temperature_grid and self.flow_temperature != 1.0:
            raise UsageError("model.flow_temperature_grid fits the sampling temperature: leave model.flow_temperature "
                             "at 1 with it (or set the temperature and no grid)")
        if not self.flow_hidden:
            raise UsageError("model.flow_hidden must be a non-empty list of positive widths")
        if self.speed_normalize and (self.scale_augment_std > 0 or (self.name == "flomo" and self.flomo_scale_std > 0)):
            key = "model.flomo_scale_std" if self.name == "flomo" else "model.scale_augment_std"
            raise UsageError(f"model.speed_normalize scales every scene to the training pace, which undoes a scaling "
                             f"augmentation: set {key}=0 with it")


def check_fields(section: Any, name: str) -> None:
    """Refuse a config section (ModelConfig / TrainConfig) holding a value outside its field's bounds (see
    :func:`~trajflow_pipeline.util.bounds.bounded`), with a UsageError naming the key and the value."""
    for item in fields(section):
        check_value(getattr(section, item.name), item.metadata, f"{name}.{item.name}")


#: How the social GNN combines a node's incoming messages (ModelConfig.gnn_aggregate).
GNN_AGGREGATES = ("sum", "mean")

#: How a run picks the flow weights it keeps (TrainConfig.flow_select).
FLOW_SELECTIONS = ("val_loss", "val_nll")
#: Training settings that say where and how a run computes, not what: a run may change them when it resumes.
EXECUTION_KEYS = ("device", "compile_flow")
#: Whether the flow stage's steps run compiled (TrainConfig.compile_flow).
COMPILE_CHOICES = ("auto", "on", "off")
#: With compile_flow = "auto", the flow stage is compiled on a CPU when it surely runs at least this many steps
#: (its minimum epochs times its batches): measured on the 2-core Xeon, compiling costs 117 s once (27 s with
#: inductor's cache of an earlier run) and saves 25 ms of a batch-128 step, so it pays from about 4,700 steps.
COMPILE_MIN_STEPS = 5000
#: The stages trained by gradient descent, each with its own settings (TrainConfig.schedule).
GRADIENT_STAGES = ("autoencoder", "flow")


@dataclass(frozen=True)
class StageSchedule:
    """How one gradient stage trains: its ``train.ae_*`` or ``train.flow_*`` settings as one object
    (:meth:`TrainConfig.schedule`), so that training reads ``schedule.max_epochs`` whichever stage it is."""

    lr: float
    weight_decay: float
    #: per process under torchrun
    batch_size: int
    #: the learning rate's factor per epoch; None: a constant rate (the autoencoder's)
    lr_decay: float | None
    min_epochs: int
    max_epochs: int
    #: epochs without a better validation loss that end the stage after `min_epochs` (0: no early stopping)
    patience: int


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation of the two training stages (AE: autoencoder; flow: flow + context encoders).

    Early stopping follows the reference implementation: after ``*_min_epochs`` epochs, a stage stops once
    ``*_patience`` epochs passed without a better validation loss (0 disables early stopping), and the best
    validation weights are kept. ``*_batch_size`` is per process under torchrun.
    """

    #: seeds torch and numpy (util.bounds.SEED: 0 .. 2**63 - 1, as every command's seed)
    seed: int = bounded(0, bounds=SEED)
    #: "auto" (CUDA when available, else CPU), "cpu", "cuda" or "cuda:N".
    device: str = "auto"
    ae_lr: float = bounded(5e-4, gt=0)
    ae_weight_decay: float = bounded(1e-4, ge=0)
    ae_batch_size: int = bounded(128, ge=1)
    ae_max_epochs: int = bounded(5000, ge=0)
    ae_min_epochs: int = bounded(100, ge=0)
    ae_patience: int = bounded(10, ge=0)
    flow_lr: float = bounded(1e-3, gt=0)
    flow_weight_decay: float = bounded(1e-5, ge=0)
    flow_batch_size: int = bounded(128, ge=1)
    flow_lr_decay: float = bounded(0.98, gt=0, le=1)
    flow_max_epochs: int = bounded(500, ge=0)
    flow_min_epochs: int = bounded(50, ge=0)
    flow_patience: int = bounded(10, ge=0)
    #: Which flow weights a run keeps. "val_loss" (the reference): those of the epoch with the lowest validation
    #: loss, the flow's NLL in its own space. "val_nll" (ours): those with the lowest evaluation NLL -- ROME
    #: densities of model draws, in metres, pooled over identical inputs, as `trajflow eval` computes it -- on a
    #: fixed subset of `flow_select_problems` validation problems with `flow_select_samples` draws each (at most
    #: `flow_select_max_pooled` per pooled group), checked every `flow_select_every` epochs and at the last one.
    #: Early stopping follows the validation loss either way, so both keep weights of the same training.
    flow_select: str = "val_loss"
    flow_select_every: int = bounded(5, ge=1)
    flow_select_problems: int = bounded(256, ge=1)
    #: at least 2: a density needs two draws
    flow_select_samples: int = bounded(100, ge=2)
    flow_select_max_pooled: int = bounded(1000, ge=2)
    #: Fraction of the training problems held out for validation when the dataset has no validation split.
    val_fraction: float = bounded(0.1, gt=0, lt=1)
    #: Clip the global gradient norm to this value; 0 disables clipping.
    grad_clip: float = bounded(0.0, ge=0)
    #: Batch size used for validation passes (no gradients, so it can be larger).
    eval_batch_size: int = bounded(256, ge=1)
    #: Run the flow stage's training steps through a compiled log-density and, where the model has a social GNN,
    #: a compiled edge block (torch.compile; the same function to float rounding, needs a C++ compiler): "on",
    #: "off", or "auto" -- on a CPU, when the stage surely runs
    #: COMPILE_MIN_STEPS steps or more, so that the one-off compile pays for itself. A machine that cannot
    #: compile trains eager and says so.
    compile_flow: str = "auto"

    def with_execution_of(self, other: TrainConfig) -> TrainConfig:
        """These settings with `other`'s EXECUTION_KEYS (device, compile_flow): for comparing what two runs train."""
        return replace(self, **{key: getattr(other, key) for key in EXECUTION_KEYS})

    def compiles_flow(self, device_type: str, planned_steps: int) -> bool:
        """Whether the flow stage compiles on a device of `device_type` ("cpu", "cuda") when it surely runs
        `planned_steps` more steps."""
        if self.compile_flow == "auto":
            return device_type == "cpu" and planned_steps >= COMPILE_MIN_STEPS
        return self.compile_flow == "on"

    def schedule(self, stage: str) -> StageSchedule:
        """The settings of gradient stage `stage` (one of GRADIENT_STAGES): train.ae_* for the autoencoder,
        train.flow_* for the flow."""
        if stage == "autoencoder":
            return StageSchedule(lr=self.ae_lr, weight_decay=self.ae_weight_decay, batch_size=self.ae_batch_size,
                                 lr_decay=None, min_epochs=self.ae_min_epochs, max_epochs=self.ae_max_epochs,
                                 patience=self.ae_patience)
        if stage == "flow":
            return StageSchedule(lr=self.flow_lr, weight_decay=self.flow_weight_decay,
                                 batch_size=self.flow_batch_size, lr_decay=self.flow_lr_decay,
                                 min_epochs=self.flow_min_epochs, max_epochs=self.flow_max_epochs,
                                 patience=self.flow_patience)
        raise ValueError(f"{stage!r} is not a gradient stage ({', '.join(GRADIENT_STAGES)})")

    def validate(self) -> None:
        """Reject values no optimiser can use, with a message naming the key."""
        check_fields(self, "train")
        if self.compile_flow not in COMPILE_CHOICES:
            raise UsageError(f"train.compile_flow must be one of {', '.join(COMPILE_CHOICES)}, not "
                             f"{self.compile_flow!r}")
        if self.flow_select not in FLOW_SELECTIONS:
            raise UsageError(f"train.flow_select must be one of {', '.join(FLOW_SELECTIONS)}, not {self.flow_select!r}")
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
        if not path.exists():
            raise UsageError(f"{path}: config file not found")
        try:
            data = tomllib.loads(input_files.read_text(path))
        except DataError as exc:  # not a regular file, or not UTF-8: a bad config file is a usage error here
            raise UsageError(str(exc)) from None
        except tomllib.TOMLDecodeError as exc:
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
    config = apply_overrides(config, overrides)
    try:
        return config.validate()
    except UsageError as error:  # a combination of values: name where they came from
        source = " and ".join(([str(path)] if path is not None else []) + (["--set"] if overrides else []))
        raise UsageError(f"{source}: {error}" if source else str(error)) from None


def apply_overrides(config: RunConfig, overrides: typing.Sequence[str]) -> RunConfig:
    """Apply ``key=value`` strings to `config` (see :func:`load_config`)."""
    values: dict[str, Any] = {}
    for item in overrides:
        if "=" not in item:
            raise UsageError(f"--set expects key=value, got {item!r}")
        key, raw = (part.strip() for part in item.split("=", 1))
        section, name = _resolve_key(key)
        values.pop(f"{section}.{name}", None)  # the last --set of a setting wins, however it is spelled
        values[f"{section}.{name}"] = parse_value(raw)
    return with_values(config, values, source="--set")


def with_values(config: RunConfig, values: dict[str, Any], source: str) -> RunConfig:
    """`config` with the settings `values` (``{"train.seed": 3}``; keys as :func:`load_config` takes them) changed,
    each checked for its type and bounds; errors name `source` (the option the values came from)."""
    merged = config.to_dict()
    for key, value in values.items():
        section, name = _resolve_key(key)
        merged[section][name] = value
    return RunConfig.from_dict(merged, source=source)


def to_toml(data: dict[str, dict[str, Any]]) -> str:
    """Serialise a two-level dict of scalars and lists of scalars as TOML."""
    lines: list[str] = []
    for section, values in data.items():
        if lines:
            lines.append("")
        lines.append(f"[{section}]")
        lines.extend(f"{key} = {toml_value(value)}" for key, value in values.items())
    return "\n".join(lines) + "\n"


def toml_value(value: Any) -> str:
    """`value` (a scalar or a list of scalars) written as TOML, as a config file or a `--set KEY=VALUE` holds it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
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


def _section(cls: type, values: Any, section: str, source: str) -> Any:
    if not isinstance(values, dict):
        raise UsageError(f"{source}: [{section}] must be a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise UsageError(f"{source}: unknown config key '{section}.{unknown[0]}'")
    kwargs = {key: _coerce(value, hints[key], f"{section}.{key}", source) for key, value in values.items()}
    for item in fields(cls):
        if item.name in kwargs:
            check_value(kwargs[item.name], item.metadata, f"{section}.{item.name}", source)
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
