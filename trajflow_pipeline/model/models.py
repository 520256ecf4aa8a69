"""The model families behind ``--model``: TrajFlow, TrajFlow without autoencoder, FloMo and constant velocity.

Common interface (:class:`TrajectoryModel`):

* ``stages`` -- the training stages in order; ``stage_loss(stage, batch)`` is what that stage minimises and
  ``stage_parameters(stage)`` what it trains (everything else is frozen while it runs). A stage listed in
  ``closed_form_stages`` is fitted in one pass by ``fit_stage(stage, batch)`` instead of by gradient descent.
  The flow models insert the closed-form stage ``standardize`` before ``flow`` when ``model.flow_standardize``,
  and append ``temperature`` (fitted by the training loop from draws on the validation split, see
  :meth:`FlowModel.set_sampling_temperature`) when ``model.flow_temperature_grid`` is set.
* ``loss(batch)`` -- the final stage's loss (the flow NLL for the flow models).
* ``log_likelihood(batch)`` -- log-density of each problem's ground-truth future under the model, in the space
  named by ``log_lik_space``.
* ``sample(batch, n, steps=None)`` -- :class:`Samples`: ``trajectories`` (B, n, steps, 2) in WORLD coordinates and
  ``log_lik`` (B, n), the log-density of each sample in ``log_lik_space`` (NOT a density over world trajectories):

  ============== =====================================================================================
  trajflow       the flow's density of the 20-d autoencoder latent (nats)
  trajflow-no-ae the flow's density of the 2*n_future alpha-scaled displacements in the target frame
  flomo          as trajflow-no-ae
  cv             the Gaussian density of the 2*steps alpha-scaled displacements in the target frame
  ============== =====================================================================================

  ``steps`` may exceed n_future: TrajFlow's auto-regressive decoder rolls out further; the direct-displacement
  models extend beyond their trained horizon at constant velocity (their last displacement, i.e. the step
  between their last two predicted positions), as the paper's reference framework does. ``beyond_horizon``
  names which of the two a model does (:data:`AUTOREGRESSIVE`, :data:`CV_EXTENSION`; the cv baseline is
  constant velocity throughout, :data:`NATIVE`), so that evaluation can record it.
"""

from __future__ import annotations

import abc
import contextlib
import hashlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import ClassVar, NamedTuple

import torch
from torch import Tensor, nn

from ..errors import UsageError
from .autoencoder import TrajectoryAutoencoder
from .batch import SceneBatch
from .config import DataSpec, ModelConfig
from .encoders import ContextEncoder, MapEncoder, PastEncoder, SocialGNN
from .flow import ConditionalSplineFlow
from .normalize import (MIN_STEP, Frame, denormalize_future, lower_quantile, normalize_future, scene_speed,
                        target_frame, to_local, to_world)
from .runtime import cpu_workers, map_in_threads, thread_chunks


#: How a model predicts past its trained horizon (``TrajectoryModel.beyond_horizon``).
AUTOREGRESSIVE = "autoregressive"
CV_EXTENSION = "constant-velocity extension"
NATIVE = "native"


class Samples(NamedTuple):
    """Sampled futures in world coordinates (B, n, steps, 2) and their log-likelihoods (B, n)."""

    trajectories: Tensor
    log_lik: Tensor


@dataclass(frozen=True)
class Normalized:
    """A batch in its target frames: the frames, the target's local past (B, P, 2) and, when known, the
    alpha-scaled future displacements (B, F, 2)."""

    frame: Frame
    local_past: Tensor
    future: Tensor | None


class TrajectoryModel(nn.Module, abc.ABC):
    """Base class: normalisation, the stage protocol and the sampling contract (see the module docstring)."""

    name: ClassVar[str]
    #: the family's stages; an instance may extend them from its config (FlowModel: "standardize")
    stages: tuple[str, ...]
    closed_form_stages: tuple[str, ...] = ()
    log_lik_space: ClassVar[str]
    #: how steps past the trained horizon are made: AUTOREGRESSIVE, CV_EXTENSION or NATIVE (module docstring)
    beyond_horizon: ClassVar[str] = CV_EXTENSION

    def __init__(self, config: ModelConfig, spec: DataSpec) -> None:
        super().__init__()
        self.config = config
        self.spec = spec
        # One draw of torch's global generator; each component's initial weights come from its own stream
        # seeded by it and the component's name (component_stream).
        self.init_seed = int(torch.randint(0, 2 ** 62, (1,)))
        if config.speed_normalize:
            if config.use_map and spec.has_map:
                raise UsageError("model.speed_normalize does not scale map crops: set model.use_map=false with it, "
                                 "or leave it off for a dataset with maps")
            # model.speed_normalize's reference pace (metres a step): NaN until fit_data_constants
            self.register_buffer("speed_reference", torch.tensor(float("nan")))

    @classmethod
    def stages_for(cls, config: ModelConfig) -> tuple[str, ...]:
        """The training stages, in order, of this family's model built with `config` (known without building it)."""
        return cls.stages

    def normalize(self, batch: SceneBatch, sampling: bool = False) -> Normalized:
        """Target frames, local past and (if present) scaled future displacements of `batch`; with
        model.speed_normalize the frames scale each scene to the training pace (:meth:`speed_scales`; `sampling`:
        for drawing futures, where model.speed_normalize_sample_threshold applies)."""
        frame = target_frame(batch.past)
        if self.config.speed_normalize:
            frame = replace(frame, scale=self.speed_scales(batch, sampling))
        future = None if batch.future is None else normalize_future(batch.future, frame, self.config.alpha)
        return Normalized(frame, to_local(batch.past, frame), future)

    def fit_data_constants(self, batch: SceneBatch) -> None:
        """Fit, on the training split and before the first stage, what the model derives from its data rather
        than learns: model.speed_normalize's reference pace, the model.speed_normalize_quantile of the training
        problems' scene speeds (the lower of two neighbours, no interpolation: at 0.5 torch's median). Kept with
        the weights (a buffer), so a resumed run or a loaded model keeps it; fitted only once."""
        if self.config.speed_normalize and torch.isnan(self.speed_reference):
            speed = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
            self.speed_reference.fill_(lower_quantile(speed, self.config.speed_normalize_quantile))

    def speed_scales(self, batch: SceneBatch, sampling: bool = False) -> Tensor:
        """Per problem (B,), the factor model.speed_normalize scales its scene by: the reference pace over the
        scene's own (:func:`~.normalize.scene_speed`), clipped to [speed_normalize_min, speed_normalize_max].
        When `sampling`, a scene faster than the reference but not faster than speed_normalize_sample_threshold
        times it keeps its own pace (factor 1)."""
        if torch.isnan(self.speed_reference):
            raise RuntimeError("model.speed_normalize: fit_data_constants(training batch) comes before any use")
        speed = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
        reference = self.speed_reference.to(speed.dtype)
        ratio = reference / speed.clamp(min=MIN_STEP)
        threshold = self.config.speed_normalize_sample_threshold
        if sampling and threshold > 1:
            own_pace = (speed > reference) & (speed <= threshold * reference)
            ratio = torch.where(own_pace, torch.ones_like(ratio), ratio)
        return ratio.clamp(self.config.speed_normalize_min, self.config.speed_normalize_max)

    @abc.abstractmethod
    def stage_parameters(self, stage: str) -> list[nn.Parameter]:
        """Parameters trained by `stage`."""

    @abc.abstractmethod
    def stage_loss(self, stage: str, batch: SceneBatch) -> Tensor:
        """Scalar loss minimised by `stage` on `batch` (which must include the future)."""

    def fit_stage(self, stage: str, batch: SceneBatch) -> None:
        """Closed-form fit of a stage in ``closed_form_stages`` on the whole training split."""
        raise ValueError(f"stage {stage!r} of {self.name} is trained by gradient descent")

    def fixed_targets(self, stage: str, batch: SceneBatch) -> Tensor | None:
        """What `stage` fits for every problem of `batch` where it cannot change while the stage trains, so that
        training computes it once (``SceneBatch.targets``) instead of at every step; None where it is not fixed
        (the default)."""
        return None

    def compile_stage(self, stage: str, rows: int) -> str | None:
        """Compile what a training step of `stage` computes for batches of `rows` problems, where the family has
        a compiled path (FlowModel: the flow stage's log-density and the social GNN's edge block); None when
        compiled, else why not."""
        return f"{self.name} has no compiled path for its {stage} stage"

    def drop_compiled(self) -> None:
        """Back to eager evaluation everywhere (after :meth:`compile_stage`)."""

    def loss(self, batch: SceneBatch) -> Tensor:
        """The final stage's loss: mean negative log-likelihood (nats) in ``log_lik_space``."""
        return self.stage_loss(self.stages[-1], batch)

    @abc.abstractmethod
    def log_likelihood(self, batch: SceneBatch) -> Tensor:
        """Log-density (B,) of each ground-truth future in ``log_lik_space``."""

    @abc.abstractmethod
    def sample(self, batch: SceneBatch, n: int, steps: int | None = None,
               generator: torch.Generator | None = None) -> Samples:
        """`n` futures per problem, `steps` long (default n_future), in world coordinates, with log-likelihoods.

        Runs without gradients; the generator (optional) makes the draw reproducible.
        """

    def _require_future(self, batch: SceneBatch) -> None:
        if batch.future is None:
            raise ValueError("this loss needs the ground-truth future (batch.future is None)")


@contextlib.contextmanager
def component_stream(model: TrajectoryModel, component: str) -> Iterator[None]:
    """Initialise `component` from its own random stream: torch's global generator seeded from the model's
    ``init_seed`` and the component's name, and restored afterwards.

    So a component's initial weights depend on the training seed and its own shape only: changing the size of
    one (a wider flow, another autoencoder) leaves the others' starting points as they were, and an ablation
    compares what it says it compares."""
    digest = hashlib.sha256(f"{model.init_seed}:{component}".encode()).digest()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int.from_bytes(digest[:8], "little") % 2 ** 63)
        yield


def _check_steps(steps: int | None, default: int) -> int:
    steps = default if steps is None else int(steps)
    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    return steps


def extend_constant_velocity(displacements: Tensor, steps: int) -> Tensor:
    """Truncate (..., F, 2) displacements to `steps`, or extend them by repeating the last displacement."""
    have = displacements.shape[-2]
    if steps <= have:
        return displacements[..., :steps, :]
    tail = displacements[..., -1:, :].expand(*displacements.shape[:-2], steps - have, 2)
    return torch.cat((displacements, tail), dim=-2)


class FlowModel(TrajectoryModel):
    """A conditional flow over a per-problem target vector, conditioned on the context encoders.

    With ``flow_standardize`` the stage ``standardize`` (closed form, after any autoencoder stage) sets the flow's
    input standardization from the training targets; its loss is the NLL of the diagonal Gaussian with those
    means and standard deviations, the floor the flow stage has to beat.
    """

    log_lik_space = "scaled_displacements"
    STANDARDIZE = "standardize"
    TEMPERATURE = "temperature"

    def __init__(self, config: ModelConfig, spec: DataSpec, features: int, seed: int = 0) -> None:
        super().__init__(config, spec)
        with component_stream(self, "past"):
            past = PastEncoder(config.past_embed, config.past_hidden, config.past_layers, config.past_out)
        social = None
        if config.use_social:
            with component_stream(self, "social"):
                node_past = PastEncoder(config.past_embed, config.past_hidden, config.past_layers, config.past_out)
                social = SocialGNN(config.gnn_width, config.gnn_layers, node_past, aggregate=config.gnn_aggregate)
        map_encoder = None
        if config.use_map and spec.has_map:
            with component_stream(self, "map"):
                map_encoder = MapEncoder(config.map_height, config.map_width, config.map_out)
        self.context = ContextEncoder(past=past, social=social, map_encoder=map_encoder)
        with component_stream(self, "flow"):
            self.flow = ConditionalSplineFlow(features, self.context.out_features, layers=config.flow_layers,
                                              bins=config.flow_bins, tail_bound=config.flow_tail_bound,
                                              hidden=tuple(config.flow_hidden), seed=seed,
                                              standardize=config.flow_standardize)
        if config.flow_temperature_grid:
            # model.flow_temperature_grid's choice, kept with the weights: NaN until the stage "temperature" runs
            self.register_buffer("fitted_temperature", torch.tensor(float("nan")))
        self.stages = self.stages_for(config)
        self.closed_form_stages = (*self.closed_form_stages,
                                   *(s for s in (self.STANDARDIZE, self.TEMPERATURE) if s in self.stages))

    @classmethod
    def stages_for(cls, config: ModelConfig) -> tuple[str, ...]:
        """The family's stages, with the closed-form "standardize" fit before the flow and "temperature" after it
        when the config asks for them."""
        stages = cls.stages
        if config.flow_standardize:
            stages = (*stages[:-1], cls.STANDARDIZE, stages[-1])
        if config.flow_temperature_grid:
            stages = (*stages, cls.TEMPERATURE)
        return stages

    def sampling_temperature(self) -> float:
        """The standard deviation of the flow's base distribution when it draws: model.flow_temperature, or with
        model.flow_temperature_grid the fitted one (1 until the stage "temperature" sets it, e.g. while the flow
        stage checks its draws)."""
        if not self.config.flow_temperature_grid:
            return self.config.flow_temperature
        fitted = float(self.fitted_temperature)
        return fitted if math.isfinite(fitted) else 1.0

    def set_sampling_temperature(self, temperature: float) -> None:
        """Set the temperature the stage "temperature" chose (kept with the weights; model.flow_temperature_grid
        only: without it the temperature is the config's)."""
        if not self.config.flow_temperature_grid:
            raise ValueError("the sampling temperature is model.flow_temperature: set model.flow_temperature_grid to "
                             "fit it")
        self.fitted_temperature.fill_(float(temperature))

    def loss(self, batch: SceneBatch) -> Tensor:
        """The flow's mean NLL (nats) in ``log_lik_space``, whatever closed-form stage follows it."""
        return self.flow_nll(batch)

    def fit_stage(self, stage: str, batch: SceneBatch) -> None:
        if stage == self.TEMPERATURE:
            raise ValueError("the stage temperature is fitted from draws on the validation split by the training "
                             "loop (set_sampling_temperature), not from a training batch")
        if stage != self.STANDARDIZE or not self.config.flow_standardize:
            super().fit_stage(stage, batch)
            return
        self._require_future(batch)
        chunks = [self.targets(self.normalize(batch.index(slice(i, i + 4096))))
                  for i in range(0, len(batch), 4096)]
        self.flow.fit_standardization(torch.cat(chunks))

    def standardized_gaussian_nll(self, batch: SceneBatch) -> Tensor:
        """Mean NLL of the batch's targets under N(shift, diag(scale^2)): the standardize stage's loss."""
        self._require_future(batch)
        return -self.flow.standardization_log_prob(self.targets(self.normalize(batch))).mean()

    @abc.abstractmethod
    def targets(self, norm: Normalized) -> Tensor:
        """The vector (B, D) the flow models for each problem."""

    @abc.abstractmethod
    def decode(self, x: Tensor, steps: int) -> Tensor:
        """Flow vectors (..., D) -> alpha-scaled displacements (..., steps, 2) in the target frame."""

    def flow_parameters(self) -> list[nn.Parameter]:
        return [*self.context.parameters(), *self.flow.parameters()]

    def stage_parameters(self, stage: str) -> list[nn.Parameter]:
        if stage == "flow":
            return self.flow_parameters()
        if stage in self.closed_form_stages:
            return []
        raise ValueError(f"unknown stage {stage!r} for {self.name}")

    def compile_stage(self, stage: str, rows: int) -> str | None:
        if stage != "flow":
            return super().compile_stage(stage, rows)
        failure = self.flow.compile_training(rows)
        if failure is None and self.context.social is not None:
            failure = self.context.social.compile_edges()
        if failure is not None:
            self.drop_compiled()   # all or nothing: one record says how the stage trains
        return failure

    def drop_compiled(self) -> None:
        self.flow.drop_compiled()
        if self.context.social is not None:
            self.context.social.drop_compiled()

    def stage_loss(self, stage: str, batch: SceneBatch) -> Tensor:
        if stage == "flow":
            return self.flow_nll(batch)
        if stage == self.STANDARDIZE and stage in self.stages:
            return self.standardized_gaussian_nll(batch)
        raise ValueError(f"unknown stage {stage!r} for {self.name}")

    def flow_nll(self, batch: SceneBatch) -> Tensor:
        """Mean negative log-likelihood of the batch's targets under the conditional flow (while training, of the
        scaled scenes when the model has a scaling augmentation)."""
        self._require_future(batch)
        return -self.log_likelihood(self.augmented(batch)).mean()

    def scale_augmentation(self) -> tuple[float, float, float]:
        """(std, min, max) of the training-time scale factors s ~ N(1, std) truncated to [min, max]; std 0 = none."""
        cfg = self.config
        return cfg.scale_augment_std, cfg.scale_augment_min, cfg.scale_augment_max

    def augmented(self, batch: SceneBatch) -> SceneBatch:
        """While training, `batch` with each problem's scene scaled about the target's position at t0 by a factor
        drawn from torch's global generator (:meth:`scale_augmentation`); otherwise, or without one, `batch`.
        Targets computed once for the unscaled futures (``batch.targets``) are dropped: they do not fit."""
        std, low, high = self.scale_augmentation()
        if not self.training or std == 0:
            return batch
        return replace(scale_scene(batch, truncated_normal_scales(len(batch), std, low, high, batch.past)),
                       targets=None)

    def log_likelihood(self, batch: SceneBatch) -> Tensor:
        self._require_future(batch)
        norm = self.normalize(batch)
        context = self.context(batch, norm.frame, norm.local_past)
        targets = batch.targets if batch.targets is not None else self.targets(norm)
        return self.flow.log_prob(targets, context)

    #: draws x problems inverted and decoded at a time when sampling: the spline's and the decoder's temporaries
    #: of a chunk stay near the cache (measured on the 2-core AMD EPYC, 100 draws for 1000 agents: the flow's
    #: inverse 3.2-3.6 s in one piece, 1.8-2.1 s in chunks of 10,000 rows). The noise is drawn first, so
    #: chunks change only float rounding (bit for bit there; tiny chunks' matrix products may round otherwise).
    #: On a CPU the chunks run side by side in torch's thread count of Python threads (:func:`map_in_threads`),
    #: their count a multiple of it and their sizes equal, so that no thread waits for a longer last chunk.
    SAMPLE_CHUNK_ROWS = 10_000

    @torch.no_grad()
    def sample(self, batch: SceneBatch, n: int, steps: int | None = None,
               generator: torch.Generator | None = None) -> Samples:
        steps = _check_steps(steps, self.spec.n_future)
        norm = self.normalize(batch, sampling=True)
        context = self.context(batch, norm.frame, norm.local_past)
        temperature = self.sampling_temperature()
        z = self.flow.noise(context, n, generator, temperature)                  # all draws first: one stream

        def draw(chunk: slice) -> tuple[Tensor, Tensor]:
            x, log_lik = self.flow.from_noise(z[:, chunk], context[chunk], temperature)   # (n, b, D), (n, b)
            return self.decode(x, steps).transpose(0, 1), log_lik.transpose(0, 1)          # (b, n, steps, 2), (b, n)

        pieces = map_in_threads(draw, thread_chunks(len(batch), n, self.SAMPLE_CHUNK_ROWS, cpu_workers(z.device)),
                                z.device)
        trajectories = denormalize_future(torch.cat([piece[0] for piece in pieces]), norm.frame, self.config.alpha)
        return Samples(trajectories, torch.cat([piece[1] for piece in pieces]))


class TrajFlow(FlowModel):
    """TrajFlow: an RNN autoencoder (stage 1, then frozen) and a conditional flow over its latent (stage 2)."""

    name = "trajflow"
    stages = ("autoencoder", "flow")
    log_lik_space = "latent"
    beyond_horizon = AUTOREGRESSIVE

    def __init__(self, config: ModelConfig, spec: DataSpec, seed: int = 0) -> None:
        super().__init__(config, spec, config.latent_dim, seed)
        with component_stream(self, "autoencoder"):
            self.autoencoder = TrajectoryAutoencoder(config.ae_embed, config.ae_hidden, config.ae_layers,
                                                     config.latent_dim)

    def stage_parameters(self, stage: str) -> list[nn.Parameter]:
        if stage == "autoencoder":
            return list(self.autoencoder.parameters())
        return super().stage_parameters(stage)

    def stage_loss(self, stage: str, batch: SceneBatch) -> Tensor:
        if stage == "autoencoder":
            self._require_future(batch)
            return self.autoencoder.reconstruction_loss(self.normalize(self.augmented(batch)).future,
                                                        self.config.alpha)
        return super().stage_loss(stage, batch)

    def targets(self, norm: Normalized) -> Tensor:
        # The autoencoder is frozen while the flow trains: its latents are fixed targets.
        with torch.no_grad():
            return self.autoencoder.encode(norm.future)

    #: problems encoded at a time by `fixed_targets`
    TARGET_CHUNK = 4096

    def fixed_targets(self, stage: str, batch: SceneBatch) -> Tensor | None:
        """The frozen autoencoder's latents of every problem, for the flow stage (on the batch's device)."""
        if stage != "flow" or len(batch) == 0:
            return None
        self._require_future(batch)
        device = next(self.parameters()).device
        trajectories = replace(batch, map_crop=None, targets=None)                 # what encoding reads
        chunks = [self.targets(self.normalize(trajectories.index(slice(i, i + self.TARGET_CHUNK)).to(device)))
                  for i in range(0, len(batch), self.TARGET_CHUNK)]
        return torch.cat(chunks).to(batch.past.device)

    def decode(self, x: Tensor, steps: int) -> Tensor:
        return self.autoencoder.decode(x, steps)


class TrajFlowNoAE(FlowModel):
    """The ablation "TrajFlow w/o AE": the same flow directly over the 2*n_future scaled displacements."""

    name = "trajflow-no-ae"
    stages = ("flow",)

    def __init__(self, config: ModelConfig, spec: DataSpec, seed: int = 0) -> None:
        super().__init__(config, spec, 2 * spec.n_future, seed)

    def targets(self, norm: Normalized) -> Tensor:
        return norm.future.flatten(1)

    def decode(self, x: Tensor, steps: int) -> Tensor:
        displacements = x.unflatten(-1, (self.spec.n_future, 2))
        return extend_constant_velocity(displacements, steps)


class FloMo(TrajFlowNoAE):
    """FloMo (Schoeller & Knoll 2021): TrajFlow w/o AE plus FloMo's training-time regularisation.

    While training (``self.training``), each problem's scene is scaled about the target's position at t0 by
    s ~ N(1, flomo_scale_std) truncated to [flomo_scale_min, flomo_scale_max] (FloMo's scaling augmentation, the
    mechanism of :meth:`FlowModel.augmented`), and noise is added to the flow's input: std beta on scaled
    displacements with |y| < flomo_zero_threshold (avoiding infinite-density points for standing agents), std
    gamma on all others. Evaluation is noise-free.
    """

    name = "flomo"

    def scale_augmentation(self) -> tuple[float, float, float]:
        cfg = self.config
        return cfg.flomo_scale_std, cfg.flomo_scale_min, cfg.flomo_scale_max

    def targets(self, norm: Normalized) -> Tensor:
        y = super().targets(norm)
        if not self.training:
            return y
        cfg = self.config
        small = y.abs() < cfg.flomo_zero_threshold
        std = torch.where(small, torch.full_like(y, cfg.flomo_beta), torch.full_like(y, cfg.flomo_gamma))
        return y + std * torch.randn_like(y)


def truncated_normal_scales(n: int, std: float, low: float, high: float, like: Tensor) -> Tensor:
    """`n` scale factors s ~ N(1, std) truncated to [low, high], by inverse-CDF sampling from torch's global
    generator (one uniform draw per factor), in `like`'s dtype and device."""
    normal = torch.distributions.Normal(0.0, 1.0)
    lo = normal.cdf(torch.tensor((low - 1) / std))
    hi = normal.cdf(torch.tensor((high - 1) / std))
    u = lo + (hi - lo) * torch.rand(n, device=like.device, dtype=like.dtype)
    return (1 + std * torch.special.ndtri(u)).clamp(low, high)


def scale_scene(batch: SceneBatch, scale: Tensor) -> SceneBatch:
    """Scale every position of each problem (B,) about the target's position at t0 (map crops unchanged)."""
    centre = batch.past[:, -1]
    view = scale[:, None, None]

    def about(points: Tensor, s: Tensor, c: Tensor) -> Tensor:
        return c + s * (points - c)

    neighbours = about(batch.neighbours, view[..., None], centre[:, None, None, :])
    neighbours = neighbours * batch.neighbours_valid[..., None].to(neighbours.dtype)
    future = None if batch.future is None else about(batch.future, view, centre[:, None, :])
    return replace(batch, past=about(batch.past, view, centre[:, None, :]), neighbours=neighbours, future=future)


class ConstantVelocity(TrajectoryModel):
    """Constant velocity from the last past step plus isotropic Gaussian noise growing linearly with horizon.

    Step k (1-based) of the future is N(x0 + k v, (sigma k)^2 I); sigma is fitted in closed form (maximum
    likelihood) on the training split. It is the sanity floor every report shows.
    """

    name = "cv"
    stages = ("fit",)
    closed_form_stages = ("fit",)
    log_lik_space = "scaled_displacements"
    beyond_horizon = NATIVE

    def __init__(self, config: ModelConfig, spec: DataSpec, seed: int = 0) -> None:
        super().__init__(config, spec)
        self.register_buffer("sigma", torch.tensor(1.0))

    def stage_parameters(self, stage: str) -> list[nn.Parameter]:
        return []

    def _velocity(self, local_past: Tensor) -> Tensor:
        if local_past.shape[1] < 2:
            return torch.zeros_like(local_past[:, 0])
        return local_past[:, -1] - local_past[:, -2]

    def _residuals(self, batch: SceneBatch) -> tuple[Tensor, Tensor]:
        """Per-step residuals divided by the step index, (B, F, 2), and the step indices (F,)."""
        self._require_future(batch)
        norm = self.normalize(batch)
        k = torch.arange(1, batch.future.shape[1] + 1, device=batch.past.device, dtype=batch.past.dtype)
        mean = k[None, :, None] * self._velocity(norm.local_past)[:, None, :]
        local_future = to_local(batch.future, norm.frame)
        return (local_future - mean) / k[None, :, None], k

    def fit_stage(self, stage: str, batch: SceneBatch) -> None:
        if stage != "fit":
            raise ValueError(f"unknown stage {stage!r} for {self.name}")
        scaled, _ = self._residuals(batch)
        self.sigma.copy_(torch.sqrt((scaled ** 2).mean()).clamp(min=1e-4))

    def _log_density(self, scaled: Tensor, k: Tensor) -> Tensor:
        """Density of positions expressed as alpha-scaled displacements (unit-Jacobian cumsum, then * alpha)."""
        sigma = self.sigma.to(scaled.dtype)
        per_dim = -0.5 * (scaled / sigma) ** 2 - torch.log(sigma * k)[..., :, None] - 0.5 * math.log(2 * math.pi)
        return per_dim.sum((-1, -2)) - 2 * k.shape[0] * math.log(self.config.alpha)

    def log_likelihood(self, batch: SceneBatch) -> Tensor:
        scaled, k = self._residuals(batch)
        return self._log_density(scaled, k)

    def stage_loss(self, stage: str, batch: SceneBatch) -> Tensor:
        if stage != "fit":
            raise ValueError(f"unknown stage {stage!r} for {self.name}")
        return -self.log_likelihood(batch).mean()

    @torch.no_grad()
    def sample(self, batch: SceneBatch, n: int, steps: int | None = None,
               generator: torch.Generator | None = None) -> Samples:
        steps = _check_steps(steps, self.spec.n_future)
        norm = self.normalize(batch, sampling=True)
        size = len(batch)
        k = torch.arange(1, steps + 1, device=batch.past.device, dtype=batch.past.dtype)
        eps = torch.randn((size, n, steps, 2), generator=generator, device=batch.past.device, dtype=batch.past.dtype)
        velocity = self._velocity(norm.local_past)[:, None, None, :]
        local = k[:, None] * velocity + self.sigma.to(eps.dtype) * k[:, None] * eps
        log_lik = self._log_density(eps * self.sigma.to(eps.dtype), k)
        return Samples(to_world(local, norm.frame), log_lik)


MODEL_CLASSES: dict[str, type[TrajectoryModel]] = {
    cls.name: cls for cls in (TrajFlow, TrajFlowNoAE, FloMo, ConstantVelocity)
}


def build_model(config: ModelConfig, spec: DataSpec, seed: int = 0) -> TrajectoryModel:
    """A fresh model of family ``config.name`` for data described by `spec`; `seed` fixes the flow permutations."""
    config.validate()
    if spec.n_future < 1 or spec.n_past < 1:
        raise ValueError("n_past and n_future must be at least 1")
    return MODEL_CLASSES[config.name](config, spec, seed=seed)
