"""Atomic outputs: a result appears complete under its final name, or not at all.

Everything trajflow writes goes to a temporary sibling first and is renamed into place (a rename within one
directory is atomic on POSIX), so an interrupted run leaves either the old result or the new one.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path


#: longest file name (bytes) that common file systems take (ext4, XFS, APFS, NTFS: 255)
NAME_MAX = 255
_RANDOM = 8  # random characters in a temporary name


def _tmp_prefix(name: str, suffix: str = "") -> str:
    """``.NAME.tmp-`` for a temporary sibling of NAME, which will be followed by random characters and `suffix`.

    A final name near NAME_MAX is legal, so its temporary sibling must be too: NAME is then cut to what fits and
    a hash of the whole name keeps siblings of different long names apart.
    """
    prefix = f".{name}.tmp-"
    room = NAME_MAX - _RANDOM - len(os.fsencode(suffix))
    if len(os.fsencode(prefix)) <= room:
        return prefix
    raw = os.fsencode(name)  # the name's bytes as the file system sees them (undecodable bytes included)
    digest = hashlib.sha256(raw).hexdigest()[:12]
    keep = os.fsdecode(raw[:room - len(f".~{digest}.tmp-")])
    return f".{keep}~{digest}.tmp-"


def _tmp_sibling(path: Path, suffix: str = "") -> Path:
    return path.with_name(f"{_tmp_prefix(path.name, suffix)}{uuid.uuid4().hex[:_RANDOM]}{suffix}")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` via a fsynced temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(path)
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write a file to; it is renamed to `path` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(path, path.suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_directory(path: str | Path, *, replace: bool = True) -> Iterator[Path]:
    """Yield a fresh temporary directory that becomes `path` only when the block completes.

    An existing `path` is swapped out only after the new directory is complete (when `replace` is true), and
    removed afterwards; on failure the temporary directory is deleted and `path` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=_tmp_prefix(path.name), dir=path.parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if path.exists():
            if not replace:
                raise FileExistsError(path)
            old = _tmp_sibling(path, ".old")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _umask() -> int:
    """The process umask (read by setting and restoring it), so temporary dirs get normal permissions."""
    mask = os.umask(0)
    os.umask(mask)
    return mask
