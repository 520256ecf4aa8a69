"""Flow training step on real ETH/UCY batches, with the social GNN run on size-ordered groups of problems.

    python bench/gnn_groups.py [--data data/eth_ucy] [--fold eth] [--batches 10] [--rounds 3] [--groups 128 8]

ETH/UCY scenes are crowded and uneven (fold eth's training problems have 34 graph nodes on average and up to 75),
so the GNN's per-edge work dominates a TrajFlow flow step on a CPU. `SocialGNN.GROUP_SIZE` problems are processed
at a time, in order of size; a group size of at least the batch size is one pass over the batch, as before.
For each group size the script times the forward and backward pass of the flow-stage loss on the same
`--batches` batches of 128 training problems (one torch thread), `--rounds` times in alternation (this machine is
shared and noisy), and prints the best time per step, in CPU seconds of this process, and its ratio to the first
group size. The dataset is ingested with `trajflow ingest eth-ucy` first.
"""

from __future__ import annotations

import argparse
import time

import torch

from trajflow_pipeline.model import ModelConfig, build_model
from trajflow_pipeline.model.config import RunConfig
from trajflow_pipeline.model.encoders import SocialGNN
from trajflow_pipeline.stages.train import _load_data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data/eth_ucy")
    parser.add_argument("--fold", default="eth")
    parser.add_argument("--batches", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--groups", type=int, nargs="+", default=[128, 16, 8, 4])
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = _load_data(args.data, args.fold, RunConfig())
    torch.manual_seed(0)
    model = build_model(ModelConfig(name="trajflow"), data.spec).train()
    order = torch.randperm(len(data.train), generator=torch.Generator().manual_seed(0))
    batches = [data.train.index(order[i * 128:(i + 1) * 128]) for i in range(args.batches)]
    best = {size: float("inf") for size in args.groups}
    for _ in range(args.rounds):
        for size in args.groups:
            SocialGNN.GROUP_SIZE = size
            start = time.process_time()
            for batch in batches:
                model.stage_loss("flow", batch).backward()
            best[size] = min(best[size], (time.process_time() - start) / len(batches))
    baseline = best[args.groups[0]]
    print(f"fold {args.fold}: flow step (forward + backward, batch 128, 1 thread), best of {args.rounds} rounds")
    for size, seconds in best.items():
        print(f"  group size {size:4d}: {seconds * 1000:6.1f} ms per step  ({baseline / seconds:.2f}x group "
              f"size {args.groups[0]})")


if __name__ == "__main__":
    main()
