"""Conditional normalizing flow: coupling layers with rational-quadratic splines, built on zuko.

Structure (paper III-A, SPEC section 6): ``layers`` coupling transforms (zuko ``GeneralCouplingTransform`` with a
``MonotonicRQSTransform`` of ``bins`` bins on [-B, B], identity tails, B = tail bound), each conditioner an MLP with
the given hidden widths and ELU, fixed random permutations between consecutive layers, base N(0, I).

Three refinements over the stock zuko classes, none changing the maths:

* The conditioner's first linear layer is split into the part acting on the pass-through features and the part
  acting on the context, and the context part is evaluated once per problem. When sampling n futures per
  problem the context is therefore not repeated n times through the widest matrix product.
* Sampling (inverse direction) with log-densities evaluates each conditioner exactly once per layer; zuko's
  generic inverse would call it a second time for the log-determinant.
* The spline (:class:`~.spline.RationalQuadraticSpline`, in :mod:`.spline`) is zuko's ``MonotonicRQSTransform``
  re-expressed with fewer, larger tensor operations (sampling 100 futures for 1000 agents evaluates ten million
  splines per layer).
* Sampling (:meth:`ConditionalSplineFlow.from_noise`) runs the couplings' inverse on the draws stored as columns
  (:meth:`SplineCoupling.inverse_columns`, :func:`spline_inverse_columns`), so that every operation runs over
  long contiguous rows instead of groups of 8 to 32 values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import torch
from torch import Tensor, nn
from torch.distributions import Transform, constraints
from torch.nn import functional as F
from zuko.flows.coupling import GeneralCouplingTransform
from zuko.lazy import LazyComposedTransform, UnconditionalTransform
from zuko.nn import Linear as ZukoLinear
from zuko.transforms import CouplingTransform, PermutationTransform

from .compiled import compile_probed
from .spline import RationalQuadraticSpline, spline_forward, spline_inverse_columns


class _SinglePassCouplingInverse(Transform):
    """Inverse of a spline coupling transform: one conditioner pass and one bin search per call."""

    domain = constraints.real_vector
    codomain = constraints.real_vector
    bijective = True

    def __init__(self, forward: CouplingTransform) -> None:
        super().__init__()
        self._forward = forward

    @property
    def inv(self) -> Transform:
        return self._forward

    def _call(self, y: Tensor) -> Tensor:
        return self.call_and_ladj(y)[0]

    def _inverse(self, x: Tensor) -> Tensor:
        return self._forward(x)

    def log_abs_det_jacobian(self, y: Tensor, x: Tensor) -> Tensor:
        return self.call_and_ladj(y)[1]

    def call_and_ladj(self, y: Tensor) -> tuple[Tensor, Tensor]:
        y_a, y_b = self._forward.split(y)
        x_b, ladj = self._forward.meta(y_a).inverse_and_ladj(y_b)
        return self._forward.merge(y_a, x_b, y.shape), ladj


class _Coupling(CouplingTransform):
    """zuko's coupling transform with the single-pass inverse above.

    When the pass-through features are the leading block (the layout :class:`ConditionalSplineFlow` uses, with
    permutations in between), splitting is slicing and merging a concatenation instead of gathers and scatters.
    """

    def __init__(self, meta: Callable[[Tensor], Transform], mask: Tensor) -> None:
        super().__init__(meta, mask)
        self.leading = int(mask.sum()) if bool(mask[:int(mask.sum())].all()) else 0

    def split(self, x: Tensor) -> tuple[Tensor, Tensor]:
        if self.leading:
            return x[..., :self.leading], x[..., self.leading:]
        return super().split(x)

    def merge(self, x_a: Tensor, x_b: Tensor, shape: torch.Size) -> Tensor:
        if self.leading:
            return torch.cat((x_a, x_b), dim=-1)
        return super().merge(x_a, x_b, shape)

    @property
    def inv(self) -> Transform:
        return _SinglePassCouplingInverse(self)


class SplineCoupling(GeneralCouplingTransform):
    """A conditional rational-quadratic spline coupling layer (true coupling: one conditioner pass per direction).

    A zuko ``GeneralCouplingTransform`` whose univariate transformation is :class:`RationalQuadraticSpline`; the
    conditioner (``hyper``) is zuko's MLP over [pass-through half, context].
    """

    def __init__(self, features: int, context: int, mask: Tensor, bins: int, bound: float,
                 hidden: tuple[int, ...]) -> None:
        super().__init__(features=features, context=context, mask=mask,
                         univariate=partial(RationalQuadraticSpline, bound=bound),
                         shapes=[(3 * bins - 1,)], hidden_features=list(hidden), activation=nn.ELU)
        self.n_pass = int(mask.sum())
        if not bool(mask[:self.n_pass].all()):
            raise ValueError("SplineCoupling passes the leading features through: mask must be True then False")
        self.bound = bound
        self.limit = RationalQuadraticSpline(torch.zeros(3 * bins - 1), bound).limit

    def meta(self, c: Tensor | None, x: Tensor) -> Transform:
        """Spline of the transformed half given the pass-through half `x` (..., B, d_a) and context c (B, C)."""
        first = self.hyper[0]
        h = F.linear(x, first.weight[:, :self.n_pass], first.bias)
        if c is not None:
            h = h + F.linear(c, first.weight[:, self.n_pass:])
        for layer in list(self.hyper)[1:]:
            h = layer(h)
        return self.univariate(h.unflatten(-1, (-1, self.total)))

    def forward(self, c: Tensor | None = None) -> Transform:
        return _Coupling(partial(self.meta, c), self.mask)

    def call_rows(self, x: Tensor, offset: Tensor) -> tuple[Tensor, Tensor]:
        """The coupling's forward direction on rows x (B, D): y and log |dy/dx| (B,), given `offset` (B, H), its
        conditioner's first layer bias plus context part (computed for all couplings at once by
        :meth:`ConditionalSplineFlow.log_prob`). The same function as ``self(c)``'s transform."""
        x_a, x_b = x[:, :self.n_pass], x[:, self.n_pass:]
        first, *rest = self.hyper
        h = torch.addmm(offset, x_a, first.weight[:, :self.n_pass].t())
        for layer in rest:
            h = layer(h)
        y_b, ladj = spline_forward(h.view(*x_b.shape, self.total), x_b, self.bound, self.limit)
        return torch.cat((x_a, y_b), dim=-1), ladj

    def inverse_columns(self, y: Tensor, c: Tensor | None, n: int) -> tuple[Tensor, Tensor]:
        """The inverse of the coupling, x and log |dx/dy| (summed per vector), on vectors stored column-wise:
        y (D, n * B) holds draw j of problem i in column j * B + i, its context c (B, C) is shared by the n draws.

        The same function as the transform's ``inv`` (one conditioner pass) to float rounding, with the
        conditioner evaluated as products W @ h over columns: each hidden activation carries a row of ones below
        it, so that a layer's bias is one more column of its weights (no broadcast bias pass over the outputs),
        and the last layer's rows are reordered so that the spline parameters come out as the rows that
        :func:`spline_inverse_columns` reads (:meth:`_spline_rows`)."""
        y_a, y_b = y[:self.n_pass], y[self.n_pass:]
        first, *rest = self.hyper
        h = _with_ones_row(first.weight.shape[0], y.shape[1], y)
        torch.mm(first.weight[:, :self.n_pass], y_a, out=h[:-1])                               # (H, n * B)
        if c is None:
            h[:-1].add_(first.bias[:, None])
        else:
            offset = torch.addmm(first.bias, c, first.weight[:, self.n_pass:].t())             # (B, H)
            h[:-1].view(offset.shape[1], n, c.shape[0]).add_(offset.t().unsqueeze(1))
        for index, layer in enumerate(rest):
            if isinstance(layer, (nn.Linear, ZukoLinear)):
                weight = torch.cat((layer.weight, layer.bias[:, None]), dim=1)                 # (out, in + 1)
                if index == len(rest) - 1:
                    phi = torch.mm(self._spline_rows(weight), h)
                else:
                    h_next = _with_ones_row(weight.shape[0], h.shape[1], h)
                    torch.mm(weight, h, out=h_next[:-1])
                    h = h_next
            elif isinstance(layer, nn.ELU):
                _elu_(h[:-1], layer.alpha)
            else:
                h[:-1] = layer(h[:-1])                                  # any other element-wise module
        x_b, ladj = spline_inverse_columns(phi.view(phi.shape[0] // y_b.shape[0], y_b.numel()), y_b.reshape(-1),
                                           self.bound, self.limit)
        return torch.cat((y_a, x_b.view(y_b.shape))), ladj.view(y_b.shape).sum(0)

    def _spline_rows(self, weight: Tensor) -> Tensor:
        """The last conditioner layer's rows, (element d, parameter p) -> (parameter p, element d), with a row of
        zeros before and after the inner derivatives: the layout :func:`spline_inverse_columns` reads."""
        elements, bins = weight.shape[0] // self.total, (self.total + 1) // 3
        order = torch.arange(weight.shape[0], device=weight.device).view(elements, self.total).t()
        weight = weight[order]                                                 # (parameter, element, in)
        pad = weight.new_zeros(1, *weight.shape[1:])
        return torch.cat((weight[:2 * bins], pad, weight[2 * bins:], pad)).flatten(0, 1)


def _elu_(x: Tensor, alpha: float) -> Tensor:
    """F.elu(x, alpha) in place, as max(x, 0) + alpha (exp(min(x, 0)) - 1) with exp as exp2: the same function to
    float rounding (largest absolute error 6.7e-8 against float64's ELU on [-30, 5], F.elu's 6.0e-8) and twice as
    fast on a CPU, where F.elu evaluates expm1 (a (32, 10,000) block, 1 thread: 790 -> 360 us; by that timing the
    conditioners' 500 ELUs of 100 draws for 1,000 agents had taken about 0.4 s of 2.2-2.3 s at one thread)."""
    negative = x.clamp(max=0).mul_(_LOG2E).exp2_().sub_(1)
    return x.clamp_(min=0).add_(negative, alpha=alpha)


_LOG2E = 1 / math.log(2)


def _with_ones_row(rows: int, columns: int, like: Tensor) -> Tensor:
    """An uninitialised (rows + 1, columns) tensor whose last row is ones (the bias row of the next product)."""
    out = like.new_empty(rows + 1, columns)
    out[rows] = 1
    return out


class ConditionalSplineFlow(nn.Module):
    """p(x | context) over `features`-dimensional vectors; base N(0, I).

    With ``standardize`` the couplings see u = (x - shift) / scale, a fixed per-feature affine map whose shift and
    scale are set once from training data (:meth:`fit_standardization`, the mean and standard deviation) and
    stored with the weights. The splines act on [-B, B], so without it their resolution depends on the units of
    x: an autoencoder latent within +-4 uses one or two of 8 bins on [-15, 15]. Densities stay densities of x
    (the map's log-determinant is included).
    """

    def __init__(self, features: int, context: int, *, layers: int = 10, bins: int = 8, tail_bound: float = 15.0,
                 hidden: tuple[int, ...] = (32, 32, 32, 32, 32), seed: int = 0, standardize: bool = False) -> None:
        super().__init__()
        if features < 2:
            raise ValueError("a coupling flow needs at least 2 features")
        self.features = features
        self.context = context
        self.standardize = standardize
        if standardize:
            self.register_buffer("shift", torch.zeros(features))
            self.register_buffer("scale", torch.ones(features))
        generator = torch.Generator().manual_seed(seed)
        mask = torch.arange(features) < features // 2
        parts: list[nn.Module] = []
        for index in range(layers):
            if index > 0:
                order = torch.randperm(features, generator=generator)
                parts.append(UnconditionalTransform(PermutationTransform, order, buffer=True))
            parts.append(SplineCoupling(features, context, mask.clone(), bins, tail_bound, hidden))
        # Maps data x to the base variable z.
        self.transform = LazyComposedTransform(*parts)
        #: the compiled log-density with gradients of `_compiled_rows` rows (:meth:`compile_training`), or None
        self._compiled: Callable[[Tensor, Tensor], Tensor] | None = None
        self._compiled_rows = 0

    def fit_standardization(self, x: Tensor) -> None:
        """Set the input map from training vectors x (N, D): shift = mean, scale = standard deviation (a feature
        that never varies keeps scale 1, so it is only shifted)."""
        if not self.standardize:
            raise ValueError("this flow was built without standardize=True")
        if x.ndim != 2 or x.shape[1] != self.features or x.shape[0] < 2:
            raise ValueError(f"standardization needs at least 2 vectors of {self.features} features, got "
                             f"{tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError("standardization got non-finite training vectors")
        x = x.double()
        std = x.std(dim=0)
        self.shift.copy_(x.mean(dim=0).to(self.shift))
        self.scale.copy_(torch.where(std > 1e-6, std, torch.ones_like(std)).to(self.scale))

    def standardization_log_prob(self, x: Tensor) -> Tensor:
        """log N(x; shift, diag(scale^2)) (B,): the diagonal Gaussian the standardization alone describes, the
        baseline the couplings improve on (N(0, I) without a standardization)."""
        return standard_normal_log_prob(self._in(x)) + self._log_scale()

    def _log_scale(self) -> Tensor | float:
        """log |det| of the standardizing map x -> u (0 without one)."""
        return -self.scale.log().sum() if self.standardize else 0.0

    def _in(self, x: Tensor) -> Tensor:
        return (x - self.shift) / self.scale if self.standardize else x

    def _out(self, u: Tensor) -> Tensor:
        return u * self.scale + self.shift if self.standardize else u

    def log_prob(self, x: Tensor, context: Tensor) -> Tensor:
        """log p(x | context) in nats: x (B, D), context (B, C) -> (B,)."""
        if x.dim() == 2 and context.dim() == 2:
            if self._compiled is not None and x.shape[0] == self._compiled_rows and torch.is_grad_enabled():
                return self._compiled(x, context)
            return self._log_prob_rows(x, context)
        z, ladj = self.transform(context).call_and_ladj(self._in(x))
        return standard_normal_log_prob(z) + ladj + self._log_scale()

    def _log_prob_rows(self, x: Tensor, context: Tensor) -> Tensor:
        """log_prob on rows x (B, D), context (B, C), through :meth:`_to_base_rows`."""
        z, ladj = self._to_base_rows(self._in(x), context)
        return standard_normal_log_prob(z) + ladj + self._log_scale()

    def compile_training(self, rows: int) -> str | None:
        """Compile the log-density with gradients for batches of `rows` rows (torch.compile, that one shape): what a
        training step of the flow computes, evaluated afterwards by generated fused kernels (the same function to
        float rounding). Other batch sizes and everything without gradients stay eager.

        A flow step at batch 128 is bound by the number of its small operations, so this pays on CPUs: measured on
        the 2-core Xeon, 1 thread, forward and backward 39.6 -> 14.8 ms, for a one-off 117 s (27 s with inductor's
        cache from an earlier run). The compiled function is tried here once, forward and backward, on seeded
        random inputs, so that a machine that cannot compile (no C++ compiler) finds out now: returns None when
        compiled, else the reason, and the flow stays eager."""
        parameter = next(self.parameters())
        generator = torch.Generator(parameter.device).manual_seed(0)
        x = torch.randn(rows, self.features, generator=generator, device=parameter.device, dtype=parameter.dtype)
        context = torch.randn(rows, self.context, generator=generator, device=parameter.device,
                              dtype=parameter.dtype, requires_grad=True)
        trained = [p for p in self.parameters() if p.requires_grad]
        compiled, failure = compile_probed(
            self._log_prob_rows, lambda log_prob: torch.autograd.grad(log_prob(x, context).sum(), [context, *trained]),
            dynamic=False)
        if compiled is not None:
            self._compiled, self._compiled_rows = compiled, rows
        return failure

    def drop_compiled(self) -> None:
        """Back to the eager log-density for every batch."""
        self._compiled, self._compiled_rows = None, 0

    def _to_base_rows(self, u: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        """The normalising direction u -> z with its log-determinant (B,) on rows u (B, D), context (B, C).

        The same function as ``self.transform(context).call_and_ladj(u)`` (tested), evaluated directly for
        training, where a step is bound by the number of operations: the context's part of every coupling's
        first conditioner layer is one product for all couplings, permutations are column gathers, and no
        transform objects are built per call."""
        parts = self.transform.transforms
        couplings = [part for part in parts if isinstance(part, SplineCoupling)]
        firsts = [coupling.hyper[0] for coupling in couplings]
        weight = torch.cat([first.weight[:, coupling.n_pass:] for coupling, first in zip(couplings, firsts)])
        offsets = torch.addmm(torch.cat([first.bias for first in firsts]), context, weight.t())
        offsets = offsets.split([first.out_features for first in firsts], dim=1)
        ladj, index = u.new_zeros(u.shape[0]), 0
        for part in parts:
            if isinstance(part, SplineCoupling):
                u, part_ladj = part.call_rows(u, offsets[index])
                ladj, index = ladj + part_ladj, index + 1
            else:
                u = u.index_select(1, _permutation(part).order)
        return u, ladj

    def to_base(self, x: Tensor, context: Tensor) -> Tensor:
        """The normalising direction x -> z."""
        return self.transform(context)(self._in(x))

    def from_base(self, z: Tensor, context: Tensor) -> Tensor:
        """The generative direction z -> x; z may carry leading sample dimensions (..., B, D)."""
        return self._out(self.transform(context).inv(z))

    def sample(self, context: Tensor, n: int, generator: torch.Generator | None = None,
               temperature: float = 1.0) -> tuple[Tensor, Tensor]:
        """n samples per context row and their log-densities: (n, B, D) and (n, B); with a base N(0, T^2 I)."""
        return self.from_noise(self.noise(context, n, generator, temperature), context, temperature)

    def noise(self, context: Tensor, n: int, generator: torch.Generator | None = None,
              temperature: float = 1.0) -> Tensor:
        """n base draws z ~ N(0, T^2 I) per context row: (n, B, D) (T = `temperature`; the same stream for any T)."""
        z = torch.randn((n, context.shape[0], self.features), generator=generator, device=context.device,
                        dtype=context.dtype)
        return z if temperature == 1.0 else z * temperature

    @torch.no_grad()
    def from_noise(self, z: Tensor, context: Tensor, temperature: float = 1.0) -> tuple[Tensor, Tensor]:
        """The samples x (n, B, D) that base draws z (n, B, D) map to, and their log-densities (n, B) under the
        flow with the base N(0, T^2 I) (T = `temperature`).

        The transform's inverse (``from_base``) evaluated column-wise (:meth:`SplineCoupling.inverse_columns`):
        the draws are stored as columns of one (D, n * B) tensor through all couplings and permutations, so every
        operation runs over long contiguous rows; x is returned as a (n, B, D) view of it. Without gradients."""
        n, size, features = z.shape
        columns = z.permute(2, 0, 1).reshape(features, n * size)              # draw j of problem i: column j B + i
        ladj = z.new_zeros(n * size)
        for part in reversed(self.transform.transforms):
            if isinstance(part, SplineCoupling):
                columns, part_ladj = part.inverse_columns(columns, context, n)
                ladj = ladj + part_ladj
            else:
                columns = columns[torch.argsort(_permutation(part).order)]
        if self.standardize:
            columns = columns * self.scale[:, None] + self.shift[:, None]
        log_lik = scaled_normal_log_prob(z, temperature) - ladj.view(n, size) + self._log_scale()
        return columns.view(features, n, size).permute(1, 2, 0), log_lik


def _permutation(part: nn.Module) -> PermutationTransform:
    """The fixed permutation a non-coupling part of the flow stands for."""
    permutation = part()
    if not isinstance(permutation, PermutationTransform):
        raise TypeError(f"unexpected flow part {permutation!r}")
    return permutation


def standard_normal_log_prob(z: Tensor) -> Tensor:
    """log N(z; 0, I) summed over the last dimension."""
    return -0.5 * (z ** 2).sum(-1) - 0.5 * z.shape[-1] * math.log(2 * math.pi)


def scaled_normal_log_prob(z: Tensor, scale: float) -> Tensor:
    """log N(z; 0, scale^2 I) summed over the last dimension (standard_normal_log_prob's bits at scale 1)."""
    if scale == 1.0:
        return standard_normal_log_prob(z)
    return standard_normal_log_prob(z / scale) - z.shape[-1] * math.log(scale)
