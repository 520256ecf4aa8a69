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
* Sampling (:meth:`ConditionalSplineFlow.from_noise`) runs the couplings' inverse on the draws stored as columns
  (:meth:`SplineCoupling.inverse_columns`, :func:`spline_inverse_columns`), so that every operation runs over
  long contiguous rows instead of groups of 8 to 32 values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any
from functools import partial

import torch
from torch import Tensor, nn
from torch.distributions import Transform, constraints
from torch.nn import functional as F
from zuko.flows.coupling import GeneralCouplingTransform
from zuko.lazy import LazyComposedTransform, UnconditionalTransform
from zuko.nn import Linear as ZukoLinear
from zuko.transforms import CouplingTransform, PermutationTransform


class RationalQuadraticSpline(Transform):
    """Monotonic rational-quadratic splines on [-B, B] with identity tails, applied element-wise to vectors.

    Mathematically identical to zuko's ``MonotonicRQSTransform`` (same unconstrained parameterisation: soft-clamped
    bin widths / heights through a softmax, knot derivatives through exp, minimum slope ``slope``), but computed
    from one parameter tensor with fewer, larger tensor operations, with an inverse that returns its
    log-determinant without a second bin search, and with a written-out backward pass for the forward direction
    (:class:`_SplineForward`: training evaluates it once per coupling and step, and autograd's recorded version
    cost four times the forward). Acts on the last dimension as a whole (event dim 1): the log-determinants are
    summed over it.

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
        self.phi = phi
        self.limit = abs(math.log(slope))
        self.bound = bound
        self.bins = bins

    def call_and_ladj(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return spline_forward(self.phi, x, self.bound, self.limit)

    def inverse_and_ladj(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """x = f^-1(y) and log |det J_{f^-1}(y)| (summed over the last dimension)."""
        _, corners = _bin_corners(_knot_table(self.phi, self.bound, self.limit), y, 1)
        d0, d1 = _derivatives(corners[..., 2, :], self.limit)[0].unbind(-1)
        (x0, x1), (y0, y1) = corners[..., 0, :].unbind(-1), corners[..., 1, :].unbind(-1)
        outside = (y <= -self.bound) | (y > self.bound)
        x, ladj = _bin_inverse(y, outside, x0, x1 - x0, y0, y1 - y0, d0, d1)
        return x, ladj.sum(-1)

    def _call(self, x: Tensor) -> Tensor:
        return self.call_and_ladj(x)[0]

    def _inverse(self, y: Tensor) -> Tensor:
        return self.inverse_and_ladj(y)[0]

    def log_abs_det_jacobian(self, x: Tensor, y: Tensor) -> Tensor:
        return self.call_and_ladj(x)[1]


def spline_forward(phi: Tensor, x: Tensor, bound: float, limit: float) -> tuple[Tensor, Tensor]:
    """y = f(x) and log dy/dx summed over the last dimension for splines `phi` (..., D, 3K - 1) on [-B, B] with
    soft-clamp limit `limit` (:class:`RationalQuadraticSpline`), through the written-out backward when gradients
    are asked for."""
    if torch.is_grad_enabled() and (phi.requires_grad or x.requires_grad):
        return _SplineForward.apply(phi, x, bound, limit)
    y, ladj, _ = _spline_forward(phi, x, bound, limit, keep=False)
    return y, ladj


def _soft_clamp(u: Tensor, scale: float) -> tuple[Tensor, Tensor]:
    """zuko's soft clamp u / (1 + |u| scale) and its denominator (1 + |u| scale), whose inverse square is the
    clamp's derivative."""
    denominator = u.abs().mul_(scale).add_(1)
    return u / denominator, denominator


def _knot_table(phi: Tensor, bound: float, limit: float, keep: list[Tensor] | None = None) -> Tensor:
    """Splines `phi` (..., D, 3K - 1) as one table (..., D, 3, K + 1): rows 0 and 1 the knots 0..K of the
    horizontal and the vertical axis (knot 0 is -B), row 2 the raw derivative logits of knots 0..K with 0 at
    both ends (exp of the soft clamp of 0 is exactly 1, the identity tails' slope). A value's bin corners and end
    derivatives are then one gather (:func:`_bin_corners`), with no fix-ups for the first and the last bin.

    zuko's soft clamp u / (1 + |2u / log slope|) bounds the width / height logits to (-limit/2, limit/2), so exp
    needs no max-shift (softmax = exp / sum). With `keep`, what the backward pass needs is appended to it."""
    bins = (phi.shape[-1] + 1) // 3
    clamped, denominator = _soft_clamp(phi[..., :2 * bins], 2 / limit)
    expd = clamped.exp_()
    cumulative = expd.unflatten(-1, (2, bins)).cumsum(-1)                                      # (..., D, 2, K)
    scale = (2 * bound) / cumulative[..., -1:]
    table = phi.new_empty(*phi.shape[:-1], 3, bins + 1)
    table[..., :2, 0] = -bound
    table[..., :2, 1:] = (cumulative * scale).sub_(bound)
    table[..., 2, ::bins] = 0
    table[..., 2, 1:bins] = phi[..., 2 * bins:]
    if keep is not None:
        keep += [expd, denominator, cumulative, scale]
    return table


def _bin_corners(table: Tensor, value: Tensor, axis: int) -> tuple[Tensor, Tensor]:
    """The bin of each value (..., D) among the knots of `axis` (0: horizontal, 1: vertical) of a knot table,
    as its two knot indices (..., D, 1, 2), and the table's entries there (..., D, 3, 2): the bin's corners
    [x0, x1], [y0, y1] and its end derivatives' raw logits."""
    bins = table.shape[-1] - 1
    k = (table[..., axis, 1:bins] < value[..., None]).sum(-1, keepdim=True)                    # bin in [0, K-1]
    pair = torch.cat((k, k + 1), dim=-1).unsqueeze(-2)
    return pair, table.gather(-1, pair.expand(*table.shape[:-1], 2))


def _derivatives(raw: Tensor, limit: float) -> tuple[Tensor, Tensor]:
    """Knot derivatives from their raw logits (zuko: exp(u / (1 + |u / log slope|))) and the clamp's
    denominators (for the backward pass)."""
    clamped, denominator = _soft_clamp(raw, 1 / limit)
    return clamped.exp_(), denominator


def _bin_inverse(y: Tensor, outside: Tensor, x0: Tensor, w: Tensor, y0: Tensor, h: Tensor, d0: Tensor,
                 d1: Tensor) -> tuple[Tensor, Tensor]:
    """x = f^-1(y) and log |dx/dy| per element, given each value's bin: its corner (x0, y0), width, height and end
    derivatives; values outside [-B, B] pass unchanged with log-determinant 0 (the root of the bin's quadratic in
    the numerically stable form)."""
    s = h / w
    rel = (y - y0).masked_fill(outside, 0.0)
    t = d0 + d1 - 2 * s
    a = h * (s - d0) + rel * t
    b = h * d0 - rel * t
    c = -s * rel
    z = 2 * c / (-b - (b * b - 4 * a * c).clamp(min=0).sqrt())
    x = x0 + z * w
    zz = z * (1 - z)
    polynomial = 2 * s * zz + d0 * (1 - z) ** 2 + d1 * z * z
    ladj = (2 * (s + t * zz).log() - (s * s * polynomial).log()).masked_fill(outside, 0.0)
    return torch.where(outside, y, x), ladj


def _exp_soft_clamp(u: Tensor, scale: float, out: Tensor | None = None) -> Tensor:
    """exp of zuko's soft clamp u / (1 + |u| scale), as exp2(u / ((1 + |u| scale) ln 2)): the same function to
    float rounding (a few ulp), and torch's CPU exp2 is several times faster than its exp. Written to `out`
    (of u's shape) when given."""
    denominator = u.abs().mul_(scale * _LN2).add_(_LN2)
    return torch.exp2(torch.div(u, denominator, out=denominator), out=out)


_LN2 = math.log(2.0)


def spline_inverse_columns(phi: Tensor, y: Tensor, bound: float, limit: float) -> tuple[Tensor, Tensor]:
    """The spline inverse of :meth:`RationalQuadraticSpline.inverse_and_ladj` for parameters stored column-wise,
    for sampling (no gradients): x = f^-1(y) and log |dx/dy| per element, (E,) each, not summed.

    phi (3K + 1, E) holds element e's parameters in column e, in rows: K width logits, K height logits, then the
    K + 1 derivative logits of knots 0..K, whose first and last rows are 0 (the end derivatives, exp(0) = 1: the
    conditioner's output rows are laid out so, see :meth:`SplineCoupling.inverse_columns`); y is (E,).

    The same function as the (..., D, 3K - 1) spline to float rounding, computed for ten million splines per
    coupling: every operation runs over rows of E contiguous values; the knots' cumulative sums start from a
    row of zeros (knot 0 is -B), so that each value's bin corners and derivatives are four and two flat index
    lookups with no fix-ups; only the cumulative sums are compared in the bin search (knot_j < y if and only if
    cumsum_j < (y + B) sum / 2B) and only the bin's corners are scaled to [-B, B]."""
    bins = (phi.shape[0] - 1) // 3
    size = y.shape[0]
    cumulative = phi.new_empty(2, bins + 1, size)                              # (axis, knot 0..K, E)
    cumulative[:, 0] = 0
    _exp_soft_clamp(phi[:2 * bins].view(2, bins, size), 2 / limit, out=cumulative[:, 1:])
    for knot in range(2, bins + 1):
        cumulative[:, knot] += cumulative[:, knot - 1]
    total = cumulative[:, bins]                                                 # (2, E)
    threshold = (y + bound).mul_(total[1]).div_(2 * bound)
    count = torch.uint8 if bins <= 256 else torch.int64                         # summing uint8 is far faster
    k = (cumulative[1, 1:bins] < threshold).view(torch.uint8).sum(0, dtype=count).long()      # bin 0..K-1
    lower = k.mul_(size).add_(torch.arange(size, device=y.device))              # flat index of knot k, axis 0
    offsets = torch.tensor([0, size, (bins + 1) * size, (bins + 2) * size], device=y.device)
    corners = cumulative.view(-1).index_select(0, (lower + offsets[:, None]).view(-1)).view(2, 2, size)
    corners.mul_(((2 * bound) / total).unsqueeze(1)).sub_(bound)                 # knots k, k + 1 of both axes
    derivatives = _exp_soft_clamp(phi[2 * bins:].reshape(-1).index_select(0, torch.cat((lower, lower + size))),
                                  1 / limit)
    (x0, x1), (y0, y1) = corners
    d0, d1 = derivatives.view(2, size)
    return _bin_inverse_columns(y, y.abs() > bound, x0, x1 - x0, y0, y1 - y0, d0, d1)


def _bin_inverse_columns(y: Tensor, outside: Tensor, x0: Tensor, w: Tensor, y0: Tensor, h: Tensor, d0: Tensor,
                         d1: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_bin_inverse` with fewer operations (in place, the quadratic's root with the sign of c folded in,
    the log-determinant as one log): the same function to float rounding, without gradients. Values outside
    [-B, B] (|y| > B; at y = -B both give x = -B and 0) are computed and then replaced."""
    s = h / w
    rel = y - y0
    t = torch.add(d0, d1).sub_(s, alpha=2)
    a = (s - d0).mul_(h).addcmul_(rel, t)
    b = torch.addcmul(h * d0, rel, t, value=-1)
    c = s * rel                                                                 # -c of the quadratic a z^2 + b z + c
    root = (a * c).mul_(4).addcmul_(b, b).clamp_(min=0).sqrt_().add_(b)
    z = c.mul_(2).div_(root)
    x = torch.addcmul(x0, z, w)
    one_z = 1 - z
    zz = z * one_z
    polynomial = (d0 * one_z).mul_(one_z).addcmul_(s, zz, value=2).addcmul_(d1, z * z)
    ratio = torch.addcmul(s, t, zz).div_(s)
    ladj = ratio.mul_(ratio).div_(polynomial).log_()                            # 2 log(s + t zz) - log(s^2 P)
    return torch.where(outside, y, x), ladj.masked_fill_(outside, 0.0)


def _spline_forward(phi: Tensor, x: Tensor, bound: float, limit: float,
                    keep: bool) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
    """y = f(x), log dy/dx summed over the last dimension and, with `keep`, what :class:`_SplineForward`'s
    backward pass needs."""
    saved: list[Tensor] | None = [] if keep else None
    pair, corners = _bin_corners(_knot_table(phi, bound, limit, saved), x, 0)
    derivatives, denominator = _derivatives(corners[..., 2, :], limit)
    d0, d1 = derivatives.unbind(-1)
    x0, y0 = corners[..., 0, 0], corners[..., 1, 0]
    w, h = (corners[..., :2, 1] - corners[..., :2, 0]).unbind(-1)
    outside = (x <= -bound) | (x > bound)
    s = h / w
    z = ((x - x0) / w).masked_fill(outside, 0.0)
    zz = z * (1 - z)
    den = s + (d0 + d1 - 2 * s) * zz
    numerator = s * z * z + d0 * zz
    polynomial = 2 * s * zz + d0 * (1 - z) ** 2 + d1 * z * z
    y = y0 + h * numerator / den
    ladj = ((s * s * polynomial).log() - 2 * den.log()).masked_fill(outside, 0.0)
    if saved is not None:
        saved += [pair, outside, z, w, h, s, derivatives, denominator, den, numerator, polynomial]
    return torch.where(outside, x, y), ladj.sum(-1), tuple(saved or ())


class _SplineForward(torch.autograd.Function):
    """The spline's forward direction (y, summed log-determinant) with its gradients written out.

    Per element, with z = (x - x0) / w, s = h / w, zz = z (1 - z), den = s + (d0 + d1 - 2s) zz,
    y = y0 + h (s z^2 + d0 zz) / den and ladj = log(s^2 P) - 2 log den, P = 2 s zz + d0 (1 - z)^2 + d1 z^2. The
    partial derivatives with respect to z, s, d0, d1 and h go back to x and to the bin's entries of the knot
    table (its two knots on each axis and its end derivatives' logits, one scatter), and from the table
    through the knots' normalisation, cumulative sum, exp and soft clamp to phi. Values outside [-B, B] pass x's
    gradient only.
    """

    @staticmethod
    def forward(ctx: Any, phi: Tensor, x: Tensor, bound: float, limit: float) -> tuple[Tensor, Tensor]:
        y, ladj, saved = _spline_forward(phi, x, bound, limit, keep=True)
        ctx.save_for_backward(*saved)
        ctx.bound, ctx.limit = bound, limit
        return y, ladj

    @staticmethod
    def backward(ctx: Any, grad_y: Tensor, grad_ladj: Tensor) -> tuple[Tensor | None, ...]:
        (expd, clamp_wh, cumulative, scale, pair, outside, z, w, h, s, derivatives, clamp_d, den, numerator,
         polynomial) = ctx.saved_tensors
        d0, d1 = derivatives.unbind(-1)
        gy = grad_y.masked_fill(outside, 0.0)
        gl = grad_ladj[..., None].expand_as(z).masked_fill(outside, 0.0)
        one_z = 1 - z
        zz = z * one_z
        slope = 1 - 2 * z
        t = torch.add(d0, d1).sub_(s, alpha=2)
        hy = gy * h / den                        # d loss / d numerator through y
        gden = torch.addcmul(gl * 2, hy, numerator).div_(den).neg_()
        gpoly = gl / polynomial
        g_z = (hy * torch.addcmul(d0 * slope, s, z, value=2)).addcmul_(gden * t, slope).addcmul_(
            gpoly, torch.addcmul(d1 * z, s, slope).sub_(d0 * one_z), value=2)
        g_s = (hy * z * z).addcmul_(gden, 1 - 2 * zz).addcmul_(gpoly, zz, value=2).addcmul_(gl, 2 / s)
        g_d0 = (hy + gden).mul_(zz).addcmul_(gpoly, one_z * one_z)
        g_d1 = (gden * zz).addcmul_(gpoly, z * z)
        g_h = torch.addcmul(g_s / w, gy, numerator / den)
        g_zw = g_z / w
        g_w = torch.addcmul(g_zw * z, g_s, s / w).neg_()
        grad_x = torch.where(outside, grad_y, g_zw) if ctx.needs_input_grad[1] else None
        if not ctx.needs_input_grad[0]:
            return None, grad_x, None, None
        # The bin's corners are its two knots on each axis (knot 0 is the constant -B): x0 enters z and w, x1 w.
        g_corners = torch.cat((torch.stack((g_zw.neg_() - g_w, g_w, gy - g_h, g_h), dim=-1).unflatten(-1, (2, 2)),
                               (torch.stack((g_d0, g_d1), dim=-1).mul_(derivatives) / (clamp_d * clamp_d))[..., None, :]),
                              dim=-2)                                                           # (..., D, 3, 2)
        g_table = z.new_zeros(*z.shape, 3, cumulative.shape[-1] + 1)
        g_table.scatter_add_(-1, pair.expand_as(g_corners), g_corners)
        # knots = cumulative * scale - B with scale = 2B / total, total = cumulative[..., -1], cumulative =
        # cumsum(expd), expd = exp(soft clamp): d knot_i / d expd_j = scale ([i >= j] - cumulative_i / total).
        g_scaled = g_table[..., :2, 1:] * scale
        correction = (g_scaled * cumulative).sum(-1, keepdim=True) / cumulative[..., -1:]
        g_expd = g_scaled.flip(-1).cumsum(-1).flip(-1).sub_(correction)
        g_wh = g_expd.flatten(-2).mul_(expd).div_(clamp_wh * clamp_wh)
        bins = cumulative.shape[-1]
        return torch.cat((g_wh, g_table[..., 2, 1:bins]), dim=-1), grad_x, None, None


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
                F.elu(h[:-1], layer.alpha, inplace=True)
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
        compiled = torch.compile(self._log_prob_rows, backend=COMPILE_BACKEND, dynamic=False, fullgraph=True)
        try:
            trained = [p for p in self.parameters() if p.requires_grad]
            torch.autograd.grad(compiled(x, context).sum(), [context, *trained])
        except Exception as error:  # noqa: BLE001 -- compilers fail in many ways; every one means "stay eager"
            return f"{type(error).__name__}: {str(error).strip().splitlines()[0] if str(error).strip() else ''}"
        self._compiled, self._compiled_rows = compiled, rows
        return None

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

    def sample(self, context: Tensor, n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """n samples per context row and their log-densities: (n, B, D) and (n, B)."""
        return self.from_noise(self.noise(context, n, generator), context)

    def noise(self, context: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
        """n base draws z ~ N(0, I) per context row: (n, B, D)."""
        return torch.randn((n, context.shape[0], self.features), generator=generator, device=context.device,
                           dtype=context.dtype)

    @torch.no_grad()
    def from_noise(self, z: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        """The samples x (n, B, D) that base draws z (n, B, D) map to, and their log-densities (n, B).

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
        log_lik = standard_normal_log_prob(z) - ladj.view(n, size) + self._log_scale()
        return columns.view(features, n, size).permute(1, 2, 0), log_lik


def _permutation(part: nn.Module) -> PermutationTransform:
    """The fixed permutation a non-coupling part of the flow stands for."""
    permutation = part()
    if not isinstance(permutation, PermutationTransform):
        raise TypeError(f"unexpected flow part {permutation!r}")
    return permutation


#: torch.compile's backend for :meth:`ConditionalSplineFlow.compile_training`: inductor generates the fused kernels;
#: tests use "aot_eager", which traces the same forward and backward graphs without generating code (seconds, not
#: the minute or two inductor takes on a 2-core CPU).
COMPILE_BACKEND = "inductor"


def standard_normal_log_prob(z: Tensor) -> Tensor:
    """log N(z; 0, I) summed over the last dimension."""
    return -0.5 * (z ** 2).sum(-1) - 0.5 * z.shape[-1] * math.log(2 * math.pi)
