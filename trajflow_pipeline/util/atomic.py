"""Atomic outputs: a result appears complete under its final name, or not at all.

Everything trajflow writes goes to a temporary sibling first and is renamed into place (a rename within one
directory is atomic on POSIX; a directory that replaces another is swapped in with one atomic exchange where the
system has one), so an interrupted run leaves either the old result or the new one. A temporary sibling's name
says which process made it, so what a killed run left in a folder is recognised and cleaned up (or, for an old
version set aside by the two-rename fallback, put back) by the next atomic write into that folder, or by opening a
dataset that is missing: :func:`recover`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import hashlib
import os
import re
import shutil
import socket
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from .progress import say

#: longest file name (bytes) that common file systems take (ext4, XFS, APFS, NTFS: 255)
NAME_MAX = 255
_RANDOM = 8  # random characters in a temporary name
#: the owner part's largest size in bytes: ``old-``, 12 hex of the host, a pid of up to 10 digits, two dashes
_OWNER_MAX = 28
#: a temporary sibling's name: the (perhaps cut) final name, then the owner (``old-`` when it holds an old version
#: set aside while its replacement moves in), the random part and any suffix
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.tmp-(?P<old>old-)?(?P<host>[0-9a-f]{12})-(?P<pid>[0-9]{1,10})-"
                        r"[a-z0-9_]{8}(?P<suffix>.*)", re.DOTALL)
#: how a long final name ends once cut to fit (see _tmp_prefix): the name it was cut from is not known
_CUT = re.compile(r"~[0-9a-f]{12}$")


@functools.cache
def _host_tag() -> str:
    """12 hex digits of this machine's name and process-id namespace: a pid identifies a process only on the
    machine, and in the container, that made it (containers may share a host name and a folder)."""
    try:
        namespace = str(os.stat("/proc/self/ns/pid").st_ino)
    except OSError:
        namespace = ""
    return hashlib.sha256(f"{socket.gethostname()}/{namespace}".encode()).hexdigest()[:12]


def _owner(old: bool = False) -> str:
    """``HOST-PID-``: this process, as written into the temporary names it makes (read at each call: forks)."""
    return f"{'old-' if old else ''}{_host_tag()}-{os.getpid()}-"


def _tmp_prefix(name: str, suffix: str = "") -> str:
    """``.NAME.tmp-`` for a temporary sibling of NAME, which will be followed by the owner, random characters
    and `suffix`.

    A final name near NAME_MAX is legal, so its temporary sibling must be too: NAME is then cut to what fits and
    a hash of the whole name keeps siblings of different long names apart.
    """
    prefix = f".{name}.tmp-"
    room = NAME_MAX - _OWNER_MAX - _RANDOM - len(os.fsencode(suffix))
    if len(os.fsencode(prefix)) <= room:
        return prefix
    raw = os.fsencode(name)  # the name's bytes as the file system sees them (undecodable bytes included)
    digest = hashlib.sha256(raw).hexdigest()[:12]
    keep = os.fsdecode(raw[:room - len(f".~{digest}.tmp-")])
    return f".{keep}~{digest}.tmp-"


def _tmp_sibling(path: Path, suffix: str = "", *, old: bool = False) -> Path:
    return path.with_name(f"{_tmp_prefix(path.name, suffix)}{_owner(old)}{uuid.uuid4().hex[:_RANDOM]}{suffix}")


def _alive(host: str, pid: int) -> bool:
    """Whether the process that made a temporary name may still be writing it (always true for another host's)."""
    if host != _host_tag() or pid == os.getpid() or os.name == "nt":  # Windows: signal 0 is CTRL_C_EVENT
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError, OSError):  # another user's, or not a pid: keep it
        return True
    return True


@dataclass(frozen=True)
class _Leftover:
    """A temporary sibling whose process is gone: what it is, and the final name it was for where known."""

    path: Path
    old: bool
    final: Path | None


def _leftovers(path: Path) -> list[_Leftover]:
    """The temporary siblings in `path`'s folder whose process is gone, newest first.

    The final name is `path` for siblings of `path`, and the name spelled in the sibling's own name for others
    (unknown where a long name was cut to fit).
    """
    try:
        entries = list(os.scandir(path.parent))
    except (FileNotFoundError, NotADirectoryError):
        return []
    own = {_tmp_prefix(path.name, suffix) for suffix in ("", path.suffix)}
    found = []
    for entry in entries:
        match = _TEMPORARY.fullmatch(entry.name)
        if match is None or _alive(match["host"], int(match["pid"])):
            continue
        final: Path | None = None
        if any(entry.name.startswith(prefix + (match["old"] or "")) for prefix in own):
            final = path
        elif not _CUT.search(match["name"]):
            final = path.parent / match["name"]
        found.append(_Leftover(Path(entry.path), bool(match["old"]), final))
    return sorted(found, key=lambda leftover: _mtime(leftover.path), reverse=True)


def _mtime(path: Path) -> int:
    try:
        return path.lstat().st_mtime_ns
    except OSError:  # removed meanwhile (another process recovering the same folder)
        return 0


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def recover(path: str | Path) -> None:
    """Clean up after interrupted writes in `path`'s folder, saying what it did.

    An old version that an interrupted replacement had set aside is put back where its final name is missing
    (the newest one, if several), and removed where the replacement is in place; every other temporary sibling
    whose process is gone is deleted. Called by every atomic write before it starts and by readers of a missing
    dataset. Temporaries of live processes, and those of other machines on a shared folder, are left alone.
    """
    path = Path(path)
    for leftover in _leftovers(path):
        if leftover.old and leftover.final is None:
            continue  # a cut long name: only a write or read of that name knows where it goes
        try:
            if leftover.old and not os.path.lexists(leftover.final):
                os.replace(leftover.path, leftover.final)
                say(("recovered", "yellow"), f" {leftover.final}: put back the previous version, which an "
                    f"interrupted replacement had left as {leftover.path.name}")
                continue
            _remove(leftover.path)
        except OSError:  # another process got there first, or it is not ours to remove: the write goes on
            continue
        if not os.path.lexists(leftover.path):
            what = "an old version already replaced" if leftover.old else "left by an interrupted run"
            say(("cleaned up", "yellow"), f" {leftover.path}: {what}")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` via a fsynced temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover(path)
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
    recover(path)
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
    recover(path)
    tmp = Path(tempfile.mkdtemp(prefix=_tmp_prefix(path.name) + _owner(), dir=path.parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if path.exists():
            if not replace:
                raise FileExistsError(path)
            _swap_in(tmp, path)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _swap_in(new: Path, path: Path) -> None:
    """Put directory `new` in the place of the existing `path` and delete the old one.

    With an atomic exchange (Linux renameat2) `path` always names a complete directory and `new` ends up holding
    the old one; elsewhere the old one is first renamed aside (a sibling marked ``old-``), which :func:`recover`
    puts back if the process dies before the second rename.
    """
    if _exchange(new, path):
        shutil.rmtree(new, ignore_errors=True)
        return
    old = _tmp_sibling(path, old=True)
    os.replace(path, old)
    os.replace(new, path)
    shutil.rmtree(old, ignore_errors=True)


_RENAME_EXCHANGE = 2  # linux/fs.h
_AT_FDCWD = -100


def _exchange(first: Path, second: Path) -> bool:
    """Atomically swap two existing paths (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    renameat2 = getattr(_libc(), "renameat2", None)
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(first), _AT_FDCWD, os.fsencode(second), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
        return False  # this system or file system cannot exchange: fall back to two renames
    raise OSError(code, os.strerror(code), str(second))


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library this process runs on (None where it cannot be loaded, e.g. on Windows)."""
    try:
        return ctypes.CDLL(None, use_errno=True)
    except (OSError, TypeError):
        return None


def _umask() -> int:
    """The process umask (read by setting and restoring it), so temporary dirs get normal permissions."""
    mask = os.umask(0)
    os.umask(mask)
    return mask
