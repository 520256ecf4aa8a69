"""The conditional coupling spline flow: invertibility, exact densities, zuko equivalence, one pass per layer."""

from __future__ import annotations

import pytest
import torch
from compile_fakes import NO_COMPILER, without_compiler
from zuko.flows.coupling import GeneralCouplingTransform
from zuko.transforms import MonotonicRQSTransform

from trajflow_pipeline.model import compiled as compiled_module
from trajflow_pipeline.model.flow import ConditionalSplineFlow, SplineCoupling, _elu_
from trajflow_pipeline.model.spline import RationalQuadraticSpline, spline_inverse_columns


def _flow(features: int = 6, context: int = 4, sharpen: float = 1.0, seed: int = 0,
          layers: int = 10) -> ConditionalSplineFlow:
    torch.manual_seed(seed)
    flow = ConditionalSplineFlow(features, context, layers=layers, bins=8, tail_bound=15.0, seed=seed)
    with torch.no_grad():
        for module in flow.modules():
            if isinstance(module, SplineCoupling):
                module.hyper[-1].weight.mul_(sharpen)
                module.hyper[-1].bias.normal_(0, sharpen * 0.3)
    return flow.double()


def test_structure_is_ten_coupling_layers_with_permutations() -> None:
    flow = ConditionalSplineFlow(20, 96)
    couplings = [m for m in flow.modules() if isinstance(m, SplineCoupling)]
    assert len(couplings) == 10 and all(isinstance(m, GeneralCouplingTransform) for m in couplings)
    hidden = [layer.weight.shape[0] for layer in couplings[0].hyper if hasattr(layer, "weight")]
    assert hidden == [32, 32, 32, 32, 32, 10 * 23]
    assert any(isinstance(layer, torch.nn.ELU) for layer in couplings[0].hyper)
    assert len(flow.transform.transforms) == 19   # couplings with a permutation between each pair


def test_inverse_of_forward_is_identity() -> None:
    flow = _flow(sharpen=3.0)
    x = torch.randn(256, 6, dtype=torch.float64) * 6
    c = torch.randn(256, 4, dtype=torch.float64)
    z = flow.to_base(x, c)
    assert not torch.allclose(z, x)
    assert torch.allclose(flow.from_base(z, c), x, atol=1e-8)


def test_sample_log_lik_matches_log_prob() -> None:
    flow = _flow(sharpen=3.0)
    c = torch.randn(16, 4, dtype=torch.float64)
    x, log_lik = flow.sample(c, 7, generator=torch.Generator().manual_seed(1))
    assert x.shape == (7, 16, 6) and log_lik.shape == (7, 16)
    again = flow.log_prob(x.reshape(-1, 6), c.repeat(7, 1)).reshape(7, 16)
    assert torch.allclose(again, log_lik, atol=1e-8)


def test_log_prob_is_change_of_variables() -> None:
    flow = _flow(features=3, sharpen=3.0)
    c = torch.randn(1, 4, dtype=torch.float64)
    for point in torch.randn(5, 3, dtype=torch.float64) * 4:
        jac = torch.autograd.functional.jacobian(lambda v: flow.to_base(v[None], c)[0], point)
        z = flow.to_base(point[None], c)[0]
        expected = torch.distributions.Normal(0.0, 1.0).log_prob(z).sum() + torch.linalg.slogdet(jac)[1]
        assert torch.allclose(flow.log_prob(point[None], c)[0], expected, atol=1e-8)


def test_density_integrates_to_one_in_2d() -> None:
    flow = _flow(features=2, sharpen=2.0, seed=3, layers=4)
    c = torch.randn(1, 4, dtype=torch.float64)
    step = 0.06
    axis = torch.arange(-18.0, 18.0, step, dtype=torch.float64) + step / 2
    grid = torch.cartesian_prod(axis, axis)
    with torch.no_grad():
        density = flow.log_prob(grid, c.expand(len(grid), -1)).exp()
    assert float(density.sum() * step * step) == pytest.approx(1.0, abs=5e-3)


def test_spline_matches_zuko_monotonic_rqs() -> None:
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(50, 4, 23, generator=g, dtype=torch.float64) * 2
    x = torch.randn(50, 4, generator=g, dtype=torch.float64) * 8
    mine = RationalQuadraticSpline(phi, bound=15.0)
    theirs = MonotonicRQSTransform(phi[..., :8], phi[..., 8:16], phi[..., 16:], bound=15.0)
    y, ladj = mine.call_and_ladj(x)
    y_ref, ladj_ref = theirs.call_and_ladj(x)
    assert torch.allclose(y, y_ref, atol=1e-10) and torch.allclose(ladj, ladj_ref.sum(-1), atol=1e-8)
    back, inv_ladj = mine.inverse_and_ladj(y)
    assert torch.allclose(back, x, atol=1e-8) and torch.allclose(inv_ladj, -ladj, atol=1e-8)
    outside = torch.tensor([[20.0, -16.0, 15.5, -30.0]], dtype=torch.float64)
    assert torch.equal(RationalQuadraticSpline(phi[:1], bound=15.0).call_and_ladj(outside)[0], outside)


def test_spline_backward_is_the_derivative() -> None:
    """The written-out backward pass of the spline (phi and x, every bin, the identity tails) passes gradcheck."""
    g = torch.Generator().manual_seed(2)
    phi = (torch.randn(6, 3, 23, generator=g, dtype=torch.float64) * 2).requires_grad_()
    x = torch.randn(6, 3, generator=g, dtype=torch.float64) * 8
    x[0] = torch.tensor([20.0, -16.0, 14.9])
    assert torch.autograd.gradcheck(lambda p, v: RationalQuadraticSpline(p, bound=15.0).call_and_ladj(v),
                                    (phi, x.requires_grad_()))


def test_log_prob_on_rows_is_the_transform() -> None:
    """log_prob's direct evaluation on rows gives zuko's composed transform's values and parameter gradients."""
    flow = _flow(sharpen=3.0)
    x = torch.randn(64, 6, dtype=torch.float64) * 6
    c = torch.randn(64, 4, dtype=torch.float64)
    z_ref, ladj_ref = flow.transform(c).call_and_ladj(x)
    expected = torch.distributions.Normal(0.0, 1.0).log_prob(z_ref).sum(-1) + ladj_ref
    grads_ref = torch.autograd.grad(expected.sum(), list(flow.parameters()))
    log_prob = flow.log_prob(x, c)
    grads = torch.autograd.grad(log_prob.sum(), list(flow.parameters()))
    assert torch.allclose(log_prob, expected, atol=1e-10)
    assert all(torch.allclose(a, b, atol=1e-9) for a, b in zip(grads, grads_ref))


def test_compiled_training_is_the_eager_log_prob(monkeypatch: pytest.MonkeyPatch) -> None:
    """compile_training's log-density (traced forward and backward graphs) gives eager values and gradients, and
    only for batches of its size with gradients."""
    monkeypatch.setattr(compiled_module, "COMPILE_BACKEND", "aot_eager")
    flow = _flow(sharpen=3.0, layers=3)                 # three couplings trace what ten do, in a third of the time
    x = torch.randn(32, 6, dtype=torch.float64) * 6
    c = torch.randn(32, 4, dtype=torch.float64, requires_grad=True)
    eager = flow.log_prob(x, c)
    eager_grads = torch.autograd.grad(eager.sum(), [c, *flow.parameters()])
    assert flow.compile_training(32) is None
    calls = []
    compiled = flow._compiled
    flow._compiled = lambda *inputs: calls.append(1) or compiled(*inputs)
    log_prob = flow.log_prob(x, c)
    grads = torch.autograd.grad(log_prob.sum(), [c, *flow.parameters()])
    assert calls == [1]
    assert torch.allclose(log_prob, eager, atol=1e-10)
    assert all(torch.allclose(a, b, atol=1e-9) for a, b in zip(grads, eager_grads))
    flow.log_prob(x[:5], c[:5])                                     # another batch size: eager
    with torch.no_grad():
        flow.log_prob(x, c)                                         # no gradients: eager
    flow.drop_compiled()
    flow.log_prob(x, c)
    assert calls == [1]
    other = _flow(sharpen=2.0, seed=5, layers=3)        # the same structure, other weights: its own values
    expected = other.log_prob(x, c)
    assert other.compile_training(32) is None and torch.allclose(other.log_prob(x, c), expected, atol=1e-10)


def test_a_flow_that_cannot_compile_says_why_and_stays_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    without_compiler(monkeypatch)
    flow = _flow()
    assert flow.compile_training(8) == NO_COMPILER
    x, c = torch.randn(8, 6, dtype=torch.float64), torch.randn(8, 4, dtype=torch.float64)
    assert torch.allclose(flow.log_prob(x, c), flow.transform(c).call_and_ladj(x)[1]
                          + torch.distributions.Normal(0.0, 1.0).log_prob(flow.to_base(x, c)).sum(-1))


def test_spline_inverse_on_columns_is_the_spline_inverse() -> None:
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(50, 4, 23, generator=g, dtype=torch.float64) * 2
    y = torch.randn(50, 4, generator=g, dtype=torch.float64) * 8
    y[0] = torch.tensor([-15.0, 15.0, 20.0, -16.0])                       # the bounds and the identity tails
    x_ref, ladj_ref = RationalQuadraticSpline(phi, bound=15.0).inverse_and_ladj(y)
    rows = phi.permute(2, 0, 1).reshape(23, -1)                           # (parameter, element)
    zero = torch.zeros(1, rows.shape[1], dtype=torch.float64)
    x, ladj = spline_inverse_columns(torch.cat((rows[:16], zero, rows[16:], zero)), y.flatten(), 15.0,
                                     RationalQuadraticSpline(phi, bound=15.0).limit)
    assert torch.allclose(x.view(50, 4), x_ref, atol=1e-10) and torch.allclose(ladj.view(50, 4).sum(-1), ladj_ref,
                                                                                atol=1e-10)
    assert torch.equal(x.view(50, 4)[0, 2:], y[0, 2:]) and torch.equal(ladj.view(50, 4)[0, 2:], zero[0, :2])


@pytest.mark.parametrize("standardize", [False, True])
def test_sampling_on_columns_is_the_transform_inverse(standardize: bool) -> None:
    """from_noise (the couplings evaluated column-wise) gives from_base's samples and their log-densities."""
    flow = _flow(sharpen=3.0)
    if standardize:
        flow = _standardized_flow(torch.linspace(-2, 2, 6, dtype=torch.float64),
                                  torch.linspace(0.5, 3, 6, dtype=torch.float64))[1]
    c = torch.randn(16, 4, dtype=torch.float64)
    z = torch.randn(7, 16, 6, dtype=torch.float64) * 6                    # some beyond the tail bound
    x, log_lik = flow.from_noise(z, c)
    assert torch.allclose(x, flow.from_base(z, c), atol=1e-9)
    again = flow.log_prob(x.reshape(-1, 6), c.repeat(7, 1)).reshape(7, 16)
    assert torch.allclose(log_lik, again, atol=1e-8)
    x32, log_lik32 = flow.float().from_noise(z.float(), c.float())        # float32: float rounding only
    assert torch.allclose(x32.double(), x, rtol=1e-4, atol=1e-4) and torch.allclose(log_lik32.double(), log_lik,
                                                                                   rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("alpha", [1.0, 0.3])
def test_sampling_elu_is_torch_elu(alpha: float) -> None:
    """Sampling's in-place ELU (exp as exp2) is F.elu: to float64 rounding, and within 1e-7 in float32."""
    x = torch.cat((torch.linspace(-40, 6, 100_001, dtype=torch.float64), torch.tensor([0.0, -0.0, -1e-30])))
    assert torch.allclose(_elu_(x.clone(), alpha), torch.nn.functional.elu(x, alpha), rtol=0, atol=1e-15)
    x32 = x.float()
    assert (_elu_(x32.clone(), alpha).double() - torch.nn.functional.elu(x32.double(), alpha)).abs().max() < 1e-7
    assert torch.isnan(_elu_(torch.tensor([float("nan")]), alpha)).all()


def test_tempered_sampling_draws_and_scores_with_the_wider_base() -> None:
    """At temperature T the base draws are T times the standard ones (the same stream), and each draw's
    log-density is the flow's with the base N(0, T^2 I): the fitted density's, less log N(z; 0, I), plus
    log N(z; 0, T^2 I)."""
    flow = _flow(sharpen=3.0)
    c = torch.randn(16, 4, dtype=torch.float64)
    standard = flow.noise(c, 7, torch.Generator().manual_seed(5))
    z = flow.noise(c, 7, torch.Generator().manual_seed(5), temperature=1.5)
    assert torch.equal(z, standard * 1.5)
    x, log_lik = flow.from_noise(z, c, temperature=1.5)
    assert torch.equal(x, flow.from_noise(z, c)[0])
    fitted = flow.log_prob(x.reshape(-1, 6), c.repeat(7, 1)).reshape(7, 16)
    base = torch.distributions.Normal(0.0, 1.0)
    tempered = fitted - base.log_prob(z).sum(-1) + torch.distributions.Normal(0.0, 1.5).log_prob(z).sum(-1)
    assert torch.allclose(log_lik, tempered, atol=1e-8)
    assert torch.equal(flow.from_noise(standard, c, temperature=1.0)[1], flow.from_noise(standard, c)[1])


def test_sampling_runs_each_conditioner_once() -> None:
    flow = ConditionalSplineFlow(20, 8)
    calls = []
    for module in flow.modules():
        if isinstance(module, SplineCoupling):
            module.hyper[-1].register_forward_hook(lambda *_: calls.append(1))
    with torch.no_grad():
        flow.transform(torch.randn(5, 8)).inv.call_and_ladj(torch.randn(3, 5, 20))   # zuko's inverse, in rows
    assert len(calls) == 10
    calls.clear()
    flow.log_prob(torch.randn(5, 20), torch.randn(5, 8))
    assert len(calls) == 10


def test_permutations_are_fixed_buffers() -> None:
    a, b = ConditionalSplineFlow(20, 8, seed=1), ConditionalSplineFlow(20, 8, seed=1)
    orders = [buf for name, buf in a.named_buffers() if "order" in name or name.endswith("_0")]
    assert orders, "permutations should be registered buffers"
    for (name, x), (_, y) in zip(a.named_buffers(), b.named_buffers()):
        assert torch.equal(x, y), name


def _standardized_flow(shift: torch.Tensor, scale: torch.Tensor) -> tuple[ConditionalSplineFlow,
                                                                            ConditionalSplineFlow]:
    """The same couplings with and without a standardizing input map (shift, scale)."""
    plain = _flow(sharpen=3.0)
    torch.manual_seed(0)
    standardized = ConditionalSplineFlow(6, 4, layers=10, bins=8, tail_bound=15.0, seed=0, standardize=True).double()
    standardized.load_state_dict({**plain.state_dict(), "shift": shift, "scale": scale})
    return plain, standardized


def test_standardization_is_an_exact_change_of_variables() -> None:
    shift = torch.linspace(-3, 4, 6, dtype=torch.float64)
    scale = torch.linspace(0.05, 2.0, 6, dtype=torch.float64)
    plain, standardized = _standardized_flow(shift, scale)
    c = torch.randn(64, 4, dtype=torch.float64)
    u = torch.randn(64, 6, dtype=torch.float64) * 3
    x = u * scale + shift
    assert torch.allclose(standardized.log_prob(x, c), plain.log_prob(u, c) - scale.log().sum(), atol=1e-10)
    assert torch.allclose(standardized.to_base(x, c), plain.to_base(u, c), atol=1e-10)
    assert torch.allclose(standardized.from_base(standardized.to_base(x, c), c), x, atol=1e-8)
    draws, log_lik = standardized.sample(c, 5, generator=torch.Generator().manual_seed(2))
    again = standardized.log_prob(draws.reshape(-1, 6), c.repeat(5, 1)).reshape(5, 64)
    assert torch.allclose(again, log_lik, atol=1e-8)


def test_fit_standardization_uses_training_mean_and_std() -> None:
    flow = ConditionalSplineFlow(3, 2, layers=2, standardize=True)
    x = torch.randn(500, 3) * torch.tensor([0.1, 3.0, 1.0]) + torch.tensor([5.0, -1.0, 0.0])
    x[:, 2] = 7.0                                     # a constant feature is shifted, never divided by ~0
    flow.fit_standardization(x)
    assert torch.allclose(flow.shift, x.mean(0), atol=1e-5)
    assert torch.allclose(flow.scale[:2], x[:, :2].std(0), atol=1e-5) and float(flow.scale[2]) == 1.0
    assert {"shift", "scale"} <= set(flow.state_dict())
    with pytest.raises(ValueError, match="non-finite"):
        flow.fit_standardization(torch.full((4, 3), float("nan")))
    with pytest.raises(ValueError, match="without standardize"):
        ConditionalSplineFlow(3, 2, layers=2).fit_standardization(x)
    # Without standardization the state dict is unchanged, so checkpoints written before the option still load.
    assert not {"shift", "scale"} & set(ConditionalSplineFlow(3, 2, layers=2).state_dict())
