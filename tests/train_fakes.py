"""A stand-in for `trajflow_pipeline.data.Problems` so training tests can feed toy batches without a dataset."""

from __future__ import annotations

from dataclasses import dataclass, field

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
