"""The tensor-level pieces of a training step: batches on the device, the stage's objective and optimizer, the
gradient check, and the mean stage loss over ranks."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ..model.batch import SceneBatch
from ..model.models import TrajectoryModel
from .distributed import DistContext


class StageObjective(nn.Module):
    """forward(batch) = the model's loss for one stage; the module DDP wraps so gradients are all-reduced."""

    def __init__(self, model: TrajectoryModel, stage: str) -> None:
        super().__init__()
        self.model = model
        self.stage = stage

    def forward(self, batch: SceneBatch) -> Tensor:
        return self.model.stage_loss(self.stage, batch)


def part(batch: SceneBatch, idx: Tensor, device: torch.device) -> SceneBatch:
    """Problems `idx` of `batch`, on `device` (map crops stay on the host until a batch needs them)."""
    piece = batch.index(idx.to(batch.past.device))
    return piece if piece.past.device == device else piece.to(device)


def on_device(batch: SceneBatch, device: torch.device) -> SceneBatch:
    """Keep map crops on the host (too large to preload); move everything else once."""
    if device.type == "cpu" or batch.map_crop is not None:
        return batch
    return batch.to(device)


def adamw(params: list[nn.Parameter], lr: float, weight_decay: float) -> torch.optim.Optimizer:
    """AdamW, fused into one kernel per step where the device supports it (several times faster on CPU)."""
    try:
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)


def finite_gradients(params: list[nn.Parameter], clip: float) -> bool:
    """Clip the global gradient norm (when `clip` > 0) and report whether every gradient is finite."""
    grads = [p for p in params if p.grad is not None]
    if not grads:
        return True
    norm = torch.nn.utils.clip_grad_norm_(grads, clip if clip > 0 else math.inf)
    return bool(torch.isfinite(norm))


@torch.no_grad()
def mean_loss(model: TrajectoryModel, stage: str, batch: SceneBatch, chunk: int, dist: DistContext,
              device: torch.device) -> float:
    """Size-weighted mean of the stage loss over `batch` (this rank's interleaved share, reduced over ranks)."""
    model.eval()
    n = len(batch)
    mine = torch.arange(dist.rank, n, dist.world)
    total, count = 0.0, 0
    for start in range(0, len(mine), chunk):
        idx = mine[start:start + chunk]
        total += float(model.stage_loss(stage, part(batch, idx, device))) * len(idx)
        count += len(idx)
    total, count = dist.sum([total, count], device)
    return total / count if count else math.nan


def copy_weights(model: nn.Module) -> dict[str, Tensor]:
    """The model's weights, copied to the host (what a training state and the kept best weights hold)."""
    return {name: value.detach().to("cpu", copy=True) for name, value in model.state_dict().items()}
