"""How often an agent standing at t0 starts walking, per fold's test location and training split: the shift
behind fold eth's NLL tail (the figures in README.md).

An agent stands when its last past step is under 0.05 m, and starts walking when it is more than 1 m from where it
stood within the future window (12 steps). Evaluation needs no model.

    trajflow ingest eth-ucy ../shared/data/eth_ucy -o /tmp/eth_ucy
    python docs/results/eth_ucy_ours/start_rates.py /tmp/eth_ucy
"""

from __future__ import annotations

import sys

import torch

from trajflow_pipeline import data as data_module

FOLDS = ("eth", "hotel", "univ", "zara1", "zara2")
STANDING_STEP_M = 0.05
WALKED_OFF_M = 1.0


def start_counts(past: torch.Tensor, future: torch.Tensor) -> tuple[int, int, int]:
    """(agents, standing at t0, of those more than WALKED_OFF_M from t0 at some future step)."""
    standing = (past[:, -1] - past[:, -2]).norm(dim=-1) < STANDING_STEP_M
    walked_off = (future - past[:, -1:]).norm(dim=-1).amax(1) > WALKED_OFF_M
    return len(past), int(standing.sum()), int((standing & walked_off).sum())


def main(dataset: str) -> None:
    print("fold  split  agents  standing  of those start walking")
    for fold in FOLDS:
        for split in ("test", "train"):
            problems = data_module.load_problems(dataset, fold=fold, split=split).batch
            agents, standing, starting = start_counts(problems.past, problems.future)
            print(f"{fold:6}{split:6}{agents:8d}{standing:7d} ({standing / agents:4.0%})"
                  f"{starting:7d} ({starting / max(standing, 1):4.0%})")


if __name__ == "__main__":
    main(sys.argv[1])
