"""Context encoders that condition the flow (paper III-C and appendix).

* :class:`PastEncoder` -- GRU over the target's past displacements: Linear(2->16)+ReLU -> GRU(16,16,3) -> Linear(->64).
* :class:`SocialGNN` -- message passing over all agents present at t0 (target + neighbours), 4 layers 32 wide.
* :class:`MapEncoder` -- CNN over a heading-aligned grey-scale crop (1 x 156 x 257 -> 64).
* :class:`ContextEncoder` -- their concatenation, computed from a :class:`SceneBatch` in the target frame.

Everything is batched over problems and neighbours with masks; N (neighbours) may be 0.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .batch import NUM_AGENT_TYPES, SceneBatch
from .compiled import compile_probed
from .config import GNN_AGGREGATES
from .gru import gru_outputs
from .normalize import Frame, past_displacements, to_local


class PastEncoder(nn.Module):
    """Linear(2 -> embed) + ReLU -> GRU(embed, hidden, layers) -> Linear(hidden -> out) on the last step."""

    def __init__(self, embed: int = 16, hidden: int = 16, layers: int = 3, out: int = 64) -> None:
        super().__init__()
        self.embed = nn.Linear(2, embed)
        self.gru = nn.GRU(embed, hidden, layers, batch_first=True)
        self.out = nn.Linear(hidden, out)
        self.out_features = out

    def forward(self, displacements: Tensor) -> Tensor:
        """Displacements (B, T, 2) -> encoding (B, out)."""
        return self.out(gru_outputs(self.gru, F.relu(self.embed(displacements)))[:, -1])


class SocialGNN(nn.Module):
    """Interaction encoder over the target and its neighbours (paper appendix, "Social Interactions").

    Nodes are all agents present at t0, the target first. A node starts as ``Linear(past encoding ++ one-hot class)``
    of its past in the target frame. Each of the ``layers`` rounds computes a message for every ordered pair (b -> a)
    with ``MLP(x_b ++ x_a ++ class_b ++ class_a ++ (p_a - p_b) ++ |p_a - p_b|)`` (positions at t0), sums the
    messages from valid senders, and updates ``x_a <- MLP(x_a ++ m_a) + x_a``. The read-out is the mean over valid
    nodes. One past encoder is shared by all classes (the class enters through the one-hot inputs), which keeps the
    graph static for DDP and the computation a single batched GRU call.

    ``aggregate="mean"`` (not in the paper) averages the messages instead of summing them. A summed message grows
    with the number of agents, so a model trained on groups of at most 20 meets contexts it never saw in a crowd of
    70 (ETH/UCY fold univ); averaged, a crowd of copies of a group encodes exactly as the group does.
    """

    def __init__(self, width: int = 32, layers: int = 4, past: PastEncoder | None = None,
                 aggregate: str = "sum") -> None:
        super().__init__()
        if aggregate not in GNN_AGGREGATES:
            raise ValueError(f"aggregate must be one of {', '.join(GNN_AGGREGATES)}, not {aggregate!r}")
        self.aggregate = aggregate
        self.past = past if past is not None else PastEncoder()
        self.embed = nn.Linear(self.past.out_features + NUM_AGENT_TYPES, width)
        edge = 2 * NUM_AGENT_TYPES + 3
        # Message MLP of layer l: ReLU(W_s x_b + W_r x_a + W_e e_ab + b) -> Linear. Its first layer is split by
        # input block so that node terms are computed per node, not per edge (see _edge_terms), and the edge
        # weights W_e of all layers are one matrix (the edge features do not change between layers).
        self.msg_sender = nn.ModuleList(nn.Linear(width, width) for _ in range(layers))
        self.msg_receiver = nn.ModuleList(nn.Linear(width, width, bias=False) for _ in range(layers))
        self.msg_edge = nn.Linear(edge, width * layers, bias=False)
        self.msg_out = nn.ModuleList(nn.Linear(width, width) for _ in range(layers))
        self.update = nn.ModuleList(nn.Sequential(nn.Linear(2 * width, width), nn.ReLU(), nn.Linear(width, width))
                                    for _ in range(layers))
        self.out_features = width
        #: :func:`pool_edges` compiled for dynamic shapes (:meth:`compile_edges`), or None
        self._compiled_pool: Callable[[Tensor, Tensor, Tensor, Tensor], Tensor] | None = None

    #: how problems are grouped on a CPU (see `forward`): a group grows, in order of size, while its padded edge
    #: tensors stay near the cache (at most GROUP_EDGES edges; measured on the 2-core AMD EPYC: an edge layer's
    #: forward and backward cost 89 ns per edge for 16 problems of 40 nodes, 269 ns for 16 of 75) and each new
    #: member pads the others by at most GROUP_PADDING edges (about what a group's fixed cost buys). Other
    #: devices take the batch in one group (not measured yet).
    GROUP_EDGES = 16384
    GROUP_PADDING = 2048

    def forward(self, nodes_past: Tensor, nodes_valid: Tensor, nodes_mask: Tensor, nodes_type: Tensor) -> Tensor:
        """Node pasts (B, n, P, 2) in the target frame, step validity (B, n, P), node mask (B, n), classes (B, n).

        Returns the graph encoding (B, width). Only real nodes' pasts are encoded. On a CPU the problems are
        ordered by how far their real nodes extend and their edges are computed on groups of similar size in that
        order (:func:`size_groups`), each on its own padded (g, k, k) layout (:meth:`_grouped_rounds`): a batch
        mixing crowded and empty scenes then costs about sum(n_i^2) edges, not B * max(n_i)^2, in tensors near
        the cache. Other devices take the batch as one group, on the padded layout when padding wastes little,
        else on the edges between real nodes only. All give the same result.
        """
        batch, n = nodes_mask.shape
        flat_mask = nodes_mask.reshape(-1)
        onehot = F.one_hot(nodes_type.clamp(0, NUM_AGENT_TYPES - 1), NUM_AGENT_TYPES).to(nodes_past.dtype)
        disp = past_displacements(nodes_past, nodes_valid).reshape(batch * n, -1, 2)[flat_mask]
        encoded = nodes_past.new_zeros(batch * n, self.past.out_features)
        encoded = encoded.masked_scatter(flat_mask[:, None], self.past(disp)).reshape(batch, n, -1)
        x = self.embed(torch.cat((encoded, onehot), dim=-1))                                       # (B, n, width)
        pos = last_observed(nodes_past, nodes_valid)                                              # (B, n, 2) at t0
        extent = (nodes_mask * torch.arange(1, n + 1, device=nodes_mask.device)).amax(dim=1)  # last real node + 1
        if x.device.type != "cpu":  # one group, in batch order
            k, edges = torch.stack((extent.max(), (nodes_mask.sum(1) ** 2).sum())).tolist()  # one host transfer
            k = max(1, k)
            return self._readout(x[:, :k], pos[:, :k], onehot[:, :k], nodes_mask[:, :k], batch * k * k <= 2 * edges)
        order = torch.argsort(extent, stable=True)
        ends = extent[order].tolist()                                                  # one transfer to the host
        bounds = size_groups(ends, self.GROUP_EDGES, self.GROUP_PADDING)
        return self._grouped_rounds(x, pos, onehot, nodes_mask, order, [(stop - start, max(1, ends[stop - 1]))
                                                                        for start, stop in bounds])

    def _grouped_rounds(self, x: Tensor, pos: Tensor, onehot: Tensor, mask: Tensor, order: Tensor,
                        shapes: list[tuple[int, int]]) -> Tensor:
        """The rounds and the read-out with the problems in `order` split into consecutive groups of `shapes`
        (members, extent), each group on its padded (members, extent, extent) edge layout.

        The nodes of all groups are packed into one (R, width) tensor, group after group, each group's block a
        (members x extent) grid: the node layers of a round then run once over all groups, and only the edge
        block (the per-edge sum, distance term, ReLU and pooling) runs per group, on views of the packed
        tensors. Returns the graph encodings (B, width) in batch order."""
        batch, n = mask.shape
        # Packed row -> flattened (problem, node) index: group by group, problem by problem, node 0..extent-1.
        start, pieces = 0, []
        for members, extent in shapes:
            problems = order[start:start + members]
            pieces.append((problems[:, None] * n + torch.arange(extent, device=order.device)).reshape(-1))
            start += members
        rows = torch.cat(pieces)
        sizes = [members * extent for members, extent in shapes]
        x, pos, onehot = (t.reshape(batch * n, -1).index_select(0, rows) for t in (x, pos, onehot))
        real = mask.reshape(-1).index_select(0, rows)                                             # (R,)
        problem = torch.div(rows, n, rounding_mode="floor")                                       # (R,)
        counts = mask.sum(1).to(x.dtype)
        senders = counts.index_select(0, problem)[:, None]                                        # (R, 1)
        dists = []
        for (members, extent), pos_g in zip(shapes, pos.split(sizes)):
            pos_g = pos_g.view(members, extent, 2)
            rel = pos_g[:, :, None, :] - pos_g[:, None, :, :]
            dists.append(torch.sqrt((rel ** 2).sum(-1, keepdim=True) + 1e-12))                    # (g, k, k, 1)
        padding = ~real[:, None]
        for sender, receiver, sender_term, receiver_term, w_dist, out, update in self._layers(onehot, pos):
            # A padding sender's term is -inf, so its edges are exactly 0 after the ReLU (and pass no gradient).
            from_b = (sender(x) + sender_term).masked_fill(padding, float("-inf"))                 # (R, width)
            to_a = receiver(x) + receiver_term
            pooled = [self._pool_edges(to_g.view(members, extent, -1), from_g.view(members, extent, -1), dist, w_dist)
                      .reshape(members * extent, -1)
                      for (members, extent), from_g, to_g, dist in zip(shapes, from_b.split(sizes), to_a.split(sizes),
                                                                       dists)]
            x = update(torch.cat((x, self._message(torch.cat(pooled), senders, out)), dim=-1)) + x
        weights = real.to(x.dtype)[:, None]
        summed = x.new_zeros(batch, x.shape[-1]).index_add_(0, problem, x * weights)
        return summed / counts.clamp(min=1.0)[:, None]

    def _readout(self, x: Tensor, pos: Tensor, onehot: Tensor, mask: Tensor, dense: bool) -> Tensor:
        """The rounds on one group of problems (on the padded layout if `dense`, else on the real edges), then the
        mean over each problem's real nodes (g, width)."""
        if dense:
            x = self._dense_rounds(x, pos, onehot, mask)
        else:
            x = self._sparse_rounds(x, pos, onehot, mask)
        weights = mask.to(x.dtype)
        return (x * weights[..., None]).sum(1) / weights.sum(1, keepdim=True).clamp(min=1.0)

    #: groups of more edges than this take the compiled edge block (:meth:`compile_edges`); smaller ones stay
    #: eager, where the compiled call's fixed cost (measured on the 2-core Xeon, 1 thread: about 0.1-0.5 ms per
    #: forward and backward) outweighs what it saves. It is also where inductor switches to other kernels, which
    #: would be a second compile, as would a group of one problem (torch.compile specialises sizes of 1).
    COMPILED_MIN_EDGES = 4096

    def _pool_edges(self, to_a: Tensor, from_b: Tensor, dist: Tensor, w_dist: Tensor) -> Tensor:
        """:func:`pool_edges`, compiled where :meth:`compile_edges` made it so, gradients are on and the group has
        more than COMPILED_MIN_EDGES edges."""
        members, extent = to_a.shape[:2]
        if (self._compiled_pool is not None and torch.is_grad_enabled() and members > 1 and extent > 1
                and members * extent * extent > self.COMPILED_MIN_EDGES):
            return self._compiled_pool(to_a, from_b, dist, w_dist)
        return pool_edges(to_a, from_b, dist, w_dist)

    def compile_edges(self) -> str | None:
        """Compile the edge block (:func:`pool_edges`, forward and its written-out backward,
        :func:`pool_edges_to_compile`) for any group shape (torch.compile with dynamic shapes): the one piece of a
        crowded step that runs per edge. Eager, it is half of a fold-eth flow step, spent in memory-bound passes
        over (g, k, k, width) temporaries; compiled, the pre-activations are recomputed in registers and never
        stored. Tried once here on random inputs; returns None when compiled, else the reason (the block stays
        eager). Only groups of more than COMPILED_MIN_EDGES edges take it."""
        weight = self.msg_edge.weight
        generator = torch.Generator(weight.device).manual_seed(0)
        width = self.out_features

        def probe(pool: Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]) -> None:
            members, extent = 4, 40                          # 6400 edges: a group that takes the compiled block
            options = dict(generator=generator, device=weight.device, dtype=weight.dtype)
            to_a, from_b = (torch.randn(members, extent, width, requires_grad=True, **options) for _ in range(2))
            dist = torch.rand(members, extent, extent, 1, **options)
            w_dist = torch.randn(width, requires_grad=True, **options)
            torch.autograd.grad(pool(to_a, from_b, dist, w_dist).sum(), [to_a, from_b, w_dist])

        self._compiled_pool, failure = compile_probed(pool_edges_to_compile, probe, dynamic=True)
        return failure

    def drop_compiled(self) -> None:
        """Back to the eager edge block."""
        self._compiled_pool = None

    def _message(self, pooled: Tensor, senders: Tensor, out: nn.Linear) -> Tensor:
        """A node's message from the sum of its senders' hidden edge terms (`pooled`) and their count: the sum of
        out(h_ab) over the senders b, or its mean. Because `out` is affine, both come from the one pooled sum
        instead of `out` applied to every edge."""
        if self.aggregate == "mean":
            return out(pooled / senders.clamp(min=1.0))
        return F.linear(pooled, out.weight) + senders * out.bias

    def _edge_terms(self, onehot: Tensor, pos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The edge part W_e e_ab of every layer's message, split into what depends on one node only.

        The edge features are [class_b, class_a, p_a - p_b, |p_a - p_b|], and W_e acts linearly on them, so
        W_e e_ab = sender_b + receiver_a + |p_a - p_b| w_dist with sender_b = W_class_b c_b - W_rel p_b and
        receiver_a = W_class_a c_a + W_rel p_a. Only the distance term is per edge: this is the same function as
        the concatenated edge features, at a fraction of the per-edge work (which dominates a crowded step).
        Returns the per-node sender and receiver terms (..., n, layers * width) and w_dist (layers * width,).
        """
        types = onehot.shape[-1]
        weight = self.msg_edge.weight
        w_sender, w_receiver = weight[:, :types], weight[:, types:2 * types]
        w_rel, w_dist = weight[:, 2 * types:2 * types + 2], weight[:, 2 * types + 2].contiguous()  # as compiled
        sender = F.linear(onehot, w_sender) - F.linear(pos, w_rel)
        receiver = F.linear(onehot, w_receiver) + F.linear(pos, w_rel)
        return sender, receiver, w_dist

    def _layers(self, onehot: Tensor, pos: Tensor) -> Iterator[tuple[nn.Module, nn.Module, Tensor, Tensor, Tensor,
                                                                     nn.Module, nn.Module]]:
        """Per layer: its sender and receiver node layers, their per-node edge terms, the distance weight, the
        message output layer and the update MLP."""
        sender_terms, receiver_terms, w_dist = self._edge_terms(onehot, pos)
        layers = len(self.update)
        return zip(self.msg_sender, self.msg_receiver, sender_terms.chunk(layers, dim=-1),
                   receiver_terms.chunk(layers, dim=-1), w_dist.chunk(layers), self.msg_out, self.update)

    def _dense_rounds(self, x: Tensor, pos: Tensor, onehot: Tensor, mask: Tensor) -> Tensor:
        """Message passing on the padded layout: edge [p, a, b] carries the message b -> a."""
        rel = pos[:, :, None, :] - pos[:, None, :, :]
        dist = torch.sqrt((rel ** 2).sum(-1, keepdim=True) + 1e-12)                               # (B, n_a, n_b, 1)
        padding = ~mask[:, :, None]                                                               # (B, n_b, 1)
        senders = mask.sum(1).to(x.dtype)[:, None, None]                                          # (B, 1, 1)
        for sender, receiver, sender_term, receiver_term, w_dist, out, update in self._layers(onehot, pos):
            # A padding sender's term is -inf, so its edges are exactly 0 after the ReLU (and pass no gradient):
            # the masked sum over senders is a plain sum over the sender axis.
            from_b = (sender(x) + sender_term).masked_fill(padding, float("-inf"))                # (B, n_b, width)
            to_a = receiver(x) + receiver_term                                                    # (B, n_a, width)
            pooled = self._pool_edges(to_a, from_b, dist, w_dist)                                 # (B, n_a, width)
            x = update(torch.cat((x, self._message(pooled, senders, out)), dim=-1)) + x
        return x

    def _sparse_rounds(self, x: Tensor, pos: Tensor, onehot: Tensor, mask: Tensor) -> Tensor:
        """The same rounds over the real nodes only, as index operations on flattened nodes and edges.

        Gathers use ``index_select``, whose backward is an ``index_add``: plain advanced indexing backpropagates
        through ``index_put`` with accumulation, which on CPU took half of a crowded ETH/UCY training step.
        """
        batch, n = mask.shape
        flat_mask = mask.reshape(-1)
        real = flat_mask.nonzero().squeeze(1)                                                     # (K,)
        problem = torch.div(real, n, rounding_mode="floor")                                       # (K,)
        node_id = torch.cumsum(flat_mask.long(), 0).reshape(batch, n) - 1
        p_idx, a_idx, b_idx = (mask[:, :, None] & mask[:, None, :]).nonzero(as_tuple=True)
        receiver_id, sender_id = node_id[p_idx, a_idx], node_id[p_idx, b_idx]                     # (E,)
        nodes = x.reshape(batch * n, -1).index_select(0, real)
        flat_pos = pos.reshape(batch * n, 2).index_select(0, real)
        flat_onehot = onehot.reshape(batch * n, -1).index_select(0, real)
        rel = flat_pos.index_select(0, receiver_id) - flat_pos.index_select(0, sender_id)
        dist = torch.sqrt((rel ** 2).sum(-1, keepdim=True) + 1e-12)                               # (E, 1)
        senders = mask.sum(1).to(x.dtype).index_select(0, problem)[:, None]                      # (K, 1)
        for sender, receiver, sender_term, receiver_term, w_dist, out, update in self._layers(flat_onehot, flat_pos):
            from_b, to_a = sender(nodes) + sender_term, receiver(nodes) + receiver_term            # (K, width)
            hidden = (from_b.index_select(0, sender_id) + to_a.index_select(0, receiver_id)).addcmul_(dist, w_dist)
            pooled = torch.zeros_like(nodes).index_add_(0, receiver_id, hidden.relu_())
            nodes = update(torch.cat((nodes, self._message(pooled, senders, out)), dim=-1)) + nodes
        return x.new_zeros(batch * n, x.shape[-1]).index_copy(0, real, nodes).reshape(batch, n, -1)


class MapEncoder(nn.Module):
    """3 conv layers (kernel 5, stride 4; zero padding 1 on the first two) then Linear(->128) -> Linear(->out)."""

    def __init__(self, height: int = 156, width: int = 257, out: int = 64) -> None:
        super().__init__()
        self.convs = nn.Sequential(nn.Conv2d(1, 8, 5, stride=4, padding=1), nn.ReLU(),
                                   nn.Conv2d(8, 16, 5, stride=4, padding=1), nn.ReLU(),
                                   nn.Conv2d(16, 32, 5, stride=4), nn.ReLU())
        h, w = height, width
        for pad in (1, 1, 0):
            h, w = (h + 2 * pad - 5) // 4 + 1, (w + 2 * pad - 5) // 4 + 1
        self.head = nn.Sequential(nn.Linear(32 * h * w, 128), nn.ReLU(), nn.Linear(128, out))
        self.out_features = out
        self.size = (height, width)

    def forward(self, crop: Tensor) -> Tensor:
        """Crops (B, 1, H, W) -> (B, out): floats in [0, 1], or uint8 grey levels (how the loader stores them, a
        quarter of the memory), converted here, on the crops' device, to level / 255 -- the same scaling as
        float crops, so both give identical outputs."""
        if tuple(crop.shape[-2:]) != self.size:
            raise ValueError(f"map crops must be {self.size[0]} x {self.size[1]}, got "
                             f"{crop.shape[-2]} x {crop.shape[-1]}")
        return self.head(self.convs(crop_values(crop, self.convs[0].weight.dtype)).flatten(1))


def crop_values(crop: Tensor, dtype: torch.dtype) -> Tensor:
    """Map crops as floats in [0, 1]: uint8 grey levels divided by 255 (as the rasters are scaled), floats as given."""
    if crop.dtype == torch.uint8:
        return crop.to(dtype) / 255.0
    return crop.to(dtype)


class ContextEncoder(nn.Module):
    """The flow's conditioning vector: past encoding ++ social encoding ++ map encoding (those enabled)."""

    def __init__(self, *, past: PastEncoder, social: SocialGNN | None, map_encoder: MapEncoder | None) -> None:
        super().__init__()
        self.past = past
        self.social = social
        self.map = map_encoder
        self.out_features = (past.out_features + (social.out_features if social is not None else 0)
                             + (map_encoder.out_features if map_encoder is not None else 0))

    def forward(self, batch: SceneBatch, frame: Frame, local_past: Tensor) -> Tensor:
        """Context (B, C) of each problem; `local_past` is the target's past in its own frame (B, P, 2)."""
        parts = [self.past(past_displacements(local_past))]
        if self.social is not None:
            parts.append(self.social(*social_nodes(batch, frame, local_past)))
        if self.map is not None:
            if batch.map_crop is None:
                raise ValueError("this model was trained with maps but the batch has no map_crop")
            parts.append(self.map(batch.map_crop))
        return torch.cat(parts, dim=-1)


def pool_edges(to_a: Tensor, from_b: Tensor, dist: Tensor, w_dist: Tensor) -> Tensor:
    """The edge block of a message round: sum_b ReLU(to_a + from_b + |p_a - p_b| w_dist) for every receiver a,
    from receiver terms (g, k, width), sender terms (g, k, width; -inf for padding senders), distances
    (g, k_a, k_b, 1) and the distance weight (width,) -> (g, k, width)."""
    hidden = torch.addcmul(to_a[:, :, None, :], dist, w_dist).add_(from_b[:, None, :, :])
    return hidden.relu_().sum(2)


def pool_edges_to_compile(to_a: Tensor, from_b: Tensor, dist: Tensor, w_dist: Tensor) -> Tensor:
    """:func:`pool_edges` with the backward pass written out (:class:`_PooledEdges`), the form that is compiled."""
    return _PooledEdges.apply(to_a, from_b, dist, w_dist)


def _edge_preactivations(to_a: Tensor, from_b: Tensor, dist: Tensor, w_dist: Tensor) -> Tensor:
    """to_a + from_b + dist w_dist on the (g, k_a, k_b, width) edge layout."""
    return torch.addcmul(to_a[:, :, None, :], dist, w_dist) + from_b[:, None, :, :]


class _PooledEdges(torch.autograd.Function):
    """:func:`pool_edges` with its own backward. With G = [pre > 0] * grad_a on the edge layout, the gradients
    are grad_to_a = sum_b G, grad_w = sum_(a, b) G dist_ab, grad_from_b = sum_a G and grad_dist = G . w. The sum
    over a is taken on the transposed layout (sender first: the same pre-activations, from_b + to_a + dist^T w),
    so both passes reduce over their layout's third axis. Compiled, each pass recomputes the pre-activations in
    registers; measured on the 2-core Xeon (1 thread), the edge block's forward and backward on groups of 13k-17k
    edges took 1.8-2.2x less time than the compiled autograd-derived backward, which reduces over a strided axis,
    and a fold-eth flow step 1.19x less."""

    @staticmethod
    def forward(ctx: Any, to_a: Tensor, from_b: Tensor, dist: Tensor, w_dist: Tensor) -> Tensor:
        ctx.save_for_backward(to_a, from_b, dist, w_dist)
        return _edge_preactivations(to_a, from_b, dist, w_dist).relu().sum(2)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        to_a, from_b, dist, w_dist = ctx.saved_tensors
        active = (_edge_preactivations(to_a, from_b, dist, w_dist) > 0).to(grad.dtype)          # (g, a, b, width)
        grad_to_a = grad * active.sum(2)
        grad_w_dist = (grad * (active * dist).sum(2)).sum((0, 1))
        # positions carry gradients only when something asks for them (never in training: they are data)
        grad_dist = None
        if ctx.needs_input_grad[2]:
            grad_dist = (active * (grad * w_dist)[:, :, None, :]).sum(3, keepdim=True)
        active_by_sender = (_edge_preactivations(from_b, to_a, dist.transpose(1, 2), w_dist) > 0).to(grad.dtype)
        grad_from_b = (active_by_sender * grad[:, None, :, :]).sum(2)                              # (g, b, width)
        return grad_to_a, grad_from_b, grad_dist, grad_w_dist


def size_groups(extents: list[int], max_edges: int, max_padding: int) -> list[tuple[int, int]]:
    """Consecutive groups (start, stop) of problems sorted by extent (ascending): a group takes the next problem
    while its padded edges (members x largest extent^2) stay within `max_edges` and the padding the newcomer adds
    to the members already in (members x the growth of extent^2) within `max_padding`. At least one per group."""
    bounds, start, top = [], 0, 0
    for index, extent in enumerate(extents):
        members = index - start
        if members and (members * (extent * extent - top * top) > max_padding
                        or (members + 1) * extent * extent > max_edges):
            bounds.append((start, index))
            start = index
        top = extent
    bounds.append((start, len(extents)))
    return bounds


def last_observed(positions: Tensor, valid: Tensor) -> Tensor:
    """The last observed position of each track (..., P, 2) given step validity (..., P); zero if never observed."""
    steps = torch.arange(valid.shape[-1], device=valid.device).expand_as(valid)
    last = torch.where(valid, steps, torch.full_like(steps, -1)).max(dim=-1).values
    picked = positions.gather(-2, last.clamp(min=0)[..., None, None].expand(*last.shape, 1, 2)).squeeze(-2)
    return picked * (last >= 0)[..., None].to(positions.dtype)


def compact_neighbours(batch: SceneBatch) -> SceneBatch:
    """Move real neighbours to the front and drop columns that are padding in every problem of the batch."""
    mask = batch.neighbours_mask
    if mask.shape[1] == 0:
        return batch
    order = torch.argsort((~mask).to(torch.int8), dim=1, stable=True)
    keep = int(mask.sum(1).max().item()) if mask.numel() else 0
    order = order[:, :keep]

    def take(value: Tensor) -> Tensor:
        index = order.reshape(*order.shape, *([1] * (value.dim() - 2))).expand(-1, -1, *value.shape[2:])
        return value.gather(1, index)

    return SceneBatch(past=batch.past, agent_type=batch.agent_type, neighbours=take(batch.neighbours),
                      neighbours_valid=take(batch.neighbours_valid), neighbours_mask=take(batch.neighbours_mask),
                      neighbours_type=take(batch.neighbours_type), future=batch.future, map_crop=batch.map_crop)


def social_nodes(batch: SceneBatch, frame: Frame, local_past: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Graph nodes (target first, then neighbours) in the target frame: pasts, step validity, mask, classes."""
    batch = compact_neighbours(batch)
    size, steps = local_past.shape[:2]
    valid_nb = batch.neighbours_valid & batch.neighbours_mask[..., None]
    nb_local = to_local(batch.neighbours, frame) * valid_nb[..., None].to(local_past.dtype)
    nodes_past = torch.cat((local_past[:, None], nb_local), dim=1)
    target_valid = torch.ones(size, 1, steps, dtype=torch.bool, device=local_past.device)
    nodes_valid = torch.cat((target_valid, valid_nb), dim=1)
    nodes_mask = torch.cat((torch.ones(size, 1, dtype=torch.bool, device=local_past.device),
                            batch.neighbours_mask), dim=1)
    nodes_type = torch.cat((batch.agent_type[:, None], batch.neighbours_type), dim=1)
    return nodes_past, nodes_valid, nodes_mask, nodes_type
