"""Process-level runtime settings for model work: device selection, the CPU memory allocator and CPU threads.

Sampling many futures allocates and frees tensors of tens of megabytes; glibc serves those with fresh ``mmap``
pages that the kernel must zero and fault in on every allocation, which on virtual machines costs more than the
arithmetic itself. :func:`tune_cpu_allocator` keeps freed memory in the process heap for reuse instead.

torch's OpenMP threads wait for work by spinning. When other processes already keep the cores busy, every thread
beyond the idle cores fights them for CPU time, and a training step can run 50 times slower than with one thread
(measured: a flow step at 42 instead of 2,149 samples/s beside two busy processes on 2 cores).
:func:`fit_threads_to_idle_cpus` chooses the thread count from what the machine leaves idle.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import torch

from ..errors import UsageError

Item = TypeVar("Item")
Result = TypeVar("Result")

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


def _cpu_times(stat: Path) -> tuple[int, int] | None:
    """(busy, total) jiffies of all CPUs from the first line of /proc/stat; None if it cannot be read."""
    try:
        fields = stat.read_text().split("\n", 1)[0].split()
        # user nice system idle iowait irq softirq steal [guest guest_nice]: guests are already counted in user
        values = [int(v) for v in fields[1:9]]
    except (OSError, ValueError, IndexError):
        return None
    if fields[0] != "cpu" or len(values) < 8:
        return None
    total = sum(values)
    return total - values[3] - values[4], total


def busy_cpus(interval_s: float = 0.2, *, stat: Path = Path("/proc/stat")) -> float | None:
    """How many CPUs other processes keep busy now, in CPUs (e.g. 1.9 of 2).

    Measured over `interval_s` from the kernel's CPU counters (Linux), while this process sleeps; elsewhere the
    one-minute load average; None where neither exists.
    """
    before = _cpu_times(stat)
    if before is not None:
        time.sleep(interval_s)
        after = _cpu_times(stat)
        if after is not None and after[1] > before[1]:
            return (os.cpu_count() or 1) * (after[0] - before[0]) / (after[1] - before[1])
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def fit_threads_to_idle_cpus(busy: float | None = None) -> tuple[int, int] | None:
    """Use no more torch threads than there are idle CPUs (at least one), given `busy` CPUs (measured if None).

    Returns (threads before, threads now) when the count was lowered, else None. Settings the user made through
    OMP_NUM_THREADS or MKL_NUM_THREADS are kept.
    """
    if os.environ.get("OMP_NUM_THREADS") or os.environ.get("MKL_NUM_THREADS"):
        return None
    threads = torch.get_num_threads()
    if busy is None:
        busy = busy_cpus()
    if busy is None or threads <= 1:
        return None
    idle = round((os.cpu_count() or threads) - busy)
    wanted = max(1, min(threads, idle))
    if wanted >= threads:
        return None
    torch.set_num_threads(wanted)
    return threads, wanted


def cpu_workers(device: torch.device) -> int:
    """How many Python threads :func:`map_in_threads` runs on `device`: torch's thread count on a CPU, else 1."""
    return torch.get_num_threads() if device.type == "cpu" else 1


def thread_chunks(items: int, rows_per_item: int, max_rows: int, workers: int) -> list[slice]:
    """Slices of `items` (each `rows_per_item` rows of work) for :func:`map_in_threads`: about `max_rows` rows each
    at most, their sizes within one item of each other and their count a multiple of `workers` where there are
    enough items, so that no thread waits for a longer last chunk; one empty slice for no items."""
    if items == 0:
        return [slice(0, 0)]
    count = -(-items * max(rows_per_item, 1) // max_rows)
    count = min(items, -(-count // workers) * workers)
    size, longer = divmod(items, count)
    starts = [index * size + min(index, longer) for index in range(count + 1)]
    return [slice(start, stop) for start, stop in zip(starts, starts[1:])]


def map_in_threads(fn: Callable[[Item], Result], items: Sequence[Item], device: torch.device) -> list[Result]:
    """[fn(item) for item in items], on a CPU with T > 1 torch threads run by T Python threads of one torch
    thread each (the global thread count is restored afterwards); elsewhere one after the other.

    For independent pieces of large no-grad work such as sampling's chunks: their kernels release the GIL, and
    two whole chunks side by side keep two cores busier than every kernel split in two (measured on the 2-core
    AMD EPYC, 100 draws for 1000 agents: 1.7-1.9x one thread, where torch's two threads on each chunk reached
    0.8-1.6x).
    Gradient mode, which is per thread in torch, is carried into the workers. torch's thread count is global to
    the process: torch work that other threads of the caller run meanwhile runs at one thread too."""
    workers = min(cpu_workers(device), len(items))
    if workers <= 1:
        return [fn(item) for item in items]
    grad = torch.is_grad_enabled()

    def call(item: Item) -> Result:
        with torch.set_grad_enabled(grad):
            return fn(item)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers, thread_name_prefix="trajflow-chunk") as pool:
            return list(pool.map(call, items))
    finally:
        torch.set_num_threads(threads)


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
