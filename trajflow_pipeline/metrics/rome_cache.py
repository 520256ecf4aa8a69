"""Finished ROME fits kept on disk while an evaluation runs, so that an interrupted one resumes where it stopped.

The ROME fits are most of an evaluation's time (an hour and more for a large test fold on one core), and a fit's
result depends only on its task, its seed and the fitting code (see :mod:`trajflow_pipeline.metrics.parallel`).
So finished fits are saved in parts, each written atomically and synced, under ``ROOT/<digest>/``. The digest
covers every task's points, queries, minimum standard deviation and KDE, the seed, the number and order of the tasks,
and what fits them: the estimator's version (:data:`ESTIMATOR`), the versions of scikit-learn, numpy and scipy,
this module's format version and the processor model (BLAS kernels differ between CPUs in the last bits). A rerun
over the very same tasks on the same setup loads the saved fits and fits only the rest; anything else gets a
directory of its own and never mixes. Loaded fits are checked against their tasks (count and length of the query
results, finite values), and a part that cannot be read is skipped: its fits are simply made again. The caller
removes ROOT once its results are safely written.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import struct
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import TrajflowError
from ..util import input_files
from ..util.atomic import atomic_file

#: one finished task: its index, its log-density arrays (one per query) and its count of PCA retries
Finished = tuple[int, tuple[tuple[np.ndarray, ...], int]]
#: bump when the way a task is fitted or saved changes, so that older saved fits are not reused
FORMAT_VERSION = 2
#: the estimator that made the saved fits (trajflow_pipeline.metrics.rome); bump when its numbers change
ESTIMATOR = "trajflow-rome-2"
#: the file in each digest directory that says how many tasks the list has (for progress displays)
MANIFEST = "tasks.json"


class RomeCache:
    """The saved results of one list of ROME tasks (see the module docstring)."""

    def __init__(self, root: Path, tasks: Sequence[Any], base_seed: int) -> None:
        self.tasks = tasks
        self.directory = Path(root) / _digest(tasks, base_seed)

    def load(self) -> dict[int, tuple[tuple[np.ndarray, ...], int]]:
        """Every finished task saved so far (index -> result) that matches its task; a part that cannot be read,
        or an entry that does not fit its task, is left out (those fits are made again)."""
        finished: dict[int, tuple[tuple[np.ndarray, ...], int]] = {}
        for part in sorted(self.directory.glob("part-*.npz")):
            try:
                entries = _read_part(part)
            except Exception:  # noqa: BLE001 - a damaged cache part (truncated, empty, not a zip) is only skipped
                continue
            for index, values, retried in entries:
                if self._matches(index, values):
                    finished[index] = (values, retried)
        return finished

    def save(self, finished: list[Finished]) -> None:
        """Add finished tasks as one more part, written atomically and synced to disk."""
        if not finished:
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        manifest = self.directory / MANIFEST
        if not manifest.exists():
            with atomic_file(manifest) as tmp:
                tmp.write_text(json.dumps({"tasks": len(self.tasks)}) + "\n")
        queries = [values for _, (values, _) in finished]
        with atomic_file(self.directory / f"part-{uuid.uuid4().hex}.npz") as tmp:
            with open(tmp, "wb") as handle:
                np.savez(handle,
                         indices=np.array([index for index, _ in finished], dtype=np.int64),
                         retries=np.array([retried for _, (_, retried) in finished], dtype=np.int64),
                         n_queries=np.array([len(v) for v in queries], dtype=np.int64),
                         lengths=np.array([np.size(a) for v in queries for a in v], dtype=np.int64),
                         values=np.concatenate([np.asarray(a, dtype=np.float64).ravel() for v in queries for a in v]
                                               or [np.zeros(0)]))
                handle.flush()
                os.fsync(handle.fileno())

    def _matches(self, index: int, values: tuple[np.ndarray, ...]) -> bool:
        """Whether a saved result has the shape its task's result has (one finite value per query point)."""
        if not 0 <= index < len(self.tasks):
            return False
        queries = self.tasks[index].queries
        return len(values) == len(queries) and all(
            v.shape == (np.shape(q)[0],) and bool(np.isfinite(v).all()) for v, q in zip(values, queries))


def saved_fits(root: Path) -> tuple[int, int] | None:
    """(fits saved, tasks) of the most recently written task list under `root`, None when there is none."""
    directories = [d for d in Path(root).glob("*") if (d / MANIFEST).is_file()] if Path(root).is_dir() else []
    if not directories:
        return None
    newest = max(directories, key=lambda d: max((p.stat().st_mtime for p in d.iterdir()), default=0.0))
    indices: set[int] = set()
    for part in newest.glob("part-*.npz"):
        try:
            indices.update(index for index, _, _ in _read_part(part))
        except Exception:  # noqa: BLE001 - a damaged part counts as not saved
            continue
    try:
        tasks = int(json.loads(input_files.read_text(newest / MANIFEST))["tasks"])
    except (TrajflowError, OSError, ValueError, KeyError, TypeError):
        return None
    return len(indices), tasks


def _read_part(path: Path) -> list[tuple[int, tuple[np.ndarray, ...], int]]:
    """The (index, values, retries) entries of one part; raises when the part is damaged or inconsistent."""
    with np.load(path) as saved:
        indices, retries, counts = saved["indices"], saved["retries"], saved["n_queries"]
        lengths, values = saved["lengths"], saved["values"]
    if not (len(indices) == len(retries) == len(counts) and counts.sum() == len(lengths)
            and lengths.sum() == len(values)):
        raise ValueError(f"{path}: inconsistent part")
    arrays = np.split(values, np.cumsum(lengths)[:-1]) if len(lengths) else []
    starts = np.concatenate(([0], np.cumsum(counts)))
    return [(int(index), tuple(arrays[starts[row]:starts[row + 1]]), int(retries[row]))
            for row, index in enumerate(indices.tolist())]


def _digest(tasks: Sequence[Any], base_seed: int) -> str:
    """A digest of everything a list of ROME tasks' results depend on (see the module docstring)."""
    digest = hashlib.sha256(json.dumps({"format": FORMAT_VERSION, "seed": base_seed, "tasks": len(tasks),
                                        "estimator": ESTIMATOR, "setup": _setup()}, sort_keys=True).encode())
    for task in tasks:
        arrays = [task.fit, *task.queries]
        digest.update(struct.pack("<dq", float(task.min_std), len(arrays)) + str(task.kde).encode() + b"\0")
        for array in arrays:
            values = np.ascontiguousarray(array, dtype=np.float64)
            digest.update(struct.pack("<q", values.ndim) + struct.pack(f"<{values.ndim}q", *values.shape))
            digest.update(values.tobytes())
    return digest.hexdigest()[:24]


@functools.cache
def _setup() -> dict[str, str]:
    """The versions of the libraries a fit runs through and the processor model."""
    from ..util.provenance import machine_description

    versions = {}
    for package in ("scikit-learn", "numpy", "scipy"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = "absent"
    return {**versions, "machine": machine_description("cpu")}
