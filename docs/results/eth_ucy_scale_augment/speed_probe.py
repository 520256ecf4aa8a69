"""The prediction-time probe behind model.speed_normalize: each fold's model with averaged GNN messages (trained
without the option) evaluated on its test scenes as they are and scaled to the training split's pace, the draws
scaled back (the figures in README.md).

    trajflow ingest eth-ucy ../shared/data/eth_ucy -o /tmp/eth_ucy
    python docs/results/eth_ucy_scale_augment/speed_probe.py /tmp/eth_ucy eth hotel zara1 univ
    python docs/results/eth_ucy_scale_augment/speed_probe.py /tmp/eth_ucy eth zara1 hotel --max 1   # only shrink

Per problem the factor is the training split's median scene speed over the scene's own (normalize.scene_speed),
clipped to [0.33, 3] (``--max``: another upper clip), as model.speed_normalize computes it; minADE / minFDE (K = 20) and NLL indep over 100 draws,
each problem's density on its own draws (no pooling of identical inputs), ROME's exact KDE.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import polars as pl
import torch

from trajflow_pipeline import data as data_module
from trajflow_pipeline.metrics.compute import compute_metrics
from trajflow_pipeline.model import load_model
from trajflow_pipeline.model.batch import SceneBatch
from trajflow_pipeline.model.models import scale_scene
from trajflow_pipeline.model.normalize import scene_speed

MODELS = Path(__file__).resolve().parents[1] / "eth_ucy_gnn_mean_folds" / "models"


def speeds(batch: SceneBatch) -> torch.Tensor:
    return scene_speed(batch.past, batch.neighbours, batch.neighbours_valid, batch.neighbours_mask)


def evaluate(model: torch.nn.Module, batch: SceneBatch, factor: torch.Tensor) -> dict[str, float]:
    """minADE, minFDE and NLL of `model`'s draws for the scenes scaled about t0 by `factor` (models.scale_scene,
    what the scaling augmentation uses), the draws scaled back about the same point."""
    with torch.no_grad():
        draws = model.sample(scale_scene(batch, factor).without_future(), 100,
                             generator=torch.Generator().manual_seed(0))[0]
    centre = batch.past[:, None, None, -1]
    draws = centre + (draws - centre) / factor[:, None, None, None]
    table = compute_metrics(draws.double().numpy(), batch.future.double().numpy(),
                            metrics=["min_ade", "min_fde", "nll"], workers=1, quiet=True)
    rows = table.filter(pl.col("aggregate"))
    return dict(zip(rows["metric"], rows["value"]))


def main(dataset: str, folds: list[str], high: float) -> None:
    torch.set_num_threads(1)
    for fold in folds:
        model = load_model(MODELS / f"trajflow-{fold}-s0" / "final").eval()
        reference = speeds(data_module.load_problems(dataset, fold=fold, split="train").batch).median()
        test = data_module.load_problems(dataset, fold=fold, split="test").batch
        own = speeds(test)
        print(f"{fold}: scene speed, training median {reference:.3f} m a step, test median {own.median():.3f}")
        for label, factor in [("as recorded", torch.ones_like(own)),
                              ("at the training pace", (reference / own.clamp(min=1e-4)).clamp(0.33, high))]:
            m = evaluate(model, test, factor)
            print(f"  {label:22s} minADE {m['min_ade']:.3f}  minFDE {m['min_fde']:.3f}  NLL {m['nll']:.2f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", help="an ingested ETH/UCY dataset")
    parser.add_argument("folds", nargs="*", default=["eth", "hotel", "univ", "zara1", "zara2"])
    parser.add_argument("--max", type=float, default=3.0, help="upper clip of the factor (model.speed_normalize_max)")
    args = parser.parse_args()
    main(args.dataset, args.folds, args.max)
