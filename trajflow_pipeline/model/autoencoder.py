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
            out = self.dec_out(torch.stack(self._roll_out(flat, steps), dim=1))
        else:
            out = self._decode_inference(flat, steps)
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

    def _decode_inference(self, flat: Tensor, steps: int) -> Tensor:
        """The same recursion as :meth:`_roll_out` and the output layer, without gradients, computed for throughput
        on many samples: (N, m) latents -> (N, steps, 2) (a view of a (steps, 2, N) tensor).

        The GRU runs on columns (one column per latent), so each gate block is a contiguous row range: the state
        rows are [the first layer's input; each layer's hidden state], layer l reads the contiguous row blocks l
        and l + 1 of it (:meth:`_inference_weights`: the r and z gates one product, the n gate's input and hidden
        products one batched product of the two blocks) and writes its new hidden state in place, which is then
        the next layer's input. The input layer is folded into the first GRU layer's input weights, and
        tanh(u) = 2 sigmoid(2u) - 1 (sigmoid has a much faster CPU kernel). `flat` may be the transpose of a
        column-wise tensor (what the flow's sampling returns): then no copy is made."""
        columns = flat.t().contiguous()                                                        # (m, N)
        size = self.dec_gru.hidden_size
        layers = [self._inference_weights(index) for index in range(self.layers)]
        state = columns.new_empty(self.layers + 1, size, columns.shape[1])
        state.copy_(columns.expand_as(state))               # the latent: the first input and every initial state
        state = state.view((self.layers + 1) * size, columns.shape[1])
        out = columns.new_empty(steps, 2, columns.shape[1])
        top = state[self.layers * size:]
        for step in range(steps):
            if step:
                state[:size].copy_(top)                                              # the next input: the top state
            for index, (w_rz, b_rz, w_n, b_n) in enumerate(layers):
                inputs = state[index * size:(index + 2) * size]                            # [x; h] (2 size, N)
                rz = torch.addmm(b_rz, w_rz, inputs).sigmoid_()
                gi_n, gh_n = torch.baddbmm(b_n, w_n, inputs.view(2, size, inputs.shape[1]))   # W_in x, W_hn h
                n = gi_n.addcmul_(rz[:size], gh_n).sigmoid_().mul_(2).sub_(1)
                hidden = state[(index + 1) * size:(index + 2) * size]
                torch.lerp(n, hidden, rz[size:], out=hidden)                                 # n + z (h - n)
            torch.addmm(self.dec_out.bias[:, None], self.dec_out.weight, top, out=out[step])
        return out.permute(2, 0, 1)

    def _inference_weights(self, index: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Decoder GRU layer `index` for :meth:`_decode_inference` on [input; hidden] columns: the r and z gates'
        weights on both and their summed biases (as columns), and the n gate's input and hidden weights stacked
        for one batched product, with their biases, times 2 (which makes its tanh a sigmoid)."""
        gru = self.dec_gru
        size = gru.hidden_size
        w_ih, w_hh = getattr(gru, f"weight_ih_l{index}"), getattr(gru, f"weight_hh_l{index}")
        b_ih, b_hh = getattr(gru, f"bias_ih_l{index}"), getattr(gru, f"bias_hh_l{index}")
        if index == 0:   # the input Linear(m -> M) feeds only this layer: fold it into its input weights
            b_ih = w_ih @ self.dec_in.bias + b_ih
            w_ih = w_ih @ self.dec_in.weight
        w_rz = torch.cat((w_ih[:2 * size], w_hh[:2 * size]), dim=1)
        b_rz = (b_ih[:2 * size] + b_hh[:2 * size])[:, None]
        w_n = 2 * torch.stack((w_ih[2 * size:], w_hh[2 * size:]))
        b_n = 2 * torch.stack((b_ih[2 * size:], b_hh[2 * size:]))[..., None]
        return w_rz, b_rz, w_n, b_n

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
