"""The tensor view of prediction problems that every model consumes: the contract between data and model.

Positions are world coordinates in metres, exactly as stored in the Parquet dataset; each model normalises
internally (translate to the target's last observed position, rotate its last step onto +x) and returns world
coordinates again, so nothing outside the model has to know about the normalisation.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from ..schemas.tables import AGENT_TYPES

#: Agent classes are indexed in the order of the dataset schema's AGENT_TYPES.
NUM_AGENT_TYPES = len(AGENT_TYPES)


@dataclass
class SceneBatch:
    """A batch of B prediction problems (one target agent each) with their context.

    past:             (B, P, 2) float32, the target's observed positions, past[:, -1] is the position at t0.
    future:           (B, F, 2) float32 ground-truth future positions (steps t0+1 .. t0+F), or None at inference.
    agent_type:       (B,) int64 index into AGENT_TYPES of the target.
    neighbours:       (B, N, P, 2) float32 past positions of the other agents present in the scene at t0,
                      aligned with the target's past steps; zero where absent.
    neighbours_valid: (B, N, P) bool, True where a neighbour position exists at that step.
    neighbours_mask:  (B, N) bool, True for real neighbours (False is padding); N may be 0.
    neighbours_type:  (B, N) int64 index into AGENT_TYPES.
    map_crop:         (B, 1, H, W) a heading-aligned grey-scale crop around the target (156 x 257 by default):
                      uint8 grey levels as the loader stores them (the map CNN divides by 255 on the device) or
                      float32 in [0, 1]; None when the dataset has no map.
    targets:          (B, D) the flow's target vector of each problem where training computed it once for a
                      stage in which it cannot change (``TrajectoryModel.fixed_targets``), else None.
    """

    past: Tensor
    agent_type: Tensor
    neighbours: Tensor
    neighbours_valid: Tensor
    neighbours_mask: Tensor
    neighbours_type: Tensor
    future: Tensor | None = None
    map_crop: Tensor | None = None
    targets: Tensor | None = None

    def __len__(self) -> int:
        return int(self.past.shape[0])

    @property
    def n_past(self) -> int:
        return int(self.past.shape[1])

    @property
    def n_future(self) -> int | None:
        return None if self.future is None else int(self.future.shape[1])

    def to(self, device: torch.device | str) -> "SceneBatch":
        """The same batch on another device (non-blocking where possible)."""
        return replace(self, **{f.name: _move(getattr(self, f.name), device) for f in fields(self)})

    def index(self, idx: Tensor | slice) -> "SceneBatch":
        """A sub-batch selecting problems `idx` along the batch dimension."""
        return replace(self, **{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[idx]
                                for f in fields(self)})

    def without_future(self) -> "SceneBatch":
        """The same inputs with the ground truth removed, as a model sees them at inference."""
        return replace(self, future=None, targets=None)


def _move(value: Tensor | None, device: torch.device | str) -> Tensor | None:
    return None if value is None else value.to(device, non_blocking=True)
