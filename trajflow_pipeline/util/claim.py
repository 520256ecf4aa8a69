"""Claims on work shared by several processes: who trains a run of an experiment, who writes its index.

A claim is an exclusive ``flock`` on a lock file. The operating system drops it when its holder exits for any
reason (a crash, ``kill -9``, the end of a session), so a claim can never go stale and needs no clean-up. Where
``fcntl`` is missing (Windows) there are no claims: :func:`claims_supported` is False and every claim succeeds, so
callers must then run one process per shared directory. A file system that refuses locks is a clear error.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from ..errors import TrajflowError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None  # type: ignore[assignment]


def claims_supported() -> bool:
    """Whether claims exclude other processes on this platform."""
    return fcntl is not None


@contextlib.contextmanager
def claim(lock_path: str | Path, *, wait: bool = False) -> Iterator[bool]:
    """Claim `lock_path` for the duration of the block: yields False when another holder has it (or, with `wait`,
    blocks until it is free and yields True).

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
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        except OSError as error:
            raise TrajflowError(f"{lock_path}: cannot lock ({error.strerror or error}); this file system does not "
                                "support file locks, so run one process per experiment directory") from None
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    finally:
        os.close(handle)
