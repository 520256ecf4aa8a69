"""Where a TrajFlow flow-stage training step spends its time on a device, and how its rate scales with batch size.

    python bench/step_profile.py                       # CUDA when available, else CPU
    python bench/step_profile.py --device cpu --batches 128 512 --no-compile

Prints, for the flow stage with up to 8 neighbours (the bench's ETH/UCY-shaped problems, bench/train.py):
- samples/s of the eager step at each ``--batches`` size (the paper trains at 128): a step bound by the number of
  its operations gains almost linearly with the batch, one bound by arithmetic does not;
- a torch.profiler reading of the batch-128 step: operators and device kernels launched per step, the kernels'
  summed device time against the step's wall time (their ratio is how busy the device is), and the operators
  with the most host time;
- the step with the flow's log-density and the GNN edge block compiled (train.compile_flow = "on"): the one-off
  compile time and the rate.
Figures, not a timed test; on a GPU absolute times count, on a CPU only ratios measured in one run.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch
from torch.profiler import ProfilerActivity, profile

from trajflow_pipeline.model import ModelConfig, build_model, tune_cpu_allocator
from train import SPEC, best_time, freeze_all_but, training_step


def trajflow_step(batch_size: int, device: torch.device, compiled: bool, stage: str = "flow",
                  recursion_gru: bool = False) -> tuple[Callable[[], None], float]:
    """A TrajFlow training step of `stage` on a fixed batch of `batch_size` problems with up to 8 neighbours
    (bench/train.py's step) and the seconds its compilation took (0 when eager).

    `recursion_gru`: the GRUs that run through gru_outputs in eval mode (the same function: they have no
    dropout), where it runs its written-out recursion on a GPU too instead of cuDNN's GRU."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name="trajflow"), SPEC).to(device).train()
    if recursion_gru:   # the GRUs run through gru_outputs; the decoder's nn.GRU is called directly
        for name, module in model.named_modules():
            if isinstance(module, torch.nn.GRU) and not name.endswith("dec_gru"):
                module.eval()
    freeze_all_but(model, stage)
    compile_seconds = 0.0
    if compiled:
        start = time.perf_counter()
        failure = model.compile_stage(stage, batch_size)
        if failure is not None:
            raise SystemExit(f"the {stage} stage did not compile: {failure}")
        compile_seconds = time.perf_counter() - start
    return training_step(model, stage, batch_size, 8, device), compile_seconds


def print_profile(step: Callable[[], None], device: torch.device, sync: Callable[[], None], steps: int = 5) -> None:
    """Operators and kernels per step, device-busy fraction and the top host-time operators of `step`."""
    step()
    sync()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    start = time.perf_counter()
    with profile(activities=activities) as prof:
        for _ in range(steps):
            step()
        sync()
    wall = (time.perf_counter() - start) / steps
    events = prof.events()
    operators = sum(1 for e in events if e.device_type.name == "CPU" and e.name.startswith("aten::"))
    kernels = [e for e in events if e.device_type.name == "CUDA"]
    print(f"profiled wall per step (profiler on): {wall * 1e3:.1f} ms; aten operator calls per step: "
          f"{operators / steps:,.0f}")
    if kernels:
        busy = sum(e.device_time for e in kernels) / 1e6 / steps   # device_time is in microseconds
        print(f"device kernels per step: {len(kernels) / steps:,.0f}; their summed time {busy * 1e3:.1f} ms "
              f"= {busy / wall:.0%} of the step's wall time")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12, max_name_column_width=40))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batches", type=int, nargs="+", default=[128, 512, 2048])
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds per figure; the best is printed")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled step")
    parser.add_argument("--gru-rounds", type=int, default=0,
                        help="first, batch-128 steps of both stages with the GRUs' two paths (cuDNN, recursion) in "
                             "this many alternating rounds (on a GPU: which path to take)")
    args = parser.parse_args()
    device = torch.device(args.device)
    tune_cpu_allocator()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    print(f"== TrajFlow flow stage, up to 8 neighbours, on {device}"
          + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else
             f" ({torch.get_num_threads()} threads)"))
    for stage in ["autoencoder", "flow"] if args.gru_rounds else []:
        rates: dict[bool, list[float]] = {False: [], True: []}
        for _ in range(args.gru_rounds):
            for recursion in (False, True):
                step, _ = trajflow_step(128, device, compiled=False, stage=stage, recursion_gru=recursion)
                rates[recursion].append(128 / best_time(step, args.repeats, 10, sync)[0])
        native, recursion = max(rates[False]), max(rates[True])
        print(f"{stage}, batch 128, best of {args.gru_rounds} alternating rounds: GRU as nn.GRU {native:,.0f} "
              f"samples/s, as the written-out recursion {recursion:,.0f} ({native / recursion:.2f}x)")
    for batch_size in args.batches:
        step, _ = trajflow_step(batch_size, device, compiled=False)
        wall, cpu = best_time(step, args.repeats, 10, sync)
        print(f"eager, batch {batch_size:>5d}: {batch_size / wall:>10,.0f} samples/s  ({wall * 1e3:.1f} ms a step, "
              f"{cpu / wall:.0%} of it host CPU time)")
    print("\n== profile of the eager batch-128 step")
    print_profile(trajflow_step(128, device, compiled=False)[0], device, sync)
    if not args.no_compile:
        step, seconds = trajflow_step(128, device, compiled=True)
        wall, _ = best_time(step, args.repeats, 10, sync)
        print(f"\n== compiled (train.compile_flow = \"on\"), batch 128: compiled in {seconds:.0f} s; "
              f"{128 / wall:,.0f} samples/s ({wall * 1e3:.1f} ms a step)")
        print_profile(step, device, sync)


if __name__ == "__main__":
    main()
