"""Which code and which machine produced a result: the git commit of the running trajflow source, when it runs
from a checkout, and the processor or GPU model.

A run trained over several sessions may be continued by newer code; `trajflow train` keeps the list of revisions
that trained it (run.json ``code_revisions``) and `trajflow eval` records the one that evaluated it, so a number in
a report can be traced to code as well as to config and data.

A revision is the full commit hash, with ``+changes.<hash>`` when the package's own files (``trajflow_pipeline/``,
untracked modules included, and ``pyproject.toml``) differ from that commit (the hash tells two different sets of
changes apart), or ``+unknown`` when git could not say. The code runs without a revision (None, recorded as
"unknown" in a run's list) outside a git checkout; "unrecorded" stands for training done before revisions were kept.
The revision is read once per process, when training or evaluation starts. Machines are recorded the same way
(run.json ``machines``, eval.json ``machine``), so a result says which hardware produced it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import subprocess
from pathlib import Path

#: the revision recorded for training done before trajflow kept revisions
UNRECORDED = "unrecorded"
#: what a run's list records for code that has no revision (not a git checkout)
UNKNOWN = "unknown"
#: the paths whose changes make the running code differ from its commit
_PACKAGE_PATHS = ("trajflow_pipeline", "pyproject.toml")


@functools.cache
def code_revision() -> str | None:
    """The revision of the checkout this package runs from (see the module docstring); cached per process."""
    return revision_of(Path(__file__).resolve().parents[2])


def revision_of(root: Path) -> str | None:
    """The revision of the trajflow source at `root`, None when `root` is not the top of a git checkout of it."""
    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "--no-optional-locks", "-C", str(root), *args], capture_output=True,
                                  text=True, timeout=20, env=environment)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout if done.returncode == 0 else None

    # Inherited GIT_* variables (GIT_DIR, GIT_WORK_TREE...) would point git at another repository.
    environment = {key: value for key, value in os.environ.items() if not key.startswith("GIT_")}
    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top.strip()).resolve() != root.resolve() or not (root / "trajflow_pipeline").is_dir():
        return None
    sha = git("rev-parse", "HEAD")
    if sha is None:
        return None
    status = git("status", "--porcelain", "--untracked-files=all", "--", *_PACKAGE_PATHS)
    diff = git("diff", "HEAD", "--", *_PACKAGE_PATHS)
    if status is None or diff is None:
        return f"{sha.strip()}+unknown"
    if not status.strip():
        return sha.strip()
    digest = hashlib.sha256(diff.encode())
    for line in sorted(status.splitlines()):
        if line.startswith("??"):  # untracked: its content is part of what runs
            path = root / line[3:].strip()
            digest.update(line.encode() + (path.read_bytes() if path.is_file() else b""))
    return f"{sha.strip()}+changes.{digest.hexdigest()[:12]}"


def revisions_after(previous: list[str] | None) -> list[str]:
    """The revisions that trained a run, once the current code takes over from `previous` (None: training that
    started before revisions were kept, recorded as UNRECORDED)."""
    return appended(previous, code_revision() or UNKNOWN)


def machines_after(previous: list[str] | None, device: str) -> list[str]:
    """The machines that trained a run, once this one (training on `device`) takes over from `previous`."""
    return appended(previous, machine_description(device))


def appended(previous: list[str] | None, current: str) -> list[str]:
    """`previous` (None: before such records were kept, UNRECORDED) followed by `current` unless it is the last."""
    history = [UNRECORDED] if previous is None else list(previous)
    return history if history and history[-1] == current else [*history, current]


def machine_description(device: str) -> str:
    """What computes on `device` ("cpu", "cuda:0"...): the processor's or the GPU's model and how many cores or
    GPUs the machine has, e.g. "CPU: AMD EPYC 7B13, 2 cores" or "GPU: NVIDIA H200 (1 of 1)"."""
    if device.startswith("cuda"):
        import torch

        index = torch.device(device).index or 0
        return f"GPU: {torch.cuda.get_device_name(index)} ({index + 1} of {torch.cuda.device_count()})"
    return f"CPU: {_processor_name()}, {os.cpu_count() or '?'} cores"


@functools.cache
def _processor_name() -> str:
    """The CPU model (Linux: /proc/cpuinfo; elsewhere what the platform module knows)."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name") and ":" in line:
                return " ".join(line.split(":", 1)[1].split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown processor"
