"""TrajFlow's flow-stage training step on real ETH/UCY batches (crowded, uneven scenes), and one whole flow epoch.

    python bench/gnn_groups.py [--data data/eth_ucy] [--fold eth] [--batches 10] [--repeats 3]
    python bench/gnn_groups.py --against ../release [--rounds 3] [--epoch] [--compile-flow]

Fold eth's training problems have 34 graph nodes on average and up to 75, so the social GNN's per-edge work and
the node GRUs dominate a step on a CPU. The script times the forward and backward pass of the flow-stage loss on
the same `--batches` shuffled batches of 128 training problems with one torch thread and prints the best time
per step over `--repeats` rounds, in CPU seconds of this process (this machine is shared and noisy). With
``--epoch`` it also trains one whole flow epoch of the fold (every training problem once, batch 128, AdamW,
``--epoch-threads`` torch threads, default 2) and prints its wall time. With ``--against TREE`` the same figures
are measured for the package in TREE (an earlier release's `git worktree`) in alternating subprocess rounds and
printed side by side (bench/side_by_side.py). With ``--compile-flow`` the flow stage's compiled pieces are
compiled first (train.compile_flow = "on"; the step and the epoch then use them; trees without them stay eager)
and the compile time is printed. The dataset is ingested with `trajflow ingest eth-ucy` first.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from trajflow_pipeline.model import ModelConfig, build_model, tune_cpu_allocator
from trajflow_pipeline.model.config import RunConfig
from release_compat import adamw, compile_flow_stage, load_data, with_fixed_targets


def step_seconds(data, model, batches: int, repeats: int) -> float:
    """Best CPU seconds per flow-stage forward + backward over `repeats` rounds of the same batches (1 thread)."""
    torch.set_num_threads(1)
    train = with_fixed_targets(model, "flow", data.train)        # once per stage, as training does
    order = torch.randperm(len(train), generator=torch.Generator().manual_seed(0))
    chosen = [train.index(order[i * 128:(i + 1) * 128]) for i in range(batches)]
    model.stage_loss("flow", chosen[0]).backward()
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        for batch in chosen:
            model.stage_loss("flow", batch).backward()
        best = min(best, (time.process_time() - start) / len(chosen))
    return best


def epoch_seconds(data, model, threads: int, compiled: bool = False) -> float:
    """Wall seconds of one flow epoch over the fold's training problems (batch 128, AdamW, `threads` threads);
    a model with `compiled` pieces first takes one untimed step at that thread count."""
    torch.set_num_threads(threads)
    params = model.stage_parameters("flow")
    keep = {id(p) for p in params}
    for p in model.parameters():
        p.requires_grad_(id(p) in keep)
    optimizer = adamw(params, 1e-4, 1e-5)
    order = torch.randperm(len(data.train), generator=torch.Generator().manual_seed(1))
    if compiled:  # compiled graphs are for one thread count: a run compiles after setting it, so not timed here
        warm_up = with_fixed_targets(model, "flow", data.train.index(order[:128]))
        model.stage_loss("flow", warm_up).backward()
        optimizer.zero_grad(set_to_none=True)
    start = time.perf_counter()
    train = with_fixed_targets(model, "flow", data.train)        # paid once per stage: counted in the epoch
    for first in range(0, len(order), 128):
        loss = model.stage_loss("flow", train.index(order[first:first + 128]))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data/eth_ucy")
    parser.add_argument("--fold", default="eth")
    parser.add_argument("--batches", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--epoch", action="store_true", help="also time one whole flow epoch")
    parser.add_argument("--epoch-threads", type=int, default=2, help="torch threads for --epoch (default 2)")
    parser.add_argument("--against", type=Path, help="also measure the package in this tree, alternating")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds with --against")
    parser.add_argument("--compile-flow", action="store_true",
                        help="flow-stage steps compiled, as train.compile_flow = \"on\" (trees without it: eager)")
    parser.add_argument("--figures-json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.against is not None:
        from side_by_side import report_side_by_side

        epoch = ["--epoch", "--epoch-threads", str(args.epoch_threads)] if args.epoch else []
        passed = ["--data", args.data, "--fold", args.fold, "--batches", str(args.batches), "--repeats",
                  str(args.repeats), *epoch, *(["--compile-flow"] if args.compile_flow else [])]
        report_side_by_side(Path(__file__), passed, args.against, args.rounds)
        return
    tune_cpu_allocator()  # as `trajflow train` does
    data = load_data(args.data, args.fold, RunConfig())
    torch.manual_seed(0)
    model = build_model(ModelConfig(name="trajflow"), data.spec).train()
    if args.compile_flow:
        compile_flow_stage(model, 128, f"fold {args.fold} flow stage")
    found = {f"fold {args.fold} flow step, batch 128, 1 thread, CPU s": [step_seconds(data, model, args.batches,
                                                                                        args.repeats), "time"]}
    if args.epoch:
        found[f"fold {args.fold} flow epoch ({len(data.train)} problems), {args.epoch_threads} threads, wall s"] = [
            epoch_seconds(data, model, args.epoch_threads, args.compile_flow), "time"]
    if args.figures_json:
        print(json.dumps(found))
        return
    for name, (value, _) in found.items():
        print(f"{name}: {value:.3f}")


if __name__ == "__main__":
    main()
