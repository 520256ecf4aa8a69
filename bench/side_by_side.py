"""Figures of a bench script for this checkout and for another tree (an earlier release's `git worktree`), measured
in alternating rounds of subprocesses in one run, so that both meet the same machine; the best of each is kept.

A script taking part accepts ``--figures-json`` (print its figures as one JSON line: name -> [value, "rate" or
"time"]) and calls :func:`report_side_by_side` when given ``--against TREE``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def figures(script: Path, args: list[str], tree: Path) -> dict[str, tuple[float, str]]:
    """One run of `script` (this checkout's file) against the package in `tree`; its figures. The run's notes
    (stderr lines starting with "# ", e.g. compile times) are passed on, prefixed with the tree."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, str(script), *args, "--figures-json"], env=env, check=True,
                          capture_output=True, text=True)
    for line in done.stderr.splitlines():
        if line.startswith("# "):
            print(f"# {tree}: {line[2:]}", flush=True)
    return {name: (float(value), kind) for name, (value, kind) in json.loads(done.stdout.splitlines()[-1]).items()}


def report_side_by_side(script: Path, args: list[str], against: Path, rounds: int) -> None:
    """Print each figure for this checkout and for `against`, best of `rounds` alternating rounds, and the ratio
    (how many times faster this checkout is)."""
    best: dict[str, dict[str, float]] = {"this": {}, "other": {}}
    kinds: dict[str, str] = {}
    for _ in range(rounds):
        for label, tree in (("this", HERE), ("other", against.resolve())):
            for name, (value, kind) in figures(script, args, tree).items():
                kinds[name] = kind
                keep = max if kind == "rate" else min
                best[label][name] = keep(best[label].get(name, value), value)
    print(f"best of {rounds} alternating rounds; this checkout ({HERE}) against {against}; load average "
          f"{os.getloadavg()[0]:.2f} at the end")
    print(f"{'figure':52s} {'this':>12s} {'other':>12s} {'speed-up':>9s}")
    for name, kind in kinds.items():
        this, other = best["this"][name], best["other"][name]
        ratio = this / other if kind == "rate" else other / this
        print(f"{name:52s} {this:>12,.3f} {other:>12,.3f} {ratio:>8.2f}x")
