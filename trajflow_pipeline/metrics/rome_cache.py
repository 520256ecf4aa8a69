"""Finished ROME fits kept on disk while an evaluation runs, so that an interrupted one resumes where it stopped.

The ROME fits are most of an evaluation's time (an hour and more for a large test fold on one core), and a fit's
result depends only on its task and seed (see :mod:`trajflow_pipeline.metrics.parallel`). So finished fits are
saved in parts, each written atomically, under ``ROOT/<digest>/``, where the digest covers every task's points,
queries and options and the seed: a rerun over the very same tasks loads them and fits only the rest, while any
other task list (other predictions, other metrics, another model) gets a directory of its own and never mixes.
The caller removes ROOT once its results are safely written.
"""

from __future__ import annotations

import hashlib
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..util.atomic import atomic_file

#: one finished task: its index, its log-density arrays (one per query) and its count of PCA retries
Finished = tuple[int, tuple[tuple[np.ndarray, ...], int]]


class RomeCache:
    """The saved results of one list of ROME tasks (see the module docstring)."""

    def __init__(self, root: Path, tasks: Sequence[object], base_seed: int) -> None:
        self.directory = Path(root) / _digest(tasks, base_seed)

    def load(self) -> dict[int, tuple[tuple[np.ndarray, ...], int]]:
        """Every finished task saved so far (index -> result); a part that cannot be read is left out (its tasks
        are simply fitted again)."""
        finished: dict[int, tuple[tuple[np.ndarray, ...], int]] = {}
        for part in sorted(self.directory.glob("part-*.npz")):
            try:
                with np.load(part) as saved:
                    indices, retries, counts = saved["indices"], saved["retries"], saved["n_queries"]
                    arrays = np.split(saved["values"], np.cumsum(saved["lengths"])[:-1])
            except (OSError, ValueError, KeyError):
                continue
            starts = np.concatenate(([0], np.cumsum(counts)))
            for row, index in enumerate(indices.tolist()):
                finished[int(index)] = (tuple(arrays[starts[row]:starts[row + 1]]), int(retries[row]))
        return finished

    def save(self, finished: list[Finished]) -> None:
        """Add finished tasks as one more part, written atomically."""
        if not finished:
            return
        queries = [values for _, (values, _) in finished]
        self.directory.mkdir(parents=True, exist_ok=True)
        with atomic_file(self.directory / f"part-{uuid.uuid4().hex}.npz") as tmp:
            with open(tmp, "wb") as handle:
                np.savez(handle,
                         indices=np.array([index for index, _ in finished], dtype=np.int64),
                         retries=np.array([retried for _, (_, retried) in finished], dtype=np.int64),
                         n_queries=np.array([len(v) for v in queries], dtype=np.int64),
                         lengths=np.array([len(a) for v in queries for a in v], dtype=np.int64),
                         values=np.concatenate([np.asarray(a, dtype=np.float64).ravel() for v in queries for a in v]
                                               or [np.zeros(0)]))


def _digest(tasks: Sequence[object], base_seed: int) -> str:
    """A digest of everything a list of ROME tasks' results depend on."""
    digest = hashlib.sha256(f"rome-tasks v1 seed={base_seed} n={len(tasks)}".encode())
    for task in tasks:
        fit, queries = task.fit, task.queries  # type: ignore[attr-defined]
        digest.update(f"|{fit.shape}|{task.min_std!r}|{len(queries)}".encode())  # type: ignore[attr-defined]
        digest.update(np.ascontiguousarray(fit, dtype=np.float64).tobytes())
        for query in queries:
            digest.update(f"|{query.shape}".encode())
            digest.update(np.ascontiguousarray(query, dtype=np.float64).tobytes())
    return digest.hexdigest()[:24]
