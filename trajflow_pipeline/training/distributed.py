"""Training under ``torchrun``: the rank and world size, reductions over ranks, and each rank's seeded share of an
epoch (its randomness comes from (seed, stage, epoch, rank), so a resumed run replays the same epochs)."""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as torch_dist
from torch import Tensor


@dataclass
class DistContext:
    """Rank / world size under torchrun, and whether this call created the process group."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    created: bool = False

    @classmethod
    def from_env(cls) -> "DistContext":
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        rank = int(os.environ.get("RANK", "0"))
        return cls(rank=rank, world=world, local_rank=int(os.environ.get("LOCAL_RANK", str(rank))))

    @property
    def active(self) -> bool:
        return self.world > 1

    def start(self, device: torch.device) -> None:
        if not self.active:
            return
        if device.type == "cuda":
            torch.cuda.set_device(device)
        if not torch_dist.is_initialized():
            torch_dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
            self.created = True

    def stop(self) -> None:
        if self.created and torch_dist.is_initialized():
            torch_dist.destroy_process_group()
            self.created = False

    def sum(self, values: Sequence[float], device: torch.device) -> list[float]:
        """Element-wise sum over ranks (float64)."""
        tensor = torch.tensor(list(values), dtype=torch.float64, device=device)
        if self.active:
            torch_dist.all_reduce(tensor)
        return tensor.tolist()

    def gather(self, value: Any) -> list[Any]:
        if not self.active:
            return [value]
        out: list[Any] = [None] * self.world
        torch_dist.all_gather_object(out, value)
        return out

    def barrier(self) -> None:
        if self.active:
            torch_dist.barrier()


def derive_seed(seed: int, stage_index: int, epoch: int, rank: int) -> int:
    """A reproducible per-(stage, epoch, rank) seed."""
    text = f"{seed}/{stage_index}/{epoch}/{rank}".encode()
    return int.from_bytes(hashlib.sha256(text).digest()[:8], "little") & ((1 << 63) - 1)


def epoch_shard(n: int, seed: int, stage_index: int, epoch: int, dist: DistContext) -> Tensor:
    """This rank's indices of the epoch's permutation, padded DistributedSampler-style to equal length."""
    generator = torch.Generator().manual_seed(derive_seed(seed, stage_index, epoch, -1))
    order = torch.randperm(n, generator=generator)
    per_rank = math.ceil(n / dist.world)
    if per_rank * dist.world > n:
        order = torch.cat((order, order[:per_rank * dist.world - n]))
    return order[dist.rank::dist.world]
