"""Small synthetic :class:`SceneBatch` generators for tests, benchmarks and smoke checks (no files involved).

:func:`bimodal_batch` mimics the paper's synthetic bimodal set (section V-A): one straight past, two future modes
(curving left or right with equal probability), each problem scaled by s ~ N(1, scale_std) and optionally placed
at a random position and heading in the world, so that only a model that normalises correctly sees identical
inputs. :func:`crowd_batch` builds random-walk scenes with neighbours for shape and speed checks.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .batch import NUM_AGENT_TYPES, SceneBatch


def bimodal_batch(n: int, *, n_past: int = 10, n_future: int = 14, step: float = 0.25, curvature: float = 0.08,
                  scale_std: float = 0.15, noise: float = 0.01, random_pose: bool = True, neighbours: int = 0,
                  seed: int = 0) -> tuple[SceneBatch, Tensor]:
    """`n` problems and their mode labels (n,) in {-1, +1} (+1 = future curving to the left of the heading)."""
    g = torch.Generator().manual_seed(seed)
    t_past = torch.arange(-(n_past - 1), 1, dtype=torch.float64) * step
    t_future = torch.arange(1, n_future + 1, dtype=torch.float64) * step
    mode = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).to(torch.float64)
    scale = (1 + scale_std * torch.randn(n, 1, 1, generator=g, dtype=torch.float64)).clamp(min=0.3)
    past = torch.stack((t_past, torch.zeros_like(t_past)), -1).expand(n, -1, -1)
    future = torch.stack((t_future.expand(n, -1), mode[:, None] * curvature * t_future ** 2), -1)
    past = past * scale + noise * torch.randn(past.shape, generator=g, dtype=torch.float64)
    future = future * scale + noise * torch.randn(future.shape, generator=g, dtype=torch.float64)
    past[:, -1] = 0.0
    if random_pose:
        angle = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
        shift = torch.randn(n, 1, 2, generator=g, dtype=torch.float64) * 20
        past, future = _pose(past, angle, shift), _pose(future, angle, shift)
    nb, nb_valid, nb_mask, nb_type = _random_neighbours(past, neighbours, g)
    batch = SceneBatch(past=past.float(), future=future.float(), agent_type=torch.zeros(n, dtype=torch.long),
                       neighbours=nb, neighbours_valid=nb_valid, neighbours_mask=nb_mask, neighbours_type=nb_type)
    return batch, mode.float()


def crowd_batch(n: int, *, n_past: int = 8, n_future: int = 12, neighbours: int = 8, step: float = 0.4,
                map_size: tuple[int, int] | None = None, seed: int = 0) -> SceneBatch:
    """Random-walk targets with up to `neighbours` random-walk neighbours (some padded, some partly observed)."""
    g = torch.Generator().manual_seed(seed)
    heading = torch.rand(n, 1, generator=g) * 2 * math.pi
    velocity = torch.cat((heading.cos(), heading.sin()), -1)[:, None, :] * step
    walk = torch.cumsum(velocity + 0.1 * torch.randn(n, n_past + n_future, 2, generator=g), dim=1)
    walk = walk - walk[:, n_past - 1:n_past] + torch.randn(n, 1, 2, generator=g) * 10
    past, future = walk[:, :n_past], walk[:, n_past:]
    nb, nb_valid, nb_mask, nb_type = _random_neighbours(past.double(), neighbours, g)
    crop = None if map_size is None else torch.rand(n, 1, *map_size, generator=g)
    return SceneBatch(past=past, future=future, agent_type=torch.randint(0, NUM_AGENT_TYPES, (n,), generator=g),
                      neighbours=nb, neighbours_valid=nb_valid, neighbours_mask=nb_mask, neighbours_type=nb_type,
                      map_crop=crop)


def _pose(points: Tensor, angle: Tensor, shift: Tensor) -> Tensor:
    c, s = angle.cos()[:, None], angle.sin()[:, None]
    x, y = points[..., 0], points[..., 1]
    return torch.stack((c * x - s * y, s * x + c * y), -1) + shift


def _random_neighbours(past: Tensor, count: int, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    n, steps = past.shape[:2]
    offsets = torch.randn(n, count, 1, 2, generator=g, dtype=torch.float64) * 3
    drift = torch.cumsum(torch.randn(n, count, steps, 2, generator=g, dtype=torch.float64) * 0.2, dim=2)
    positions = past[:, None] + offsets + drift
    mask = torch.rand(n, count, generator=g) < 0.8
    first = torch.randint(0, steps, (n, count), generator=g)
    valid = (torch.arange(steps)[None, None, :] >= first[..., None]) & mask[..., None]
    positions = torch.where(valid[..., None], positions, torch.zeros_like(positions))
    types = torch.randint(0, NUM_AGENT_TYPES, (n, count), generator=g)
    return positions.float(), valid, mask, types
