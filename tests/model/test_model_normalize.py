"""Target-frame normalisation: heading along +x, robust headings, exact inverse."""

from __future__ import annotations

import math

import torch

from trajflow_pipeline.model.normalize import (denormalize_future, heading, normalize_future, past_displacements,
                                               positions_to_displacements, target_frame, to_local, to_world)


def _random_tracks(n: int = 64, steps: int = 20, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.cumsum(torch.randn(n, steps, 2, generator=g, dtype=dtype), 1) + torch.randn(n, 1, 2, generator=g,
                                                                                              dtype=dtype) * 50


def test_round_trip_is_exact_to_1e6() -> None:
    track = _random_tracks()
    past, future = track[:, :8], track[:, 8:]
    frame = target_frame(past)
    scaled = normalize_future(future, frame, alpha=10.0)
    assert torch.allclose(denormalize_future(scaled, frame, alpha=10.0), future, atol=1e-6, rtol=0)
    assert torch.allclose(to_world(to_local(past, frame), frame), past, atol=1e-6, rtol=0)


def test_round_trip_float32_single_precision() -> None:
    track = _random_tracks(dtype=torch.float32)
    past, future = track[:, :8], track[:, 8:]
    frame = target_frame(past)
    back = denormalize_future(normalize_future(future, frame, 10.0), frame, 10.0)
    assert (back - future).abs().max() < 1e-4


def test_last_step_points_along_plus_x_and_origin_at_t0() -> None:
    past = _random_tracks()[:, :8]
    local = to_local(past, target_frame(past))
    assert torch.allclose(local[:, -1], torch.zeros(64, 2, dtype=torch.float64), atol=1e-9)
    last = local[:, -1] - local[:, -2]
    assert torch.allclose(last[:, 1], torch.zeros(64, dtype=torch.float64), atol=1e-9)
    assert (last[:, 0] > 0).all()


def test_displacements_are_scaled_steps() -> None:
    positions = torch.tensor([[[1.0, 0.0], [3.0, 1.0]]])
    assert torch.equal(positions_to_displacements(positions, 10.0), torch.tensor([[[10.0, 0.0], [20.0, 10.0]]]))


def test_zero_last_step_falls_back_to_last_movement() -> None:
    past = torch.tensor([[[0.0, 0.0], [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]],      # moved up, then stood still
                         [[2.0, 2.0], [2.0, 2.0], [2.0, 2.0], [2.0, 2.0]]])     # never moved
    cos, sin = heading(past)
    assert torch.allclose(cos, torch.tensor([0.0, 1.0]), atol=1e-7)
    assert torch.allclose(sin, torch.tensor([1.0, 0.0]), atol=1e-7)
    single = heading(torch.zeros(3, 1, 2))
    assert torch.equal(single[0], torch.ones(3)) and torch.equal(single[1], torch.zeros(3))
    assert torch.isfinite(normalize_future(past + 1, target_frame(past), 10.0)).all()


def test_rotation_is_a_proper_rotation() -> None:
    past = _random_tracks()[:, :8]
    frame = target_frame(past)
    assert torch.allclose(frame.cos ** 2 + frame.sin ** 2, torch.ones(64, dtype=torch.float64))
    angle = math.pi / 3
    turned = torch.stack((past[..., 0] * math.cos(angle) - past[..., 1] * math.sin(angle),
                          past[..., 0] * math.sin(angle) + past[..., 1] * math.cos(angle)), -1)
    assert torch.allclose(to_local(turned, target_frame(turned)), to_local(past, frame), atol=1e-8)


def test_past_displacements_ignore_missing_steps() -> None:
    track = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]])
    valid = torch.tensor([[False, True, True, True]])
    assert torch.equal(past_displacements(track, valid), torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 0.0]]]))
    assert past_displacements(track[:, :1]).shape == (1, 1, 2)
