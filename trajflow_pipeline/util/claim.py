"""Claims on work shared by several processes: who trains a run of an experiment.

A claim is an exclusive, non-blocking ``flock`` on a lock file. The operating system drops it when its holder
exits for any reason (a crash, ``kill -9``, the end of a session), so a claim can never go stale and needs no
clean-up. Where ``fcntl`` is missing (Windows) every claim succeeds: one process per experiment directory there.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None  # type: ignore[assignment]


@contextlib.contextmanager
def claim(lock_path: str | Path) -> Iterator[bool]:
    """Try to claim `lock_path` for the duration of the block; yields False when another holder has it.

    The lock file stays behind (removing it would race with a process about to lock it); it holds no data.
    """
    lock_path = Path(lock_path)
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    handle = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        if fcntl is None:
            yield True
            return
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    finally:
        os.close(handle)
