"""Benchmark ROME fits: our batched estimator against romepy as installed and against a previous release's path.

    python bench/rome.py [--fits 200] [--rounds 3] [--previous WORKTREE]

Point sets of the two shapes evaluation fits most (100 draws x 12 steps = 100 x 24, 50 x 28): real 12-step ETH
futures (world metres, when TRAJFLOW_DATA has ETH/UCY) and synthetic multi-modal sets. Each round fits every set
through `trajflow_pipeline.metrics.parallel` in one process (clusterings and exact densities batched), through
romepy's ROME (one BLAS thread), and, with --previous (a `git worktree` of an earlier release), through that
release's `fit_and_score` in a subprocess on the very same sets; rounds alternate so that load hits all alike.
Our estimator runs twice, with the exact KDE (the default) and with the reference KDE (romepy's arithmetic through
scikit-learn). Prints the median fits per second of each, the ratios, whether the reference KDE's values equal
romepy's (and the earlier release's) bit for bit, and how many exact values differ from them by more than 1e-9.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# this file is bench/rome.py: keep its folder off the import path, so that `import rome` finds romepy
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from trajflow_pipeline.metrics import rome  # noqa: E402
from trajflow_pipeline.metrics.parallel import RomeTask, run_rome_tasks  # noqa: E402

PREVIOUS = """
import sys, time, numpy as np
sys.path.insert(0, sys.argv[1])
from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score
data = np.load(sys.argv[2])
tasks = [RomeTask(fit=f, queries=(q,)) for f, q in zip(data["fits"], data["queries"])]
start = time.perf_counter()
values = [fit_and_score(t, i)[0] for i, t in enumerate(tasks)]
print(time.perf_counter() - start)
np.save(sys.argv[3], np.stack(values))
"""


def point_sets(n_sets: int, n: int, dim: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(fits (n_sets, n, dim), queries (n_sets, 2, dim)): real ETH futures when available, else synthetic."""
    rng = np.random.default_rng(seed)
    path = Path(os.environ.get("TRAJFLOW_DATA", "/nonexistent")) / "eth_ucy" / "eth" / "test" / "biwi_eth.txt"
    steps = dim // 2
    if path.is_file():
        rows = np.loadtxt(path)
        pool = []
        for ped in np.unique(rows[:, 1]):
            track = rows[rows[:, 1] == ped]
            track = track[np.argsort(track[:, 0])]
            pool += [track[s:s + steps, 2:4].ravel() for s in range(0, len(track) - steps + 1, 2)
                     if np.all(np.diff(track[s:s + steps, 0]) == 10)]
        pool = np.array(pool)
        chosen = np.stack([rng.choice(len(pool), size=n + 2, replace=False) for _ in range(n_sets)])
        sets = pool[chosen]
    else:
        sets = rng.normal(size=(n_sets, n + 2, dim)) * rng.uniform(0.2, 3, size=(n_sets, 1, dim))
        sets[:, : n // 3] += 3.0
    return sets[:, :n], sets[:, n:]


def romepy_fits(fits: np.ndarray, queries: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(seconds, log-densities) through romepy as installed, or None when it is not."""
    try:
        from rome.ROME import ROME
    except ImportError:
        return None
    from threadpoolctl import threadpool_limits

    start = time.perf_counter()
    with threadpool_limits(limits=1):
        values = [ROME().fit(f).score_samples(q) for f, q in zip(fits, queries)]
    return time.perf_counter() - start, np.stack(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fits", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--previous", type=Path, help="a worktree of an earlier release, timed on the same sets")
    args = parser.parse_args()
    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; one process each")
    for n, dim in ((100, 24), (50, 28)):
        fits, queries = point_sets(args.fits, n, dim, seed=n + dim)
        kdes = {"ours": rome.KDE_EXACT, "ours-reference-kde": rome.KDE_REFERENCE}
        tasks = {name: [RomeTask(fit=f, queries=(q,), kde=kde) for f, q in zip(fits, queries)]
                 for name, kde in kdes.items()}
        times: dict[str, list[float]] = {**{name: [] for name in kdes}, "romepy": [], "previous": []}
        values: dict[str, np.ndarray] = {}
        for _ in range(args.rounds):
            for name in kdes:
                start = time.perf_counter()
                values[name] = np.stack([r[0] for r in run_rome_tasks(tasks[name], workers=1, quiet=True)])
                times[name].append(time.perf_counter() - start)
            reference = romepy_fits(fits, queries)
            if reference is not None:
                times["romepy"].append(reference[0])
                values["romepy"] = reference[1]
            if args.previous is not None:
                with tempfile.TemporaryDirectory() as tmp:
                    np.savez(Path(tmp) / "sets.npz", fits=fits, queries=queries)
                    out = subprocess.run([sys.executable, "-c", PREVIOUS, str(args.previous), f"{tmp}/sets.npz",
                                          f"{tmp}/values.npy"], check=True, capture_output=True, text=True)
                    times["previous"].append(float(out.stdout.strip().splitlines()[-1]))
                    values["previous"] = np.load(f"{tmp}/values.npy")
        rates = {k: args.fits / float(np.median(v)) for k, v in times.items() if v}
        line = ", ".join(f"{k} {rate:,.0f} fits/s" for k, rate in rates.items())
        ratios = ", ".join(f"{rates['ours'] / rate:.1f}x {k}" for k, rate in rates.items() if k != "ours")
        print(f"{n} x {dim}: {line}; ours = {ratios}")
        for other in ("romepy", "previous"):
            if other in values:
                same = np.array_equal(values["ours-reference-kde"], values[other])
                off = np.abs(values["ours"] - values[other]) > 1e-9 * np.abs(values[other])
                print(f"  against {other}: reference KDE {'bit-identical' if same else 'DIFFERENT'}; exact KDE "
                      f"differs by > 1e-9 relative at {int(off.sum())} of {off.size} values (docs/rome.md)")


if __name__ == "__main__":
    main()
