"""Benchmark the metric library: seconds per 1,000 evaluated agents, serial vs parallel ROME fits.

    python bench/eval.py [--agents 100] [--samples 100] [--steps 12] [--workers 2] [--joint 0] [--rounds 3]

Synthetic pedestrian-like problems (metres, 0.4 s steps): a ground-truth future per agent and `samples`
predicted futures around it in three modes (straight, veer left, veer right) with noise growing over the
horizon. Evaluates minADE/minFDE (K=20) and NLL (one ROME fit per agent on samples x steps*2 points; this
dominates) — plus joint minADE/minFDE/NLL over scenes of `--joint` agents when given — once with
workers=1 and once with `--workers`, alternating for `--rounds` rounds (so that load from other programs on
a shared machine hits both alike), checks that the tables are identical, and prints the median seconds per
1,000 agents for each and their ratio. Parallel times include starting the worker processes (the first
round also starts the forkserver that imports ROME once).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from trajflow_pipeline.metrics import compute_metrics


def synthetic_problems(n_agents: int, n_samples: int, n_steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(pred (A, S, T, 2), gt (A, T, 2)) for pedestrian-like agents with a three-mode predictor."""
    rng = np.random.default_rng(seed)
    dt = 0.4
    speed = rng.uniform(0.8, 1.6, size=(n_agents, 1))
    heading = rng.uniform(-np.pi, np.pi, size=(n_agents, 1))
    turn = rng.normal(0.0, 0.05, size=(n_agents, n_steps))
    angle = heading + np.cumsum(turn, axis=1)
    gt = np.cumsum(np.stack([np.cos(angle), np.sin(angle)], axis=-1) * speed[..., None] * dt, axis=1)
    mode = rng.integers(0, 3, size=(n_agents, n_samples, 1)) - 1             # -1, 0, +1: right, straight, left
    veer = mode * 0.08 * np.arange(1, n_steps + 1)                            # radians, growing over the horizon
    pred_angle = angle[:, None] + veer + rng.normal(0.0, 0.03, size=(n_agents, n_samples, n_steps))
    pred_speed = speed[:, None] * rng.normal(1.0, 0.1, size=(n_agents, n_samples, 1))
    step = np.stack([np.cos(pred_angle), np.sin(pred_angle)], axis=-1) * pred_speed[..., None] * dt
    pred = np.cumsum(step, axis=2)
    return pred, gt


def main() -> None:
    """Parse arguments, time serial and parallel evaluation, print per-1,000-agent seconds and the ratio."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=100, help="agents evaluated per run (default 100)")
    parser.add_argument("--samples", type=int, default=100, help="drawn samples per agent (default 100)")
    parser.add_argument("--steps", type=int, default=12, help="future steps (default 12)")
    parser.add_argument("--workers", type=int, default=2, help="processes of the parallel run (default 2)")
    parser.add_argument("--joint", type=int, default=0, help="agents per scene for joint metrics (0: none)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating serial / parallel rounds (default 3)")
    args = parser.parse_args()

    pred, gt = synthetic_problems(args.agents, args.samples, args.steps)
    metrics = ["min_ade", "min_fde", "nll"]
    joint_key = None
    if args.joint > 0:
        metrics += ["min_ade_joint", "min_fde_joint", "nll_joint"]
        joint_key = np.arange(args.agents) // args.joint
    print(f"{args.agents} agents x {args.samples} samples x {args.steps} steps; metrics {', '.join(metrics)}; "
          f"{os.cpu_count()} cores")

    timings: dict[int, list[float]] = {1: [], args.workers: []}
    tables = {}
    for round_index in range(args.rounds):  # alternate serial / parallel so that load from others hits both
        for workers in (1, args.workers):
            start = time.perf_counter()
            tables[workers] = compute_metrics(pred, gt, joint_key=joint_key, metrics=metrics, workers=workers,
                                              quiet=True)
            timings[workers].append(time.perf_counter() - start)
            print(f"round {round_index + 1}, workers={workers}: {timings[workers][-1]:.1f} s "
                  f"(load average {os.getloadavg()[0]:.2f})")
        if not tables[1].equals(tables[args.workers]):
            raise SystemExit("serial and parallel results differ")
    per_1000 = {w: float(np.median(t)) / args.agents * 1000 for w, t in timings.items()}
    print(f"serial:     {per_1000[1]:.1f} s per 1,000 agents (median of {args.rounds})")
    print(f"workers={args.workers}: {per_1000[args.workers]:.1f} s per 1,000 agents (median of {args.rounds}, "
          "including worker start-up)")
    print(f"ratio serial / parallel: {per_1000[1] / per_1000[args.workers]:.2f}x; tables identical: True")


if __name__ == "__main__":
    main()
