"""``stage.json``: what an experiment's data stage records in the dataset directory it built.

::

    DATA/stage.json   {"kind": "ingest" | "augment", "name": ..., "identity": ..., "options": {...},
                       "inputs": [{"path", "size", "mtime_ns", "sha256"}, ...], "upstream": ...,
                       "output": ..., "builds": N, "built": ISO date, "version": ...}

`identity` hashes what the stage's result depends on: its kind, name and options, and the content of what it read
(the raw files' relative paths, sizes and SHA-256 for an ingest; the source dataset's ``data_sha256`` for an
augmentation). `output` is the built dataset's ``data_sha256``, so a dataset replaced since (by hand) is not taken
for the one the record describes. `inputs` keep each file's size and modification time beside its hash, so an
unchanged file is not read again to tell. `builds` counts how often the stage was built into this directory.
The record is written after the dataset (atomically); a dataset without one is built again when its stage runs.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..errors import TrajflowError
from ..util import input_files
from ..util.atomic import atomic_write_text

STAGE_FILE = "stage.json"


@dataclass(frozen=True)
class StageRecord:
    """The record of one built data stage (see the module docstring)."""

    kind: str
    name: str
    identity: str
    output: str
    options: dict[str, Any] = field(default_factory=dict)
    inputs: list[dict[str, Any]] = field(default_factory=list)
    upstream: str | None = None
    builds: int = 1
    built: str = ""
    version: str = ""


def read_stage_record(dataset: str | Path) -> StageRecord | None:
    """The record in the dataset directory `dataset`; None when there is none or it cannot be read (the stage is
    then built again: a record is never needed to read the dataset itself)."""
    try:
        values = json.loads(input_files.read_text(Path(dataset) / STAGE_FILE))
        return StageRecord(**values)
    except (TrajflowError, OSError, ValueError, TypeError):
        return None


def write_stage_record(dataset: str | Path, record: StageRecord) -> None:
    """Write `record` into the dataset directory `dataset` (atomically)."""
    atomic_write_text(Path(dataset) / STAGE_FILE, json.dumps(asdict(record), indent=2, sort_keys=True) + "\n")
