"""Process-level runtime settings for model work: device selection and the CPU memory allocator.

Sampling many futures allocates and frees tensors of tens of megabytes; glibc serves those with fresh ``mmap``
pages that the kernel must zero and fault in on every allocation, which on virtual machines costs more than the
arithmetic itself. :func:`tune_cpu_allocator` keeps freed memory in the process heap for reuse instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

import torch

from ..errors import UsageError

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_tuned = False


def tune_cpu_allocator() -> bool:
    """Make glibc reuse freed heap memory instead of unmapping it (Linux/glibc only; idempotent).

    Returns whether the setting was applied. Memory stays reserved by the process after large tensors are freed,
    which is what a long-running training or sampling process wants anyway.
    """
    global _tuned
    if _tuned:
        return True
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_MAX, 0) == 1 and libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    except (OSError, AttributeError):
        return False
    _tuned = ok
    return ok


def resolve_device(name: str, local_rank: int | None = None) -> torch.device:
    """``auto`` -> CUDA when available (the local rank's GPU under torchrun), else CPU; explicit names checked."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", local_rank or 0)
        return torch.device("cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UsageError(f"device {name!r} requested but CUDA is not available")
        device = torch.device(name)
        if device.index is None:
            device = torch.device("cuda", local_rank or 0)
        if device.index >= torch.cuda.device_count():
            raise UsageError(f"device {name!r} does not exist ({torch.cuda.device_count()} CUDA device(s))")
        return device
    raise UsageError(f"unknown device {name!r}; use auto, cpu, cuda or cuda:N")
