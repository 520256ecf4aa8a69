"""Rational-quadratic splines on [-B, B] with identity tails: zuko's ``MonotonicRQSTransform`` re-expressed with
fewer, larger tensor operations, a written-out backward pass for training, and an inverse on column-stored draws
for sampling (the flow's couplings, :mod:`.flow`, evaluate ten million of them per layer when sampling)."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor
from torch.distributions import Transform, constraints


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
