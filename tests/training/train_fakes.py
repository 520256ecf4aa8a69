"""A stand-in for `trajflow_pipeline.data.Problems` so training tests can feed toy batches without a dataset."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from trajflow_pipeline.model.batch import SceneBatch


@dataclass
class FakeProblems:
    """The attributes of `trajflow_pipeline.data.Problems` that training reads."""

    batch: SceneBatch
    n_past: int
    n_future: int
    has_map: bool = False
    dataset: str = "toy"
    dt: float = 0.25
    fingerprint: dict[str, str] = field(default_factory=lambda: {"dataset": "toy", "manifest_sha256": "0" * 64})

    def __len__(self) -> int:
        return len(self.batch)

    @property
    def group_id(self) -> np.ndarray:
        """Every toy problem is its own identical-input group."""
        return np.arange(len(self.batch), dtype=np.int64)
