"""model.speed_normalize: every scene seen at the training pace. The scene speed, the frame's scale and its exact
inverse, the fitted reference kept with the weights, scale invariance of every model, and the refused combinations."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.model.batch import SceneBatch
from trajflow_pipeline.model.config import MODEL_NAMES, DataSpec, ModelConfig
from trajflow_pipeline.model.models import build_model
from trajflow_pipeline.model.normalize import lower_quantile, scene_speed, target_frame, to_local, to_world
from trajflow_pipeline.model.toy import crowd_batch

SPEC = DataSpec(n_past=8, n_future=12)


def _double(batch: SceneBatch) -> SceneBatch:
    """The batch's positions in float64 (masks and classes as they are)."""
    return replace(batch, past=batch.past.double(), neighbours=batch.neighbours.double(), future=batch.future.double())


def _scaled(batch: SceneBatch, factor: float) -> SceneBatch:
    """The whole world scaled about the origin: every position times `factor`."""
    future = None if batch.future is None else batch.future * factor
    return replace(batch, past=batch.past * factor, neighbours=batch.neighbours * factor, future=future)


def test_scene_speed_is_the_mean_observed_step_of_every_agent() -> None:
    past = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]]])                      # steps 1 and 2
    neighbours = torch.tensor([[[[0.0, 0.0], [0.0, 4.0], [0.0, 0.0]],                 # steps 4, (unseen)
                                [[5.0, 5.0], [5.0, 5.0], [9.0, 5.0]]]])               # padding: not counted
    valid = torch.tensor([[[True, True, False], [True, True, True]]])
    mask = torch.tensor([[True, False]])
    assert scene_speed(past, neighbours, valid, mask).tolist() == pytest.approx([(1 + 2 + 4) / 3])
    still = torch.zeros(1, 3, 2)
    assert scene_speed(still, neighbours[:, :0], valid[:, :0], mask[:, :0]).tolist() == [0.0]


def test_the_reference_is_a_quantile_of_the_training_paces() -> None:
    """speed_normalize_quantile: 0.5 is torch's median (the lower middle value); a higher quantile scales fewer
    training scenes, and with speed_normalize_max = 1 only those faster than the reference."""
    batch = crowd_batch(41, neighbours=3)
    speeds = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
    references = {}
    for q in (0.5, 0.9):
        model = build_model(ModelConfig(name="cv", speed_normalize=True, speed_normalize_max=1.0,
                                        speed_normalize_quantile=q), SPEC)
        model.fit_data_constants(batch)
        references[q] = float(model.speed_reference)
        scaled = model.speed_scales(batch) < 1
        assert torch.equal(scaled, speeds > model.speed_reference)
    assert references[0.5] == float(speeds.median())
    assert references[0.9] == float(speeds.sort().values[36])                            # floor(0.9 * 40)
    even = speeds[:40]
    assert float(lower_quantile(even, 0.5)) == float(even.median())
    with pytest.raises(UsageError, match="speed_normalize_quantile"):
        ModelConfig(speed_normalize_quantile=1.0).validate()


def test_a_scaled_frame_round_trips_exactly() -> None:
    batch = _double(crowd_batch(5, neighbours=3))
    frame = replace(target_frame(batch.past), scale=torch.tensor([0.5, 1.0, 2.0, 3.0, 0.33], dtype=torch.float64))
    local = to_local(batch.future, frame)
    plain = to_local(batch.future, target_frame(batch.past))
    assert torch.allclose(local, plain * frame.scale[:, None, None])
    assert torch.allclose(to_world(local, frame), batch.future, atol=1e-12)
    draws = local[:, None].expand(-1, 4, -1, -1)                                   # (B, n, F, 2), as sampling has
    assert torch.allclose(to_world(draws, frame), batch.future[:, None].expand(-1, 4, -1, -1), atol=1e-12)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_model_sees_a_scaled_world_alike(name: str) -> None:
    """With speed_normalize a world scaled by k gives the same normalised problem, so the same losses and
    log-likelihoods, and draws scaled by k (the same noise)."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name, speed_normalize=True, flomo_scale_std=0.0), SPEC).double().eval()
    batch = _double(crowd_batch(16, neighbours=4))
    with pytest.raises(RuntimeError, match="fit_data_constants"):
        model.normalize(batch)
    model.fit_data_constants(batch)
    reference = float(model.speed_reference)
    speeds = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
    assert reference == pytest.approx(float(speeds.median()))
    model.fit_data_constants(_scaled(batch, 5.0))                                     # fitted once
    assert float(model.speed_reference) == reference
    for stage in model.stages:
        if stage in model.closed_form_stages:
            model.fit_stage(stage, batch)
    faster = _scaled(batch, 1.5)
    assert torch.allclose(model.speed_scales(faster) * 1.5, model.speed_scales(batch), rtol=1e-9)
    for stage in model.stages:
        assert torch.allclose(model.stage_loss(stage, faster), model.stage_loss(stage, batch), rtol=1e-7, atol=1e-9)
    assert torch.allclose(model.log_likelihood(faster), model.log_likelihood(batch), rtol=1e-7, atol=1e-9)
    draws = model.sample(batch.without_future(), 3, generator=torch.Generator().manual_seed(1))
    fast_draws = model.sample(faster.without_future(), 3, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(fast_draws.trajectories, draws.trajectories * 1.5, rtol=1e-6, atol=1e-9)


def test_the_reference_is_kept_with_the_weights() -> None:
    config = ModelConfig(name="trajflow", speed_normalize=True)
    model = build_model(config, SPEC)
    model.fit_data_constants(crowd_batch(32, neighbours=4))
    again = build_model(config, SPEC)
    again.load_state_dict(model.state_dict())
    assert float(again.speed_reference) == float(model.speed_reference) > 0
    assert "speed_reference" not in build_model(ModelConfig(name="trajflow"), SPEC).state_dict()


def test_combinations_it_cannot_serve_are_refused() -> None:
    with pytest.raises(UsageError, match="scale_augment_std=0"):
        build_model(ModelConfig(name="trajflow", speed_normalize=True, scale_augment_std=0.5), SPEC)
    with pytest.raises(UsageError, match="flomo_scale_std=0"):
        build_model(ModelConfig(name="flomo", speed_normalize=True), SPEC)
    with pytest.raises(UsageError, match="map crops"):
        build_model(ModelConfig(name="trajflow", speed_normalize=True), replace(SPEC, has_map=True))
    build_model(ModelConfig(name="trajflow", speed_normalize=True, use_map=False), replace(SPEC, has_map=True))


@pytest.mark.parametrize("name", ["trajflow", "cv"])
def test_the_sample_threshold_leaves_moderately_fast_scenes_at_their_own_pace(name: str) -> None:
    """speed_normalize_sample_threshold: when drawing, scenes between the reference and the threshold times it keep
    factor 1, faster and slower ones are scaled as in training; training's losses and log_likelihood do not change,
    and a scene left at its own pace is drawn as a model without speed normalization draws it."""
    batch = _double(crowd_batch(24, neighbours=3))
    base = dict(name=name, speed_normalize=True, speed_normalize_max=1.0, flomo_scale_std=0.0)
    torch.manual_seed(0)
    plain = build_model(ModelConfig(**base), SPEC).double().eval()
    torch.manual_seed(0)
    model = build_model(ModelConfig(**base, speed_normalize_sample_threshold=1.1), SPEC).double().eval()
    for m in (plain, model):
        m.fit_data_constants(batch)
        for stage in m.stages:
            if stage in m.closed_form_stages:
                m.fit_stage(stage, batch)
    speeds = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
    reference = model.speed_reference
    between = (speeds > reference) & (speeds <= 1.1 * reference)
    assert between.any() and (speeds > 1.1 * reference).any()
    trained, drawn = model.speed_scales(batch), model.speed_scales(batch, sampling=True)
    assert torch.equal(trained, plain.speed_scales(batch, sampling=True))               # threshold 1: as trained
    assert torch.all(drawn[between] == 1) and torch.all(trained[between] < 1)
    assert torch.equal(drawn[~between], trained[~between])
    for stage in model.stages:
        assert torch.equal(model.stage_loss(stage, batch), plain.stage_loss(stage, batch))
    assert torch.equal(model.log_likelihood(batch), plain.log_likelihood(batch))
    draws = model.sample(batch.without_future(), 3, generator=torch.Generator().manual_seed(1)).trajectories
    before = plain.sample(batch.without_future(), 3, generator=torch.Generator().manual_seed(1)).trajectories
    assert torch.allclose(draws[~between], before[~between], rtol=1e-9, atol=1e-12)
    assert not torch.allclose(draws[between], before[between])
    with pytest.raises(UsageError, match="speed_normalize_sample_threshold"):
        ModelConfig(speed_normalize_sample_threshold=0.5).validate()
