"""torch.nn.GRU's function (batch first, zero initial state) with fewer, larger operations and its own backward.

The encoders run stacks of small GRUs (hidden 16 to 20) over short sequences for hundreds of graph nodes per
batch, where the cost is the number of tensor operations, not arithmetic. Here each layer's input projection is
one product over all steps, a step is a handful of element-wise operations, and the backward pass is written out
(backpropagation through time) instead of recorded op by op: the same values and gradients as ``nn.GRU`` with the
same parameters, to float rounding (tested).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn


def gru_outputs(gru: nn.GRU, inputs: Tensor) -> Tensor:
    """Top-layer outputs (N, T, H) of `gru` over `inputs` (N, T, I) from a zero hidden state, as ``gru(inputs)[0]``.

    `gru` must be unidirectional, batch first, with biases and no dropout (how the encoders build theirs).
    """
    if gru.bidirectional or not gru.batch_first or not gru.bias or (gru.dropout and gru.training):
        raise ValueError("gru_outputs takes a unidirectional, batch-first GRU with biases and no dropout")
    weights = [getattr(gru, f"{kind}_l{layer}") for layer in range(gru.num_layers)
               for kind in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")]
    keep = torch.is_grad_enabled() and (inputs.requires_grad or any(w.requires_grad for w in weights))
    return _GRU.apply(keep, inputs, *weights)


def _tanh(value: Tensor) -> Tensor:
    """tanh(u) in place as 2 sigmoid(2u) - 1 (the same function; torch's CPU sigmoid is several times faster)."""
    return torch.sigmoid_(value.mul_(2)).mul_(2).sub_(1)


class _GRU(torch.autograd.Function):
    """Forward: per layer gi = x W_ih^T + b_ih over all steps, then per step gh = h W_hh^T + b_hh,
    (r, z) = sigmoid(gi_rz + gh_rz), n = tanh(gi_n + r * gh_n), h <- n + z (h - n). Backward: the same
    recursion reversed, each layer's weight gradients as products over all steps. Sequences are kept time-major
    (T, N, .), so that every step works on contiguous blocks."""

    @staticmethod
    def forward(ctx: Any, keep: bool, inputs: Tensor, *weights: Tensor) -> Tensor:
        """`keep`: save what the backward pass needs (not when nothing asks for gradients)."""
        saved: list[Tensor] = []
        layer_input = inputs.transpose(0, 1).contiguous()                                  # (T, N, I)
        steps, size = layer_input.shape[:2]
        for layer in range(len(weights) // 4):
            w_ih, w_hh, b_ih, b_hh = weights[4 * layer:4 * layer + 4]
            hidden = w_hh.shape[1]
            gi = torch.addmm(b_ih, layer_input.view(steps * size, -1), w_ih.t()).view(steps, size, 3 * hidden)
            outputs = layer_input.new_empty(steps + 1, size, hidden)                        # [0] = the zero state
            outputs[0].zero_()
            if keep:
                rz_all = layer_input.new_empty(steps, size, 2 * hidden)
                n_all, gh_n_all = layer_input.new_empty(steps, size, hidden), layer_input.new_empty(steps, size, hidden)
            for step in range(steps):
                h = outputs[step]
                gh = torch.addmm(b_hh, h, w_hh.t())
                rz = torch.add(gi[step, :, :2 * hidden], gh[:, :2 * hidden], out=rz_all[step] if keep else None)
                torch.sigmoid_(rz)
                n = torch.addcmul(gi[step, :, 2 * hidden:], rz[:, :hidden], gh[:, 2 * hidden:],
                                  out=n_all[step] if keep else None)
                _tanh(n)
                torch.lerp(n, h, rz[:, hidden:], out=outputs[step + 1])
                if keep:
                    gh_n_all[step] = gh[:, 2 * hidden:]
            if keep:
                saved += [layer_input, outputs, rz_all, n_all, gh_n_all]
            layer_input = outputs[1:]
        if keep:
            ctx.save_for_backward(*weights, *saved)
            ctx.layers = len(weights) // 4
        return layer_input.transpose(0, 1)

    @staticmethod
    def backward(ctx: Any, grad_outputs: Tensor) -> tuple[Tensor | None, ...]:
        layers = ctx.layers
        tensors = ctx.saved_tensors
        weights, saved = tensors[:4 * layers], tensors[4 * layers:]
        grads: list[Tensor | None] = [None] * (4 * layers)
        grad_layer_output = grad_outputs.transpose(0, 1)                                   # (T, N, H)
        grad_inputs = None
        for layer in reversed(range(layers)):
            w_ih, w_hh = weights[4 * layer], weights[4 * layer + 1]
            layer_input, outputs, rz_all, n_all, gh_n_all = saved[5 * layer:5 * layer + 5]
            steps, size, hidden = n_all.shape
            grad_rz = torch.empty_like(rz_all)         # d loss / d pre-activations of r, z (in gi and in gh)
            grad_pre_n = torch.empty_like(n_all)       # d loss / d (gi_n + r * gh_n)
            grad_gh_n = torch.empty_like(n_all)        # d loss / d gh_n
            w_hh_rz, w_hh_n = w_hh[:2 * hidden], w_hh[2 * hidden:]
            grad_h = grad_layer_output[steps - 1].clone()
            for step in reversed(range(steps)):
                if step < steps - 1:
                    grad_h += grad_layer_output[step]
                rz, n, previous = rz_all[step], n_all[step], outputs[step]
                r, z = rz[:, :hidden], rz[:, hidden:]
                # h = n + z (previous - n): dh/dn = 1 - z, dh/dz = previous - n, dh/dprevious = z
                pre_n = torch.mul(grad_h - grad_h * z, 1 - n * n, out=grad_pre_n[step])
                slope = rz - rz * rz                                                       # sigmoid'
                torch.mul(pre_n * gh_n_all[step], slope[:, :hidden], out=grad_rz[step, :, :hidden])
                torch.mul(grad_h * (previous - n), slope[:, hidden:], out=grad_rz[step, :, hidden:])
                torch.mul(pre_n, r, out=grad_gh_n[step])
                grad_h = torch.addmm(grad_h * z, grad_rz[step], w_hh_rz).addmm_(grad_gh_n[step], w_hh_n)
            flat_rz, flat_n = grad_rz.view(steps * size, -1), grad_pre_n.view(steps * size, -1)
            flat_gh_n = grad_gh_n.view(steps * size, -1)
            flat_input = layer_input.reshape(steps * size, -1)
            flat_previous = outputs[:-1].reshape(steps * size, -1)
            grads[4 * layer] = torch.cat((flat_rz.t() @ flat_input, flat_n.t() @ flat_input))
            grads[4 * layer + 1] = torch.cat((flat_rz.t() @ flat_previous, flat_gh_n.t() @ flat_previous))
            grads[4 * layer + 2] = torch.cat((flat_rz.sum(0), flat_n.sum(0)))
            grads[4 * layer + 3] = torch.cat((flat_rz.sum(0), flat_gh_n.sum(0)))
            if layer > 0 or ctx.needs_input_grad[1]:
                grad_inputs = torch.addmm(flat_n @ w_ih[2 * hidden:], flat_rz, w_ih[:2 * hidden])
                grad_inputs = grad_inputs.view(steps, size, -1)
            grad_layer_output = grad_inputs
        return None, (grad_inputs.transpose(0, 1) if ctx.needs_input_grad[1] else None), *grads
