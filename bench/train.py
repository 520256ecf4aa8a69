"""Training throughput and sampling latency of the models (figures printed; not a timed test).

    python bench/train.py                      # CPU with 2 threads, and CUDA when available
    python bench/train.py --threads 1 --repeats 5 --models trajflow
    python bench/train.py --no-cpu             # CUDA only
    python bench/train.py --models trajflow --against ../release   # against an earlier release's worktree
    python bench/train.py --models trajflow --compile-flow         # flow stage compiled (train.compile_flow)
    python bench/train.py --models trajflow --sampling-only --against ../release --rounds 4

Training: samples/s of one optimisation step per stage (loss, backward, finiteness check, fused AdamW) at batch
128 on ETH/UCY-shaped problems (8 past, 12 future steps) with up to 0, 8 and 24 neighbours (80% of them present).
Sampling: wall time of ``model.sample(batch, 100)`` for 1000 agents (up to 8 neighbours each), which returns the
log-likelihood of every sample.
Each figure is the best of ``--repeats`` timed rounds, so that noise from other processes inflates it least; the
load average printed with the figures says how busy the machine was. Beside wall-clock rates the bench prints
rates per CPU-second of this process: with one thread that approximates an idle machine's wall time.
With ``--against TREE`` the figures of this checkout and of the package in TREE are measured in alternating
subprocess rounds (``--rounds``) and printed side by side with their ratio (bench/side_by_side.py).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import torch

from trajflow_pipeline.model import DataSpec, ModelConfig, build_model, tune_cpu_allocator
from trajflow_pipeline.model.toy import crowd_batch
from release_compat import adamw, compile_flow_stage, finite_gradients, with_fixed_targets

SPEC = DataSpec(n_past=8, n_future=12, dataset="bench", dt=0.4)


def best_time(fn: Callable[[], object], repeats: int, inner: int, sync: Callable[[], None]) -> tuple[float, float]:
    """Best mean wall seconds and best mean process CPU seconds per call of `fn` over `repeats` rounds.

    With one thread, CPU seconds approximate the wall time on an idle machine even when other processes compete.
    """
    fn()
    sync()
    wall = cpu = float("inf")
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        for _ in range(inner):
            fn()
        sync()
        wall = min(wall, (time.perf_counter() - start) / inner)
        cpu = min(cpu, (time.process_time() - start_cpu) / inner)
    return wall, cpu


#: set by --compile-flow: the flow stage's steps run compiled (train.compile_flow = "on"), where the tree has it
COMPILE_FLOW = False
#: set by --sampling-only: the training figures are skipped
SAMPLING_ONLY = False


def freeze_all_but(model: torch.nn.Module, stage: str) -> list[torch.nn.Parameter]:
    """The parameters `stage` trains, the only ones left requiring gradients (as the training loop does)."""
    params = model.stage_parameters(stage)
    keep = {id(p) for p in params}
    for p in model.parameters():
        p.requires_grad_(id(p) in keep)
    return params


def training_step(model: torch.nn.Module, stage: str, batch_size: int, neighbours: int,
                  device: torch.device) -> Callable[[], None]:
    """One training step of `stage` on a fixed batch of `batch_size` problems with up to `neighbours` neighbours:
    loss, backward, finiteness check, fused AdamW. Call after :func:`freeze_all_but` and any compilation."""
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = adamw(params, 1e-4, 1e-5)
    batch = with_fixed_targets(model, stage, crowd_batch(batch_size, neighbours=neighbours, seed=1).to(device))

    def step() -> None:
        loss = model.stage_loss(stage, batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if finite_gradients(params, 0.0):
            optimizer.step()

    return step


def training_rate(name: str, stage: str, neighbours: int, device: torch.device, repeats: int,
                  sync: Callable[[], None]) -> tuple[float, float]:
    """Samples per second of the training step of `stage` at batch 128 (by wall time, by CPU time)."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name), SPEC).to(device).train()
    freeze_all_but(model, stage)
    if COMPILE_FLOW and stage == "flow":
        compile_flow_stage(model, 128, f"{name} {stage} {neighbours} neighbours")
    wall, cpu = best_time(training_step(model, stage, 128, neighbours, device), repeats, 10, sync)
    return 128 / wall, 128 / cpu


def sampling_latency(name: str, device: torch.device, repeats: int,
                     sync: Callable[[], None]) -> tuple[float, float]:
    """Seconds (wall, CPU) to draw 100 futures with log-likelihoods for each of 1000 agents."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name), SPEC).to(device).eval()
    batch = crowd_batch(1000, neighbours=8, seed=2).without_future().to(device)
    if name == "cv":
        model.fit_stage("fit", crowd_batch(1000, neighbours=0, seed=3).to(device))
    generator = torch.Generator(device=device).manual_seed(0)

    def draw() -> None:
        trajectories, log_lik = model.sample(batch, 100, generator=generator)
        assert trajectories.shape == (1000, 100, 12, 2) and log_lik.shape == (1000, 100)

    return best_time(draw, repeats, 1, sync)


def figures(device: torch.device, models: list[str], repeats: int) -> dict[str, list]:
    """The figures of :func:`run` as name -> [value, "rate" | "time"] (wall clock), for side-by-side runs."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    out: dict[str, list] = {}
    for name in models:
        for stage in [] if SAMPLING_ONLY else [s for s in build_model(ModelConfig(name=name), SPEC).stages
                                               if s != "fit"]:
            for neighbours in (0, 8, 24):
                wall, _ = training_rate(name, stage, neighbours, device, repeats, sync)
                out[f"{name} {stage} {neighbours} neighbours, samples/s"] = [wall, "rate"]
        out[f"{name} sampling 100 x 1000 agents, s"] = [sampling_latency(name, device, repeats, sync)[0], "time"]
    return out


def run(device: torch.device, models: list[str], repeats: int) -> None:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    label = f"{device}" + (f", {torch.get_num_threads()} threads" if device.type == "cpu" else "")
    print(f"\n== {label}; load average {os.getloadavg()[0]:.2f} ==")
    print(f"{'model':16s} {'stage':12s} {'neighbours':>10s} {'samples/s':>12s} {'per CPU-s':>12s}")
    for name in models:
        stages = [s for s in build_model(ModelConfig(name=name), SPEC).stages if s != "fit"]
        for stage in [] if SAMPLING_ONLY else stages:
            for neighbours in (0, 8, 24):
                wall, cpu = training_rate(name, stage, neighbours, device, repeats, sync)
                print(f"{name:16s} {stage:12s} {neighbours:>10d} {wall:>12,.0f} {cpu:>12,.0f}")
    print(f"{'model':16s} {'sampling 100 x 1000 agents, with log-likelihoods: wall s':>58s} {'CPU s':>8s}")
    for name in models:
        wall, cpu = sampling_latency(name, device, repeats, sync)
        print(f"{name:16s} {wall:>58.3f} {cpu:>8.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[2], help="torch CPU thread counts (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds per figure; the best is printed")
    parser.add_argument("--models", nargs="+", default=["trajflow", "trajflow-no-ae", "flomo", "cv"])
    parser.add_argument("--no-cuda", action="store_true", help="skip the CUDA figures")
    parser.add_argument("--no-cpu", action="store_true", help="skip the CPU figures")
    parser.add_argument("--against", type=Path, help="also measure the package in this tree (a git worktree), "
                                                     "alternating, and print the ratios (CPU, first --threads)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds with --against")
    parser.add_argument("--compile-flow", action="store_true",
                        help="flow-stage steps compiled, as train.compile_flow = \"on\" (trees without it: eager)")
    parser.add_argument("--sampling-only", action="store_true", help="only the sampling figures")
    parser.add_argument("--figures-json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    global COMPILE_FLOW, SAMPLING_ONLY
    COMPILE_FLOW, SAMPLING_ONLY = args.compile_flow, args.sampling_only
    if args.against is not None:
        from side_by_side import report_side_by_side

        passed = ["--threads", str(args.threads[0]), "--repeats", str(args.repeats), "--models", *args.models,
                  *(["--compile-flow"] if args.compile_flow else []),
                  *(["--sampling-only"] if args.sampling_only else [])]
        report_side_by_side(Path(__file__), passed, args.against, args.rounds)
        return
    tune_cpu_allocator()
    if args.figures_json:
        torch.set_num_threads(args.threads[0])
        print(json.dumps(figures(torch.device("cpu"), args.models, args.repeats)))
        return
    for threads in [] if args.no_cpu else args.threads:
        torch.set_num_threads(threads)
        run(torch.device("cpu"), args.models, args.repeats)
    if torch.cuda.is_available() and not args.no_cuda:
        run(torch.device("cuda"), args.models, args.repeats)


if __name__ == "__main__":
    main()
