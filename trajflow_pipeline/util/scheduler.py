"""Where independent tasks run: worker processes on this machine, or tasks on a Ray cluster.

Both backends are a :class:`concurrent.futures.Executor` with a `capacity` (how many tasks run at once): callers
submit top-level functions and wait on the futures (``as_completed``), so the experiment's runs and the
evaluation's ROME batches are scheduled the same way whichever backend runs them: a caller chooses one by
constructing it.

:class:`LocalPool` is a process pool whose workers are never forked from the caller (the caller may have live
OpenMP threads, and forking those can deadlock the child): they come from a 'forkserver' (a fresh interpreter that
has imported `preload` once and forks each worker cheaply) or from 'spawn'. Each worker ends with the process that
started it, however that ends (:func:`exit_with_parent`), ignores Ctrl-C while idle (a running task is interrupted
as usual), so an interrupted pool leaves no orphan and no traceback per idle worker.

:class:`RayPool` submits each task as a Ray task asking for its :class:`Resources`. Ray is imported only here and
only when a RayPool is made, so nothing else changes, or loads Ray, without one. A task whose worker died (the
process killed, its node lost) is run again by Ray up to `retries` times; an exception the task raises is never
retried (it would fail again) and comes back as the task's own exception, not Ray's wrapper. Ray's workers need
trajflow importable (the same environment on every node) and any paths a task is given on a file system they share.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

from ..errors import TrajflowError, UsageError

#: the --ray value that starts a Ray instance on this machine rather than connecting to a running cluster
RAY_LOCAL = "local"


@dataclass(frozen=True)
class Resources:
    """What one task asks of a Ray cluster: CPUs and GPUs (Ray schedules by these and hides the other GPUs)."""

    cpus: float = 1.0
    gpus: float = 0.0


def exit_with_parent(grace_s: float = 30.0) -> None:
    """End this worker as soon as the process that started it ends, however it ends (a SIGTERM or SIGKILL to the
    parent alone leaves its workers running otherwise, holding what they claimed): an interrupt first, so that
    temporary files are cleaned up and pools shut down, then a kill after `grace_s` seconds."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(grace_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _start_worker(initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
    """A LocalPool worker's start: tied to its parent, Ctrl-C ignored until a task runs, then `initializer`."""
    exit_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if initializer is not None:
        initializer(*initargs)


def _interruptible(fn: Callable[..., Any], args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
    """Run one task of a LocalPool worker with Ctrl-C (and the parent-death interrupt) raising KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return fn(*args, **kwargs)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class LocalPool(ProcessPoolExecutor):
    """`workers` processes on this machine (see the module docstring)."""

    def __init__(self, workers: int, *, preload: Sequence[str] = (), initializer: Callable[..., None] | None = None,
                 initargs: tuple[Any, ...] = ()) -> None:
        if preload and "forkserver" in multiprocessing.get_all_start_methods():
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(list(preload))
        else:
            context = multiprocessing.get_context("spawn")
        super().__init__(max_workers=workers, mp_context=context, initializer=_start_worker,
                         initargs=(initializer, initargs))
        self.capacity = workers

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        return super().submit(_interruptible, fn, args, kwargs)


def _ray() -> Any:
    """The ray module, or a usage error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise UsageError("--ray needs Ray, which is not installed: pip install -e '.[ray]'") from None
    return ray


def connect_ray(address: str) -> Any:
    """Connect this process to the Ray cluster at `address` ('auto': the one `ray start` made on this machine, or
    HOST:PORT, or ray://HOST:PORT; 'local': start a private one here) once, and return the ray module. A process
    already connected (a Ray worker, a test's instance) stays on its cluster."""
    ray = _ray()
    if ray.is_initialized():
        return ray
    try:
        ray.init(address=None if address == RAY_LOCAL else address, include_dashboard=False,
                 logging_level=logging.WARNING, log_to_driver=True)
    except (ConnectionError, ValueError, RuntimeError) as error:
        raise TrajflowError(f"--ray {address}: cannot connect to a Ray cluster ({one_line(error)}); start one with "
                            f"`ray start --head`, or use --ray {RAY_LOCAL} for a Ray instance on this "
                            "machine") from None
    return ray


def cluster_resources(address: str) -> Resources:
    """The CPUs and GPUs of the whole Ray cluster at `address` (connecting first)."""
    total = connect_ray(address).cluster_resources()
    return Resources(cpus=float(total.get("CPU", 0.0)), gpus=float(total.get("GPU", 0.0)))


class _RayFuture(Future):
    """A Future for one Ray task: cancelling it cancels the task (the task sees a KeyboardInterrupt)."""

    def __init__(self, ray: Any, ref: Any) -> None:
        super().__init__()
        self._ray, self._ref = ray, ref

    def cancel(self) -> bool:
        if not self.done():
            self._ray.cancel(self._ref)
        return super().cancel()


class RayPool(Executor):
    """Tasks on the Ray cluster at `address`, each asking for `resources`; a task whose worker died is run again up
    to `retries` times (see the module docstring)."""

    def __init__(self, address: str, resources: Resources = Resources(), *, retries: int = 0) -> None:
        self._ray = connect_ray(address)
        self.address, self.resources, self.retries = address, resources, retries
        total = self._ray.cluster_resources()
        limits = [float(total.get(kind, 0.0)) // asked for kind, asked in (("CPU", resources.cpus),
                                                                          ("GPU", resources.gpus)) if asked > 0]
        self.capacity = max(1, int(min(limits, default=1)))
        self._remote: dict[Callable[..., Any], Any] = {}
        self._futures: list[_RayFuture] = []

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        remote = self._remote.get(fn)
        if remote is None:
            remote = self._remote[fn] = self._ray.remote(fn).options(
                num_cpus=self.resources.cpus, num_gpus=self.resources.gpus, max_retries=self.retries,
                retry_exceptions=False)
        ref = remote.remote(*args, **kwargs)
        future = _RayFuture(self._ray, ref)
        ref.future().add_done_callback(_copy_outcome(future, self._ray))
        self._futures.append(future)
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if cancel_futures:
            for future in self._futures:
                future.cancel()
        if wait:
            for future in self._futures:
                if not future.cancelled():
                    future.exception()  # waits; the outcome stays with the future
        self._futures = []

    def __exit__(self, exc_type: Any, exc: Any, traceback: Any) -> bool:
        # interrupted or failed: the tasks still queued or running are of no use, so they are cancelled, not awaited
        self.shutdown(wait=exc_type is None, cancel_futures=exc_type is not None)
        return False


def _copy_outcome(target: _RayFuture, ray: Any) -> Callable[[Future], None]:
    """A done-callback that hands a Ray future's outcome to `target`, with a task's own exception in place of
    Ray's wrapper of it (so a DataError raised on a worker is a DataError here, with its one-line message)."""

    def copy(source: Future) -> None:
        if target.cancelled():
            return
        try:
            result = source.result()
        except ray.exceptions.RayTaskError as error:
            cause = getattr(error, "cause", None)
            target.set_exception(cause if isinstance(cause, BaseException) else error)
        except BaseException as error:  # the worker died beyond its retries, the task was cancelled, ...
            target.set_exception(error)
        else:
            target.set_result(result)

    return copy


def one_line(error: BaseException) -> str:
    """The first line of an error's message (its type when it has none), for a report of failed tasks."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
