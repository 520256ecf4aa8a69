"""Which code produced a result: the git commit of the running trajflow source, when it runs from a checkout.

A run trained over several sessions may be continued by newer code; `trajflow train` keeps the list of revisions
that trained it (run.json ``code_revisions``) and `trajflow eval` records the one that evaluated it, so a number in
a report can be traced to code as well as to config and data. An installed copy outside a git checkout has no
revision (None); its version number is recorded as before.
"""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

#: the revision recorded for training done before trajflow kept revisions
UNRECORDED = "unrecorded"


@functools.cache
def code_revision() -> str | None:
    """The commit of the checkout this package runs from ("<sha>", or "<sha>+changes" when tracked files differ
    from it), None when the package does not run from a git checkout or git is not available."""
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != root or not (root / "trajflow_pipeline").is_dir():
        return None
    sha = git("rev-parse", "--short=12", "HEAD")
    if sha is None:
        return None
    changes = git("status", "--porcelain", "--untracked-files=no")
    return f"{sha}+changes" if changes else sha


def revisions_after(previous: list[str] | None) -> list[str]:
    """The revisions that trained a run, once the current code takes over from `previous` (None: training that
    started before revisions were kept, recorded as UNRECORDED)."""
    revisions = [UNRECORDED] if previous is None else list(previous)
    current = code_revision() or "unknown"
    return revisions if revisions and revisions[-1] == current else [*revisions, current]
