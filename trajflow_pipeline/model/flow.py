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
* The spline (:class:`RationalQuadraticSpline`) is zuko's ``MonotonicRQSTransform`` re-expressed with fewer,
  larger tensor operations (sampling 100 futures for 1000 agents evaluates ten million splines per layer).
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
from zuko.transforms import CouplingTransform, PermutationTransform


class RationalQuadraticSpline(Transform):
    """Monotonic rational-quadratic splines on [-B, B] with identity tails, applied element-wise to vectors.

    Mathematically identical to zuko's ``MonotonicRQSTransform`` (same unconstrained parameterisation: soft-clamped
    bin widths / heights through a softmax, knot derivatives through exp, minimum slope ``slope``), but computed
    from one parameter tensor with fewer, larger tensor operations, and with an inverse that returns its
    log-determinant without a second bin search. Acts on the last dimension as a whole (event dim 1): the log-
    determinants are summed over it.

    ``phi`` has shape (..., D, 3K - 1): K widths, K heights, K - 1 inner derivatives per element.
    """

    domain = constraints.real_vector
    codomain = constraints.real_vector
    bijective = True
    sign = +1

    def __init__(self, phi: Tensor, bound: float = 5.0, slope: float = 1e-3) -> None:
        super().__init__()
        bins = (phi.shape[-1] + 1) // 3
        if bins < 2:
            raise ValueError("a rational-quadratic spline needs at least 2 bins")
        self.limit = abs(math.log(slope))
        # zuko's soft clamp of the width / height logits, u / (1 + |2u / log slope|), bounds them to
        # (-limit/2, limit/2), so exp needs no max-shift (softmax = exp / sum).
        widths_heights = phi[..., :2 * bins]
        expd = (widths_heights / widths_heights.abs().mul_(2 / self.limit).add_(1)).exp()
        cumulative = expd.unflatten(-1, (2, bins)).cumsum(-1)                                  # (..., 2, K)
        knots = (cumulative * ((2 * bound) / cumulative[..., -1:])).sub_(bound)
        # Knots 1..K of each axis (knot 0 is -B).
        self.horizontal, self.vertical = knots.unbind(-2)
        # Unconstrained derivatives at the K - 1 inner knots (1 at both ends); only the two around each value's
        # bin are ever used, so their clamp and exp are applied after the lookup.
        self.raw_derivatives = phi[..., 2 * bins:]
        self.bound = bound
        self.bins = bins

    def _locate(self, value: Tensor, knots: Tensor) -> tuple[Tensor, ...]:
        """Bin of each value among `knots` and the bin's corner values; `outside` marks values not in (-B, B].

        The first bin's lower knot (-B) and the end derivatives (1) are filled in after the lookups, with masked
        fills of scalars: cheaper than padding the knot tensors, which for sampling are large."""
        bins = self.bins
        k = (knots[..., :bins - 1] < value[..., None]).sum(-1, keepdim=True)                 # bin in [0, K-1]
        below = (k - 1).clamp_(min=0)
        edges = torch.cat((below, k), dim=-1)
        x0, x1 = self.horizontal.gather(-1, edges).unbind(-1)
        y0, y1 = self.vertical.gather(-1, edges).unbind(-1)
        raw = self.raw_derivatives.gather(-1, torch.cat((below, k.clamp(max=bins - 2)), dim=-1))
        d0, d1 = (raw / raw.abs().mul_(1 / self.limit).add_(1)).exp().unbind(-1)   # zuko: u / (1 + |u / log slope|)
        first, last = (k == 0).squeeze(-1), (k == bins - 1).squeeze(-1)
        x0, y0 = x0.masked_fill(first, -self.bound), y0.masked_fill(first, -self.bound)
        d0, d1 = d0.masked_fill(first, 1.0), d1.masked_fill(last, 1.0)
        outside = (value <= -self.bound) | (value > self.bound)
        return outside, x0, x1, y0, y1, d0, d1

    @staticmethod
    def _log_jacobian(z: Tensor, zz: Tensor, s: Tensor, d0: Tensor, d1: Tensor) -> Tensor:
        """log dy/dx of the bin's rational quadratic at z, with zz = z (1 - z)."""
        numerator = s * s * (2 * s * zz + d0 * (1 - z) ** 2 + d1 * z * z)
        return numerator.log() - 2 * (s + (d0 + d1 - 2 * s) * zz).log()

    def call_and_ladj(self, x: Tensor) -> tuple[Tensor, Tensor]:
        outside, x0, x1, y0, y1, d0, d1 = self._locate(x, self.horizontal)
        dx, dy = x1 - x0, y1 - y0
        s = dy / dx
        z = ((x - x0) / dx).masked_fill(outside, 0.0)
        zz = z * (1 - z)
        y = y0 + dy * (s * z * z + d0 * zz) / (s + (d0 + d1 - 2 * s) * zz)
        ladj = self._log_jacobian(z, zz, s, d0, d1).masked_fill(outside, 0.0)
        return torch.where(outside, x, y), ladj.sum(-1)

    def inverse_and_ladj(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """x = f^-1(y) and log |det J_{f^-1}(y)| (summed over the last dimension)."""
        outside, x0, x1, y0, y1, d0, d1 = self._locate(y, self.vertical)
        dx, dy = x1 - x0, y1 - y0
        s = dy / dx
        rel = (y - y0).masked_fill(outside, 0.0)
        t = d0 + d1 - 2 * s
        a = dy * (s - d0) + rel * t
        b = dy * d0 - rel * t
        c = -s * rel
        z = 2 * c / (-b - (b * b - 4 * a * c).clamp(min=0).sqrt())
        x = x0 + z * dx
        ladj = self._log_jacobian(z, z * (1 - z), s, d0, d1).neg_().masked_fill(outside, 0.0)
        return torch.where(outside, y, x), ladj.sum(-1)

    def _call(self, x: Tensor) -> Tensor:
        return self.call_and_ladj(x)[0]

    def _inverse(self, y: Tensor) -> Tensor:
        return self.inverse_and_ladj(y)[0]

    def log_abs_det_jacobian(self, x: Tensor, y: Tensor) -> Tensor:
        return self.call_and_ladj(x)[1]


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
        z, ladj = self.transform(context).call_and_ladj(self._in(x))
        return standard_normal_log_prob(z) + ladj + self._log_scale()

    def to_base(self, x: Tensor, context: Tensor) -> Tensor:
        """The normalising direction x -> z."""
        return self.transform(context)(self._in(x))

    def from_base(self, z: Tensor, context: Tensor) -> Tensor:
        """The generative direction z -> x; z may carry leading sample dimensions (..., B, D)."""
        return self._out(self.transform(context).inv(z))

    def sample(self, context: Tensor, n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """n samples per context row and their log-densities: (n, B, D) and (n, B)."""
        return self.from_noise(self.noise(context, n, generator), context)

    def noise(self, context: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
        """n base draws z ~ N(0, I) per context row: (n, B, D)."""
        return torch.randn((n, context.shape[0], self.features), generator=generator, device=context.device,
                           dtype=context.dtype)

    def from_noise(self, z: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        """The samples x (n, B, D) that base draws z (n, B, D) map to, and their log-densities (n, B)."""
        u, ladj = self.transform(context).inv.call_and_ladj(z)
        return self._out(u), standard_normal_log_prob(z) - ladj + self._log_scale()


def standard_normal_log_prob(z: Tensor) -> Tensor:
    """log N(z; 0, I) summed over the last dimension."""
    return -0.5 * (z ** 2).sum(-1) - 0.5 * z.shape[-1] * math.log(2 * math.pi)
