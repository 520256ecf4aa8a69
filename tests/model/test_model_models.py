"""The four model families: shapes, world-frame outputs, horizons past n_future, masks, baselines' specifics."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from compile_fakes import NO_COMPILER, without_compiler

from trajflow_pipeline.model import compiled as compiled_module
from trajflow_pipeline.model.autoencoder import TrajectoryAutoencoder
from trajflow_pipeline.model.batch import SceneBatch
from trajflow_pipeline.model.config import MODEL_NAMES, DataSpec, ModelConfig
from trajflow_pipeline.model.encoders import (SocialGNN, compact_neighbours, pool_edges, pool_edges_to_compile,
                                             size_groups, social_nodes)
from trajflow_pipeline.model.models import (FloMo, build_model, extend_constant_velocity, scale_scene,
                                             truncated_normal_scales)
from trajflow_pipeline.model.normalize import displacements_to_positions, target_frame, to_local
from trajflow_pipeline.model.runtime import thread_chunks
from trajflow_pipeline.model.toy import bimodal_batch, crowd_batch

SPEC = DataSpec(n_past=8, n_future=12)


def _model(name: str, spec: DataSpec = SPEC, **kwargs: object) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model(ModelConfig(name=name, **kwargs), spec).eval()


def _rotate(batch: SceneBatch, angle: float, shift: tuple[float, float]) -> SceneBatch:
    c, s = math.cos(angle), math.sin(angle)
    matrix = torch.tensor([[c, s], [-s, c]])
    offset = torch.tensor(shift)

    def move(points: torch.Tensor) -> torch.Tensor:
        return points @ matrix + offset

    neighbours = move(batch.neighbours) * batch.neighbours_valid[..., None]
    return replace(batch, past=move(batch.past), future=move(batch.future), neighbours=neighbours)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_shapes_losses_and_long_horizons(name: str) -> None:
    batch = crowd_batch(6, neighbours=5)
    model = _model(name)
    for stage in model.stages:
        if stage in model.closed_form_stages:
            model.fit_stage(stage, batch)
        loss = model.stage_loss(stage, batch)
        assert loss.shape == () and torch.isfinite(loss)
    assert model.log_likelihood(batch).shape == (6,)
    for steps in (None, 5, 30):
        trajectories, log_lik = model.sample(batch.without_future(), 4, steps=steps)
        assert trajectories.shape == (6, 4, steps or 12, 2) and log_lik.shape == (6, 4)
        assert torch.isfinite(trajectories).all() and torch.isfinite(log_lik).all()
    assert isinstance(model.log_lik_space, str) and model.log_lik_space


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae"])
def test_no_neighbours_and_maps(name: str) -> None:
    spec = DataSpec(n_past=8, n_future=12, has_map=True)
    model = _model(name, spec)
    assert model.context.map is not None
    batch = crowd_batch(3, neighbours=0, map_size=(156, 257))
    assert batch.neighbours.shape[1] == 0
    trajectories, _ = model.sample(batch, 2)
    assert trajectories.shape == (3, 2, 12, 2)
    assert torch.isfinite(model.loss(batch))
    with pytest.raises(ValueError, match="map_crop"):
        model.loss(replace(batch, map_crop=None))
    assert _model(name).context.map is None


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_samples_follow_the_scene_pose(name: str) -> None:
    """Rotating and moving the whole scene moves the samples the same way (normalisation + exact inverse)."""
    batch = crowd_batch(5, neighbours=4)
    model = _model(name)
    if name == "cv":
        model.fit_stage("fit", batch)
    angle, shift = 0.7, (40.0, -25.0)
    a, la = model.sample(batch, 3, generator=torch.Generator().manual_seed(5))
    b, lb = model.sample(_rotate(batch, angle, shift), 3, generator=torch.Generator().manual_seed(5))
    expected = _rotate(replace(batch, future=a.reshape(5, -1, 2)), angle, shift).future.reshape(a.shape)
    assert torch.allclose(b, expected, atol=2e-3)
    assert torch.allclose(la, lb, atol=2e-3)


def test_direct_models_extend_at_constant_velocity() -> None:
    model = _model("trajflow-no-ae")
    batch = crowd_batch(4, neighbours=2)
    long, _ = model.sample(batch, 3, steps=16, generator=torch.Generator().manual_seed(1))
    short, _ = model.sample(batch, 3, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(long[:, :, :12], short, atol=1e-5)
    steps = long[:, :, 11:] - long[:, :, 10:-1]
    assert torch.allclose(steps, steps[:, :, :1].expand_as(steps), atol=1e-4)
    disp = torch.arange(6.0).reshape(1, 3, 2)
    assert extend_constant_velocity(disp, 5)[0, 3:].tolist() == [[4.0, 5.0], [4.0, 5.0]]
    assert extend_constant_velocity(disp, 2).shape == (1, 2, 2)


def test_sample_log_lik_is_the_flow_density_of_the_sample() -> None:
    model = _model("trajflow-no-ae")
    batch = crowd_batch(4, neighbours=3)
    trajectories, log_lik = model.sample(batch, 1, generator=torch.Generator().manual_seed(2))
    replay = model.log_likelihood(replace(batch, future=trajectories[:, 0]))
    assert torch.allclose(replay, log_lik[:, 0], atol=5e-2)


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae", "flomo"])
def test_flow_temperature_widens_the_draws_only(name: str) -> None:
    """model.flow_temperature changes the draws (and their scores) and nothing the training reads: the same
    weights give the same training log-likelihoods; at T the draws are those of the base noise scaled by T."""
    batch = crowd_batch(6, neighbours=3)
    model = _model(name)
    warm = _model(name, flow_temperature=1.5)
    warm.load_state_dict(model.state_dict())
    assert torch.equal(warm.log_likelihood(batch), model.log_likelihood(batch))
    draws, log_lik = warm.sample(batch, 50, generator=torch.Generator().manual_seed(3))
    cold, cold_log_lik = model.sample(batch, 50, generator=torch.Generator().manual_seed(3))
    spread = lambda d: (d - d.mean(1, keepdim=True)).norm(dim=-1).mean()   # noqa: E731
    assert spread(draws) > spread(cold)
    norm = warm.normalize(batch)
    context = warm.context(batch, norm.frame, norm.local_past)
    z = warm.flow.noise(context, 50, torch.Generator().manual_seed(3), 1.5)
    assert torch.allclose(log_lik.T, warm.flow.from_noise(z, context, 1.5)[1], atol=1e-4)


def test_decoder_rolls_out_past_the_trained_horizon() -> None:
    torch.manual_seed(0)
    ae = TrajectoryAutoencoder()
    latent = torch.randn(5, 20)
    long, short = ae.decode(latent, 35), ae.decode(latent, 12)
    assert long.shape == (5, 35, 2) and torch.allclose(long[:, :12], short, atol=1e-6)
    assert ae.decode(torch.randn(3, 4, 20), 7).shape == (3, 4, 7, 2)


def test_decoder_without_gradients_is_the_gru_decoder() -> None:
    """Sampling's decoder (GRU on columns, gates rearranged, without gradients) is nn.GRU's recursion."""
    torch.manual_seed(1)
    ae = TrajectoryAutoencoder().double()
    latent = torch.randn(20, 3, 5, dtype=torch.float64).permute(1, 2, 0)   # a transposed layout, as sampling gives
    reference = ae.decode(latent, 17)                                        # parameters need gradients: nn.GRU
    with torch.no_grad():
        fast = ae.decode(latent, 17)
    assert reference.requires_grad and not fast.requires_grad
    assert torch.allclose(fast, reference, atol=1e-12)


def test_autoencoder_loss_is_rmse_on_positions() -> None:
    torch.manual_seed(0)
    ae = TrajectoryAutoencoder()
    disp = torch.randn(8, 12, 2)
    recon = ae(disp)
    expected = ((displacements_to_positions(recon, 10.0) - displacements_to_positions(disp, 10.0)) ** 2)
    expected = expected.sum(-1).mean().sqrt()
    assert torch.allclose(ae.reconstruction_loss(disp, 10.0), expected, atol=1e-5)


def test_gnn_ignores_padding_and_neighbour_order() -> None:
    batch = crowd_batch(4, neighbours=6)
    frame = target_frame(batch.past)
    local = to_local(batch.past, frame)
    torch.manual_seed(0)
    gnn = SocialGNN().eval()
    base = gnn(*social_nodes(batch, frame, local))
    garbage = torch.where(batch.neighbours_mask[..., None, None], batch.neighbours,
                          torch.full_like(batch.neighbours, 1e3))
    assert torch.allclose(gnn(*social_nodes(replace(batch, neighbours=garbage), frame, local)), base, atol=1e-5)
    order = torch.randperm(6)
    shuffled = replace(batch, neighbours=batch.neighbours[:, order], neighbours_valid=batch.neighbours_valid[:, order],
                       neighbours_mask=batch.neighbours_mask[:, order], neighbours_type=batch.neighbours_type[:, order])
    assert torch.allclose(gnn(*social_nodes(shuffled, frame, local)), base, atol=1e-5)
    padded = compact_neighbours(batch)
    assert padded.neighbours.shape[1] == int(batch.neighbours_mask.sum(1).max())


def test_constant_velocity_fits_its_noise_scale() -> None:
    g = torch.Generator().manual_seed(0)
    n, sigma = 4000, 0.05
    velocity = torch.randn(n, 1, 2, generator=g)
    steps = torch.arange(-7, 13, dtype=torch.float32)[None, :, None]
    track = steps * velocity
    k = torch.arange(1, 13, dtype=torch.float32)[None, :, None]
    track[:, 8:] += sigma * k * torch.randn(n, 12, 2, generator=g)
    batch = crowd_batch(n, neighbours=0)
    batch = replace(batch, past=track[:, :8], future=track[:, 8:])
    model = _model("cv")
    model.fit_stage("fit", batch)
    assert float(model.sigma) == pytest.approx(sigma, rel=0.05)
    trajectories, _ = model.sample(batch.index(slice(0, 50)), 400)
    mean = trajectories.mean(1)
    assert torch.allclose(mean, (steps[:, 8:] * velocity)[:50], atol=4 * sigma * 12 / 20)
    spread = (trajectories[:, :, -1] - mean[:, None, -1]).std()
    assert float(spread) == pytest.approx(sigma * 12, rel=0.15)


def test_flomo_noise_and_scaling_only_while_training() -> None:
    batch, _ = bimodal_batch(32, n_past=8, n_future=12, neighbours=2)
    model = _model("flomo")
    assert isinstance(model, FloMo)
    model.eval()
    assert torch.equal(model.loss(batch), model.loss(batch))
    model.train()
    assert not torch.equal(model.loss(batch), model.loss(batch))
    factors = truncated_normal_scales(10000, *model.scale_augmentation(), like=batch.past)
    assert float(factors.min()) >= 0.3 and float(factors.max()) <= 1.7
    assert float(factors.mean()) == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae"])
def test_scale_augmentation_trains_every_gradient_stage_on_scaled_scenes(name: str) -> None:
    """model.scale_augment_std: while training, a stage's loss is the loss of the scenes scaled about t0 by factors
    drawn from torch's generator (fixed targets of the unscaled futures dropped); off by default and in eval."""
    batch, _ = bimodal_batch(24, n_past=8, n_future=12, neighbours=3)
    plain = _model(name)
    assert plain.scale_augmentation()[0] == 0.0
    model = _model(name, scale_augment_std=0.4, scale_augment_min=0.5, scale_augment_max=2.0)
    model.load_state_dict(plain.state_dict())
    for stage in model.stages:
        fixed = model.fixed_targets(stage, batch)
        given = batch if fixed is None else replace(batch, targets=fixed)
        assert torch.equal(model.stage_loss(stage, given), plain.stage_loss(stage, given))      # eval: no scaling
        model.train()
        torch.manual_seed(5)
        augmented = model.stage_loss(stage, given)
        torch.manual_seed(5)
        factors = truncated_normal_scales(len(batch), 0.4, 0.5, 2.0, like=batch.past)
        model.eval()
        expected = model.stage_loss(stage, scale_scene(batch, factors))
        assert float(factors.min()) >= 0.5 and float(factors.max()) <= 2.0 and float(factors.std()) > 0.1
        assert torch.allclose(augmented, expected, rtol=1e-5, atol=1e-5)
        assert not torch.allclose(augmented, plain.stage_loss(stage, given), rtol=1e-3, atol=1e-3)


def _reference_rounds(gnn: SocialGNN, x: torch.Tensor, pos: torch.Tensor, onehot: torch.Tensor,
                      mask: torch.Tensor) -> torch.Tensor:
    """The GNN's rounds written as documented, edge by edge on the padded layout:
    m_a = sum (or mean) over valid b of MLP(x_b ++ x_a ++ class_b ++ class_a ++ (p_a - p_b) ++ |p_a - p_b|)."""
    n, layers = mask.shape[1], len(gnn.update)
    rel = pos[:, :, None, :] - pos[:, None, :, :]                                    # [p, a, b] = p_a - p_b
    edge = torch.cat((onehot[:, None].expand(-1, n, -1, -1), onehot[:, :, None].expand(-1, -1, n, -1), rel,
                      torch.sqrt((rel ** 2).sum(-1, keepdim=True) + 1e-12)), dim=-1)
    for layer, w_edge in enumerate(gnn.msg_edge.weight.chunk(layers, dim=0)):
        first = torch.cat((gnn.msg_sender[layer].weight, gnn.msg_receiver[layer].weight, w_edge), dim=1)
        pair = torch.cat((x[:, None].expand(-1, n, -1, -1), x[:, :, None].expand(-1, -1, n, -1), edge), dim=-1)
        hidden = torch.relu(torch.nn.functional.linear(pair, first, gnn.msg_sender[layer].bias))
        message = (gnn.msg_out[layer](hidden) * mask[:, None, :, None]).sum(2)
        if gnn.aggregate == "mean":
            message = message / mask.sum(1)[:, None, None]
        x = gnn.update[layer](torch.cat((x, message), dim=-1)) + x
    return x


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_gnn_dense_and_sparse_message_passing_match_the_documented_rounds(aggregate: str) -> None:
    batch = crowd_batch(6, neighbours=7)
    frame = target_frame(batch.past)
    nodes = social_nodes(batch, frame, to_local(batch.past, frame))
    torch.manual_seed(0)
    gnn = SocialGNN(aggregate=aggregate)
    past, valid, mask, types = nodes
    onehot = torch.nn.functional.one_hot(types, 5).float()
    x = torch.randn(*mask.shape, 32)
    pos = 3 * torch.randn(*mask.shape, 2)
    # Values and gradients (x, positions, the edge weights) of both implementations against the literal one; the
    # sparse path gathers with index_select and scatters with index_add, the dense one pools with a product.
    results = []
    for rounds in (lambda *a: _reference_rounds(gnn, *a), gnn._dense_rounds, gnn._sparse_rounds):
        x_leaf, pos_leaf = x.clone().requires_grad_(True), pos.clone().requires_grad_(True)
        gnn.zero_grad()
        out = rounds(x_leaf, pos_leaf, onehot, mask)[mask]
        (out ** 2).sum().backward()
        results.append((out.detach(), x_leaf.grad[mask], pos_leaf.grad[mask], gnn.msg_edge.weight.grad.clone(),
                        gnn.msg_sender[0].weight.grad.clone()))
    reference = results[0]
    for result in results[1:]:
        assert torch.allclose(result[0], reference[0], atol=1e-4)
        for grad, expected in zip(result[1:], reference[1:]):
            assert torch.allclose(grad, expected, rtol=1e-4, atol=1e-3)


def test_averaged_messages_encode_a_crowd_of_copies_as_the_group_itself() -> None:
    """With mean aggregation every agent doubled (same past, same place) gives the same encoding; summed
    messages double, so the sum-aggregating GNN's encoding moves: what a model meets in a crowd."""
    batch = crowd_batch(5, neighbours=6)
    frame = target_frame(batch.past)
    past, valid, mask, types = social_nodes(batch, frame, to_local(batch.past, frame))
    doubled = [torch.cat((t, t), dim=1) for t in (past, valid, mask, types)]
    moved = {}
    for aggregate in ("mean", "sum"):
        torch.manual_seed(0)
        gnn = SocialGNN(aggregate=aggregate).double().eval()
        with torch.no_grad():
            group = gnn(past.double(), valid, mask, types)
            crowd = gnn(doubled[0].double(), *doubled[1:])
        moved[aggregate] = float((crowd - group).abs().max() / group.abs().max())
    assert moved["mean"] < 1e-9
    assert moved["sum"] > 1e-2


def test_gnn_groups_problems_by_size_without_changing_the_result(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rounds on size-ordered groups of problems, each cut to its own extent, give each problem what the problem
    gets alone, in the batch's order, gradients included; nodes need not be compacted (float64, so that only
    rounding could differ)."""
    torch.manual_seed(0)
    gnn = SocialGNN().double()
    batch, n = 21, 9
    mask = torch.rand(batch, n) < torch.linspace(0.05, 0.9, batch)[:, None]   # from nearly empty to crowded
    mask[:, 0] = True                                                            # the target
    mask[3, 1:] = False                                                          # alone
    mask[5, 1:8], mask[5, 8] = False, True                                       # a hole before its last node
    past = 3 * torch.randn(batch, n, 8, 2, dtype=torch.float64)
    valid = torch.ones(batch, n, 8, dtype=torch.bool) & mask[..., None]
    types = torch.randint(0, 5, (batch, n))

    def encode(group_edges: int, rows: slice | None = None) -> tuple[torch.Tensor, ...]:
        monkeypatch.setattr(SocialGNN, "GROUP_EDGES", group_edges)
        monkeypatch.setattr(SocialGNN, "GROUP_PADDING", group_edges)
        leaf = past.clone().requires_grad_(True)
        gnn.zero_grad()
        chosen = slice(None) if rows is None else rows
        out = gnn(leaf[chosen], valid[chosen], mask[chosen], types[chosen])
        (out ** 2).sum().backward()
        return out.detach(), leaf.grad, gnn.msg_edge.weight.grad.clone()

    grouped = encode(4 * n * n)                                                  # groups of 4 or fewer
    alone = [encode(4 * n * n, slice(i, i + 1)) for i in range(batch)]
    assert torch.allclose(grouped[0], torch.cat([a[0] for a in alone]), rtol=1e-10, atol=1e-12)
    assert torch.allclose(grouped[1], sum(a[1] for a in alone), rtol=1e-10, atol=1e-12)
    assert torch.allclose(grouped[2], sum(a[2] for a in alone), rtol=1e-10, atol=1e-12)
    whole = encode(batch * n * n)                                                # one group
    for value, expected in zip(whole, grouped):
        assert torch.allclose(value, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae"])
def test_sampling_in_chunks_gives_the_same_bits(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Draws are inverted and decoded a chunk of problems at a time; the noise is drawn first, so chunking
    changes nothing but float rounding (matrix products of other shapes may sum in another order)."""
    model = _model(name).eval()
    batch = crowd_batch(13, neighbours=4).without_future()
    whole = model.sample(batch, 6, steps=14, generator=torch.Generator().manual_seed(3))
    monkeypatch.setattr(type(model), "SAMPLE_CHUNK_ROWS", 6 * 4)                # chunks of 4 problems, one of 1
    chunked = model.sample(batch, 6, steps=14, generator=torch.Generator().manual_seed(3))
    assert torch.allclose(whole.trajectories, chunked.trajectories, rtol=1e-5, atol=1e-5)
    assert torch.allclose(whole.log_lik, chunked.log_lik, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae"])
def test_sampling_in_threads_gives_the_serial_draws(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """With two torch threads the chunks run in two Python threads of one torch thread each: the same draws as
    one after the other (float rounding only), and torch's thread count is two again afterwards."""
    model = _model(name).eval()
    batch = crowd_batch(13, neighbours=4).without_future()
    monkeypatch.setattr(type(model), "SAMPLE_CHUNK_ROWS", 6 * 3)                # 6 chunks of 2 or 3 problems
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        serial = model.sample(batch, 6, steps=14, generator=torch.Generator().manual_seed(3))
        torch.set_num_threads(2)
        threaded = model.sample(batch, 6, steps=14, generator=torch.Generator().manual_seed(3))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert torch.allclose(serial.trajectories, threaded.trajectories, rtol=1e-5, atol=1e-5)
    assert torch.allclose(serial.log_lik, threaded.log_lik, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("problems, n, rows, workers", [(1000, 100, 10_000, 2), (512, 100, 10_000, 2),
                                                        (512, 100, 10_000, 1), (13, 6, 18, 2), (3, 20, 10_000, 2),
                                                        (1, 100, 10, 4), (7, 0, 10_000, 3)])
def test_sample_chunks_cover_the_problems_in_equal_pieces(problems: int, n: int, rows: int, workers: int) -> None:
    chunks = thread_chunks(problems, n, rows, workers)
    covered = torch.cat([torch.arange(problems)[chunk] for chunk in chunks])
    assert torch.equal(covered, torch.arange(problems))
    sizes = [chunk.stop - chunk.start for chunk in chunks]
    assert max(sizes) - min(sizes) <= 1 and min(sizes) >= 1
    assert (max(sizes) - 1) * n < max(rows, n)
    assert len(chunks) % workers == 0 or len(chunks) == problems
    assert thread_chunks(0, n, rows, workers) == [slice(0, 0)]


def test_size_groups_keep_padding_and_group_edges_in_bounds() -> None:
    extents = [1, 1, 2, 2, 3, 5, 5, 5, 9, 9]
    assert size_groups(extents, 10**6, 10**6) == [(0, 10)]
    assert size_groups(extents, 1, 10**6) == [(i, i + 1) for i in range(10)]    # one problem per group at least
    bounds = size_groups(extents, 100, 20)
    assert bounds[0][0] == 0 and bounds[-1][1] == 10
    assert all(stop == next_start for (_, stop), (next_start, _) in zip(bounds, bounds[1:]))
    for start, stop in bounds:
        members = extents[start:stop]
        assert len(members) == 1 or len(members) * members[-1] ** 2 <= 100
    assert size_groups([], 100, 20) == [(0, 0)]


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae", "flomo"])
def test_flow_standardize_adds_a_closed_form_stage(name: str) -> None:
    batch = crowd_batch(40, neighbours=3)
    plain = _model(name)
    model = _model(name, flow_standardize=True)
    assert model.stages == (*plain.stages[:-1], "standardize", "flow")
    assert "standardize" in model.closed_form_stages and model.stage_parameters("standardize") == []
    with pytest.raises(ValueError, match="unknown stage"):
        plain.stage_loss("standardize", batch)
    model.fit_stage("standardize", batch)
    targets = model.targets(model.normalize(batch))
    assert torch.allclose(model.flow.shift, targets.mean(0), atol=1e-5)
    assert torch.allclose(model.flow.scale, targets.std(0), atol=1e-5)
    # The stage's loss is the NLL of the fitted diagonal Gaussian.
    gaussian = torch.distributions.Normal(targets.mean(0), targets.std(0))
    expected = -gaussian.log_prob(targets).sum(-1).mean()
    assert torch.allclose(model.stage_loss("standardize", batch), expected, atol=1e-4)


@pytest.mark.parametrize("name", ["trajflow", "trajflow-no-ae", "flomo"])
def test_fixed_targets_are_what_each_step_would_compute(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Training computes TrajFlow's frozen-autoencoder latents once per flow stage (in chunks); a batch carrying
    them gives the loss and gradients the step computes itself. The other families have none (FloMo's targets
    are noisy and rescaled at every step)."""
    model = _model(name).train()
    batch = crowd_batch(37, neighbours=5)
    monkeypatch.setattr(type(model), "TARGET_CHUNK", 16, raising=False)
    fixed = model.fixed_targets("flow", batch)
    if name != "trajflow":
        assert fixed is None
        return
    assert model.fixed_targets("autoencoder", batch) is None
    carried = replace(batch, targets=fixed)
    torch.manual_seed(1)
    own = model.stage_loss("flow", batch.index(slice(3, 20)))
    torch.manual_seed(1)
    cached = model.stage_loss("flow", carried.index(slice(3, 20)))
    assert torch.allclose(cached, own, rtol=1e-6)
    assert carried.index(slice(3, 20)).targets.shape == (17, model.config.latent_dim)
    assert carried.without_future().targets is None


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_packed_groups_give_the_one_group_readout(aggregate: str) -> None:
    """The CPU path (nodes of all groups packed in one tensor, edges per group) reads out what the dense and
    the sparse rounds over the whole batch read out, gradients included (float64)."""
    torch.manual_seed(0)
    gnn = SocialGNN(aggregate=aggregate).double()
    batch, n = 11, 7
    mask = torch.rand(batch, n) < torch.linspace(0.1, 0.9, batch)[:, None]
    mask[:, 0] = True
    onehot = torch.nn.functional.one_hot(torch.randint(0, 5, (batch, n)), 5).double()
    x0, pos0 = torch.randn(batch, n, 32, dtype=torch.float64), 3 * torch.randn(batch, n, 2, dtype=torch.float64)
    extent = (mask * torch.arange(1, n + 1)).amax(dim=1)
    order = torch.argsort(extent, stable=True)
    ends = extent[order].tolist()
    shapes = [(stop - start, max(1, ends[stop - 1])) for start, stop in size_groups(ends, 3 * n * n, 3 * n * n)]
    assert len(shapes) > 2
    results = []
    for readout in (lambda *a: gnn._grouped_rounds(*a, order, shapes), lambda *a: gnn._readout(*a, True),
                    lambda *a: gnn._readout(*a, False)):
        x, pos = x0.clone().requires_grad_(True), pos0.clone().requires_grad_(True)
        gnn.zero_grad()
        out = readout(x, pos, onehot, mask)
        (out ** 2).sum().backward()
        results.append((out.detach(), x.grad[mask], pos.grad[mask], gnn.msg_edge.weight.grad.clone(),
                        gnn.update[0][0].weight.grad.clone()))
    for result in results[1:]:
        for value, expected in zip(result, results[0]):
            assert torch.allclose(value, expected, rtol=1e-9, atol=1e-10)


def test_the_compiled_edge_block_gives_the_eager_rounds(monkeypatch: pytest.MonkeyPatch) -> None:
    """SocialGNN.compile_edges (traced forward and backward graphs, dynamic shapes) gives the eager encodings and
    gradients on groups of several sizes; groups of few edges, and rounds without gradients, stay eager; drop_compiled goes back to eager everywhere (float64)."""
    monkeypatch.setattr(compiled_module, "COMPILE_BACKEND", "aot_eager")
    torch.manual_seed(0)
    gnn = SocialGNN().double()
    batch, n = 17, 8
    mask = torch.rand(batch, n) < torch.linspace(0.05, 0.9, batch)[:, None]
    mask[:, 0] = True
    mask[0, 1:] = False                                                          # alone: a group of extent 1
    past = 3 * torch.randn(batch, n, 8, 2, dtype=torch.float64)
    valid = torch.ones(batch, n, 8, dtype=torch.bool) & mask[..., None]
    types = torch.randint(0, 5, (batch, n))
    monkeypatch.setattr(SocialGNN, "GROUP_EDGES", 3 * n * n)                     # groups of 3 or fewer
    monkeypatch.setattr(SocialGNN, "GROUP_PADDING", 3 * n * n)
    monkeypatch.setattr(SocialGNN, "COMPILED_MIN_EDGES", 12)                    # small groups stay eager

    def encode() -> tuple[torch.Tensor, ...]:
        leaf = past.clone().requires_grad_(True)
        gnn.zero_grad()
        out = gnn(leaf, valid, mask, types)
        (out ** 2).sum().backward()
        return out.detach(), leaf.grad, gnn.msg_edge.weight.grad.clone(), gnn.msg_sender[0].weight.grad.clone()

    eager = encode()
    assert gnn.compile_edges() is None
    shapes = []
    compiled = gnn._compiled_pool
    gnn._compiled_pool = lambda *inputs: shapes.append(tuple(inputs[0].shape[:2])) or compiled(*inputs)
    for value, expected in zip(encode(), eager):
        assert torch.allclose(value, expected, rtol=1e-10, atol=1e-12)
    assert shapes and all(members * extent * extent > 12 for members, extent in shapes)
    assert len(set(shapes)) > 1                                                  # one compiled block, many shapes
    calls = len(shapes)
    with torch.no_grad():
        gnn(past, valid, mask, types)
    gnn.drop_compiled()
    encode()
    assert len(shapes) == calls


def test_the_written_out_edge_backward_is_autograds_when_positions_are_data() -> None:
    """pool_edges_to_compile's own backward (as training takes it: distances without gradients, padding senders
    at -inf) gives autograd's gradients of pool_edges for the receiver and sender terms and the distance weight."""
    generator = torch.Generator().manual_seed(0)
    members, extent, width = 3, 7, 5
    pos = torch.randn(members, extent, 2, generator=generator, dtype=torch.float64)
    dist = torch.sqrt(((pos[:, :, None] - pos[:, None]) ** 2).sum(-1, keepdim=True) + 1e-12)
    to_a = torch.randn(members, extent, width, generator=generator, dtype=torch.float64)
    from_b = torch.randn(members, extent, width, generator=generator, dtype=torch.float64)
    from_b[:, extent - 2:] = float("-inf")
    w_dist = torch.randn(width, generator=generator, dtype=torch.float64)
    grad = torch.randn(members, extent, width, generator=generator, dtype=torch.float64)
    results = []
    for pool in (pool_edges, pool_edges_to_compile):
        leaves = [t.clone().requires_grad_(True) for t in (to_a, from_b, w_dist)]
        out = pool(leaves[0], leaves[1], dist, leaves[2])
        results.append((out.detach(), *torch.autograd.grad(out, leaves, grad)))
    for value, expected in zip(*reversed(results)):
        assert torch.allclose(value, expected, rtol=1e-12, atol=1e-12)
    assert torch.count_nonzero(results[1][2][:, extent - 2:]) == 0                # padding senders get nothing


def test_a_gnn_that_cannot_compile_says_why_and_its_model_stays_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    without_compiler(monkeypatch)
    gnn = SocialGNN()
    assert gnn.compile_edges() == NO_COMPILER
    assert gnn._compiled_pool is None
    model = _model("trajflow")
    monkeypatch.setattr(type(model.flow), "compile_training", lambda flow, rows: setattr(flow, "_compiled", len))
    assert model.compile_stage("flow", 8) == NO_COMPILER
    assert model.flow._compiled is None                     # all or nothing: the flow compiled, then dropped


def test_each_component_starts_from_its_own_random_stream() -> None:
    """Changing one component's size leaves every other component's initial weights as they were; the global
    seed still decides the model (issue 28: ablations compare what they say they compare)."""
    def weights(seed: int, **kwargs: object) -> dict[str, torch.Tensor]:
        torch.manual_seed(seed)
        return build_model(ModelConfig(name="trajflow", **kwargs), SPEC).state_dict()

    base, wider_flow, other_ae = weights(0), weights(0, flow_hidden=[48] * 5), weights(0, ae_embed=24)
    for name, value in base.items():
        if not name.startswith("flow."):
            assert torch.equal(value, wider_flow[name]), name
        if not name.startswith("autoencoder."):
            assert torch.equal(value, other_ae[name]), name
    assert not torch.equal(base["context.past.embed.weight"], weights(1)["context.past.embed.weight"])
    again = weights(0)
    assert all(torch.equal(value, again[name]) for name, value in base.items())
