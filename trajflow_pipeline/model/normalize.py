"""Agent-centric normalisation: the frame every model reasons in, and its exact inverse.

For each problem the *target frame* has its origin at the target's last observed position and its x axis along
the target's last past step, so that the target always "drives along +x" at t0. Futures are represented as
per-step displacements in that frame, multiplied by ``alpha`` (10 by default) so that pedestrian steps of a few
centimetres reach a range where the spline flow (tail bound 15) has resolution. With model.speed_normalize the
frame also scales each scene to the training split's pace (Frame.scale, from :func:`scene_speed`).

All functions are batched over the leading dimension and work in any floating dtype (use float64 when an exact
round trip matters, e.g. for tests to 1e-6).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

#: Steps shorter than this (metres) carry no usable heading.
MIN_STEP = 1e-4


@dataclass(frozen=True)
class Frame:
    """Per-problem target frame: origin (B, 2) in world coordinates, heading (cos, sin), each (B,), and optionally
    a scale (B,) that local coordinates are multiplied by (model.speed_normalize; None: 1)."""

    origin: Tensor
    cos: Tensor
    sin: Tensor
    scale: Tensor | None = None

    def expand(self, n: int) -> "Frame":
        """The same frames repeated `n` times per problem (problem-major), for (B * n) samples."""
        return Frame(self.origin.repeat_interleave(n, 0), self.cos.repeat_interleave(n, 0),
                     self.sin.repeat_interleave(n, 0),
                     None if self.scale is None else self.scale.repeat_interleave(n, 0))


def heading(past: Tensor, min_step: float = MIN_STEP) -> tuple[Tensor, Tensor]:
    """Unit heading (cos, sin) of the last past step of each problem, robust to standing agents.

    The last step is used when it is longer than `min_step`; otherwise the most recent step that is, and +x
    when the agent never moved (or there is a single past position).
    """
    batch = past.shape[0]
    if past.shape[1] < 2:
        one = past.new_ones(batch)
        return one, past.new_zeros(batch)
    steps = past[:, 1:] - past[:, :-1]                                     # (B, P-1, 2)
    length = torch.linalg.vector_norm(steps, dim=-1)                       # (B, P-1)
    moving = length > min_step
    index = torch.arange(steps.shape[1], device=past.device).expand_as(moving)
    last = torch.where(moving, index, torch.full_like(index, -1)).max(dim=1).values   # (B,)
    chosen = steps.gather(1, last.clamp(min=0)[:, None, None].expand(-1, 1, 2)).squeeze(1)
    norm = length.gather(1, last.clamp(min=0)[:, None]).squeeze(1)
    found = last >= 0
    safe = torch.where(found, norm, torch.ones_like(norm))
    cos = torch.where(found, chosen[:, 0] / safe, torch.ones_like(norm))
    sin = torch.where(found, chosen[:, 1] / safe, torch.zeros_like(norm))
    return cos, sin


def target_frame(past: Tensor) -> Frame:
    """The target frame of each problem from its past positions (B, P, 2)."""
    cos, sin = heading(past)
    return Frame(past[:, -1], cos, sin)


def _per_problem(value: Tensor, like: Tensor) -> Tensor:
    """View a (B,) or (B, 2) per-problem tensor so it broadcasts against points (B, ..., 2)."""
    extra = like.dim() - value.dim()
    return value.reshape(value.shape[0], *([1] * extra), *value.shape[1:])


def to_local(points: Tensor, frame: Frame) -> Tensor:
    """World points (B, ..., 2) -> target-frame points (translate to the origin, rotate heading onto +x)."""
    origin = _per_problem(frame.origin, points)
    cos = _per_problem(frame.cos, points[..., 0])
    sin = _per_problem(frame.sin, points[..., 0])
    d = points - origin
    local = torch.stack((cos * d[..., 0] + sin * d[..., 1], -sin * d[..., 0] + cos * d[..., 1]), dim=-1)
    return local if frame.scale is None else local * _per_problem(frame.scale, points[..., 0])[..., None]


def to_world(points: Tensor, frame: Frame) -> Tensor:
    """Exact inverse of :func:`to_local`."""
    origin = _per_problem(frame.origin, points)
    cos = _per_problem(frame.cos, points[..., 0])
    sin = _per_problem(frame.sin, points[..., 0])
    if frame.scale is not None:
        points = points / _per_problem(frame.scale, points[..., 0])[..., None]
    x, y = points[..., 0], points[..., 1]
    return torch.stack((cos * x - sin * y, sin * x + cos * y), dim=-1) + origin


def scene_speed(past: Tensor, neighbours: Tensor, neighbours_valid: Tensor, neighbours_mask: Tensor) -> Tensor:
    """Mean step length (B,) over every observed past step of every agent of each problem: the target's past
    (B, P, 2) and its neighbours' (B, N, P, 2), a step counting where both of its end points are observed (and
    finite); 0 for a problem without any step. What model.speed_normalize scales scenes by: only what is observed
    at t0, so training and prediction compute it alike."""
    target_steps = past.diff(dim=1)
    target_length = torch.linalg.vector_norm(target_steps, dim=-1)                      # (B, P-1)
    target_seen = torch.isfinite(target_length)
    seen = neighbours_valid & neighbours_mask[..., None]                                # (B, N, P)
    both = seen[..., 1:] & seen[..., :-1]
    length = torch.linalg.vector_norm(neighbours.diff(dim=2), dim=-1)                   # (B, N, P-1)
    both = both & torch.isfinite(length)
    total = (torch.where(target_seen, target_length, 0).sum(1)
             + torch.where(both, length, 0).sum((1, 2)))
    count = target_seen.sum(1) + both.sum((1, 2))
    return total / count.clamp(min=1)


def lower_quantile(values: Tensor, q: float) -> Tensor:
    """The q-quantile of a 1-d tensor without interpolation: the sorted value at index floor(q (n - 1)), so at
    q = 0.5 the lower of the two middle values, as torch.median gives (and no size limit, unlike
    torch.quantile)."""
    return values.sort().values[int(q * (values.numel() - 1))]


def positions_to_displacements(positions: Tensor, alpha: float) -> Tensor:
    """Local future positions (B, F, 2) (origin = position at t0) -> alpha-scaled per-step displacements."""
    previous = torch.cat((torch.zeros_like(positions[:, :1]), positions[:, :-1]), dim=1)
    return (positions - previous) * alpha


def displacements_to_positions(displacements: Tensor, alpha: float) -> Tensor:
    """Exact inverse of :func:`positions_to_displacements` along dim -2 (works for (..., F, 2))."""
    return torch.cumsum(displacements / alpha, dim=-2)


def past_displacements(local_past: Tensor, valid: Tensor | None = None) -> Tensor:
    """Per-step displacements of past tracks (..., P, 2) -> (..., max(P-1, 1), 2), zero where a step is missing.

    A step counts only when both of its end points are observed (`valid`, (..., P) bool). A single observed
    position yields one zero displacement so that recurrent encoders always see a sequence.
    """
    if local_past.shape[-2] < 2:
        return torch.zeros_like(local_past[..., :1, :])
    steps = local_past[..., 1:, :] - local_past[..., :-1, :]
    if valid is None:
        return steps
    both = (valid[..., 1:] & valid[..., :-1]).unsqueeze(-1)
    return torch.where(both, steps, torch.zeros_like(steps))


def normalize_future(future: Tensor, frame: Frame, alpha: float) -> Tensor:
    """World future positions (B, F, 2) -> alpha-scaled displacements (B, F, 2) in the target frame."""
    return positions_to_displacements(to_local(future, frame), alpha)


def denormalize_future(displacements: Tensor, frame: Frame, alpha: float) -> Tensor:
    """Alpha-scaled target-frame displacements (B, ..., F, 2) -> world positions; inverse of normalize_future."""
    return to_world(displacements_to_positions(displacements, alpha), frame)
