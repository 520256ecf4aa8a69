"""The RNN autoencoder over future displacements (paper section III-B; SPEC section 6).

Encoder: Linear(2 -> M) + ReLU -> GRU(M, d, L) -> Linear(d -> m) applied to the top GRU output of the last step.
Decoder: the hidden state of every GRU layer starts as the latent, the first input is the latent; each step
applies Linear(m -> M) -> GRU -> Linear(d -> 2), and the next input is the top hidden state. Because the decoder
is auto-regressive it can roll out any number of steps, including past the horizon it was trained on.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .gru import gru_outputs
from .normalize import displacements_to_positions


class TrajectoryAutoencoder(nn.Module):
    """GRU encoder/decoder between alpha-scaled displacement sequences (B, T, 2) and latents (B, m)."""

    def __init__(self, embed: int = 20, hidden: int = 20, layers: int = 3, latent: int = 20) -> None:
        super().__init__()
        if latent != hidden:
            raise ValueError("the decoder tiles the latent over the GRU layers: latent must equal hidden")
        self.layers = layers
        self.latent_dim = latent
        self.enc_embed = nn.Linear(2, embed)
        self.enc_gru = nn.GRU(embed, hidden, layers, batch_first=True)
        self.enc_out = nn.Linear(hidden, latent)
        self.dec_in = nn.Linear(latent, embed)
        self.dec_gru = nn.GRU(embed, hidden, layers, batch_first=True)
        self.dec_out = nn.Linear(hidden, 2)

    def encode(self, displacements: Tensor) -> Tensor:
        """Scaled displacements (B, T, 2) -> latent (B, m), read from the last step's top GRU output."""
        return self.enc_out(gru_outputs(self.enc_gru, F.relu(self.enc_embed(displacements)))[:, -1])

    def decode(self, latent: Tensor, steps: int) -> Tensor:
        """Latents (..., m) -> scaled displacements (..., steps, 2), for any `steps` >= 1."""
        lead = latent.shape[:-1]
        flat = latent.reshape(-1, latent.shape[-1])
        if torch.is_grad_enabled() and (flat.requires_grad or any(p.requires_grad for p in self.parameters())):
            tops = self._roll_out(flat, steps)
        else:
            tops = self._roll_out_inference(flat, steps)
        out = self.dec_out(torch.stack(tops, dim=1))
        return out.reshape(*lead, steps, 2)

    def _roll_out(self, flat: Tensor, steps: int) -> list[Tensor]:
        """Top hidden state of every decoder step, with nn.GRU (differentiable)."""
        hidden = flat.unsqueeze(0).expand(self.layers, -1, -1).contiguous()
        inputs, tops = flat, []
        for _ in range(steps):
            _, hidden = self.dec_gru(self.dec_in(inputs).unsqueeze(1), hidden)
            inputs = hidden[-1]
            tops.append(inputs)
        return tops

    def _roll_out_inference(self, flat: Tensor, steps: int) -> list[Tensor]:
        """The same recursion as :meth:`_roll_out` without gradients, computed for throughput on many samples.

        The GRU equations are evaluated with contiguous gate blocks, the input layer folded into the first GRU
        layer's input weights, and tanh(u) = 2 sigmoid(2u) - 1 (sigmoid has a much faster CPU kernel).
        """
        layers = [self._inference_weights(index) for index in range(self.layers)]
        hidden = [flat] * self.layers
        inputs, tops = flat, []
        for _ in range(steps):
            x = inputs
            for index, (w_rz, b_rz, w_in, b_in, w_hn, b_hn) in enumerate(layers):
                h = hidden[index]
                rz = torch.sigmoid(F.linear(torch.cat((x, h), dim=1), w_rz, b_rz))
                size = h.shape[1]
                reset, update = rz[:, :size], rz[:, size:]
                n = torch.sigmoid(F.linear(x, w_in, b_in) + reset * F.linear(h, w_hn, b_hn)).mul_(2).sub_(1)
                x = n + update * (h - n)
                hidden[index] = x
            inputs = x
            tops.append(x)
        return tops

    def _inference_weights(self, index: int) -> tuple[Tensor, ...]:
        """Weights of decoder GRU layer `index` rearranged for :meth:`_roll_out_inference`."""
        gru = self.dec_gru
        size = gru.hidden_size
        w_ih, w_hh = getattr(gru, f"weight_ih_l{index}"), getattr(gru, f"weight_hh_l{index}")
        b_ih, b_hh = getattr(gru, f"bias_ih_l{index}"), getattr(gru, f"bias_hh_l{index}")
        if index == 0:   # the input Linear(m -> M) feeds only this layer: fold it into its input weights
            b_ih = w_ih @ self.dec_in.bias + b_ih
            w_ih = w_ih @ self.dec_in.weight
        w_rz = torch.cat((w_ih[:2 * size], w_hh[:2 * size]), dim=1)
        b_rz = b_ih[:2 * size] + b_hh[:2 * size]
        # n = tanh(u) is computed as 2 sigmoid(2u) - 1: the factor 2 goes into the weights.
        return (w_rz, b_rz, 2 * w_ih[2 * size:], 2 * b_ih[2 * size:], 2 * w_hh[2 * size:], 2 * b_hh[2 * size:])

    def forward(self, displacements: Tensor) -> Tensor:
        """Reconstruction of `displacements` through the latent."""
        return self.decode(self.encode(displacements), displacements.shape[1])

    def reconstruction_loss(self, displacements: Tensor, alpha: float) -> Tensor:
        """RMSE (metres) between true and reconstructed *positions* (cumulative sums), not displacements.

        Measuring positions penalises the drift that small per-step errors accumulate into (paper III-B).
        """
        target = displacements_to_positions(displacements, alpha)
        recon = displacements_to_positions(self(displacements), alpha)
        return torch.sqrt(((recon - target) ** 2).sum(-1).mean() + 1e-12)
