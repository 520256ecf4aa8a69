"""Fold eth's worst agents under the model with averaged GNN messages: the flow's own log-density against ROME's
NLL, how far the draws fall from them, and what their neighbours change (the figures in README.md).

    trajflow ingest eth-ucy ../shared/data/eth_ucy -o /tmp/eth_ucy
    python docs/results/eth_ucy_scale_augment/worst_agents.py /tmp/eth_ucy
    python docs/results/eth_ucy_scale_augment/worst_agents.py /tmp/eth_ucy \
        docs/results/eth_ucy_speed_normalize/models/trajflow-eth-s0       # the same for another fold-eth run
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import torch
from scipy.stats import spearmanr

from trajflow_pipeline import data as data_module
from trajflow_pipeline.model import load_model
from trajflow_pipeline.model.normalize import scene_speed

RUN = Path(__file__).resolve().parents[1] / "eth_ucy_gnn_mean_folds" / "models" / "trajflow-eth-s0"


def main(dataset: str, run: Path = RUN) -> None:
    torch.set_num_threads(1)
    rome = (pl.read_parquet(run / "eval" / "metrics.parquet")
            .filter(~pl.col("aggregate") & (pl.col("metric") == "nll")).sort("agent_index")["value"].to_numpy())
    batch = data_module.load_problems(dataset, fold="eth", split="test").batch
    model = load_model(run / "final").eval()
    alone = replace(batch, neighbours_mask=torch.zeros_like(batch.neighbours_mask))
    with torch.no_grad():
        log_lik, log_lik_alone = model.log_likelihood(batch).numpy(), model.log_likelihood(alone).numpy()
        draws = model.sample(batch.without_future(), 100, generator=torch.Generator().manual_seed(0))[0]
    worst = np.argsort(-rome)[:10]
    ends = draws[:, :, -1]
    spread = ends.std(1).norm(dim=-1).numpy()
    closest = (ends - batch.future[:, None, -1]).norm(dim=-1).min(1).values.numpy()
    print(f"{len(rome)} agents; Spearman(flow log-density, ROME NLL) = {spearmanr(log_lik, rome).statistic:.2f}")
    print("ten worst by ROME NLL:", np.round(rome[worst], 1))
    print("  share of agents with a higher flow log-density:", np.round((log_lik[:, None] > log_lik[worst]).mean(0), 2))
    print(f"  closest of 100 draws to the final ground truth, m (median agent {np.median(closest):.2f}):",
          np.round(closest[worst], 2))
    print(f"  spread of the draws' final positions, m (median agent {np.median(spread):.2f}):",
          np.round(spread[worst], 2))
    step = (batch.neighbours[:, :, -1] - batch.neighbours[:, :, -2]).norm(dim=-1)
    seen = batch.neighbours_mask & batch.neighbours_valid[:, :, -1] & batch.neighbours_valid[:, :, -2]
    speed = ((step * seen).sum(1) / seen.sum(1).clamp(min=1)).numpy()
    print("  their neighbours' mean last past step, m (0: none seen):", np.round(speed[worst], 2))
    own = scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)
    print("  their scenes' speed, m a step:", np.round(own.numpy()[worst], 2))
    target_steps = torch.cat((batch.past[:, -1:], batch.future), 1).diff(dim=1).norm(dim=-1)
    print("  their last past step and mean future step, m:", np.round(
        (batch.past[:, -1] - batch.past[:, -2]).norm(dim=-1).numpy()[worst], 2), np.round(
        target_steps.mean(1).numpy()[worst], 2))
    if model.config.speed_normalize:
        print("  model.speed_normalize's factors:", np.round(model.speed_scales(batch).numpy()[worst], 2))
    change = np.abs(log_lik - log_lik_alone)
    print(f"  flow log-density change without the neighbours, nats (median agent {np.median(change):.2f}):",
          np.round(change[worst], 2))


if __name__ == "__main__":
    main(sys.argv[1], *(Path(arg) for arg in sys.argv[2:3]))
