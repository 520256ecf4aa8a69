"""Prediction-time probe of model.speed_normalize_min: each fold's model of ours (trained with the floor 0.33)
evaluated on its test scenes with lower floors, so that scenes more than 3x the training pace are scaled further
towards it (the figures in README.md).

    trajflow ingest eth-ucy ../shared/data/eth_ucy -o data/eth_ucy
    python docs/results/eth_ucy_ours/floor_probe.py data/eth_ucy eth hotel --floors 0.33 0.25 0.2 0.15

Per problem the factor is the model's fitted training pace over the scene's own speed, clipped to [floor, 1]
(model.speed_scales with the model's speed_normalize_min replaced); minADE / minFDE (K = 20) and NLL indep over 100
draws, each problem's density on its own draws (no pooling of identical inputs), ROME's exact KDE: the figures of
speed_probe.py, comparable among the rows of one fold, not with the report's (which pools identical inputs).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import polars as pl
import torch

from trajflow_pipeline import data as data_module
from trajflow_pipeline.metrics.compute import compute_metrics
from trajflow_pipeline.model import load_model
from trajflow_pipeline.model.models import TrajectoryModel

MODELS = Path(__file__).resolve().parent / "models"


def with_floor(model: TrajectoryModel, floor: float) -> TrajectoryModel:
    """The same model (same weights and fitted pace) scaling scenes down by at most 1 / `floor`."""
    model.config = dataclasses.replace(model.config, speed_normalize_min=floor)
    return model


def probe(model: TrajectoryModel, dataset: str, fold: str, floors: list[float]) -> None:
    """Print, per floor, the share of test problems at the floor and the fold's metrics."""
    batch = data_module.load_problems(dataset, fold=fold, split="test").batch
    for floor in floors:
        with_floor(model, floor)
        with torch.no_grad():
            factor = model.speed_scales(batch)
            draws = model.sample(batch.without_future(), 100, generator=torch.Generator().manual_seed(0))[0]
        table = compute_metrics(draws.double().numpy(), batch.future.double().numpy(),
                                metrics=["min_ade", "min_fde", "nll"], workers=1, quiet=True)
        rows = table.filter(pl.col("aggregate"))
        value = dict(zip(rows["metric"], rows["value"]))
        print(f"{fold} floor {floor:.2f}: at the floor {float((factor <= floor + 1e-6).float().mean()):.0%}, "
              f"median factor {float(factor.median()):.2f}; minADE {value['min_ade']:.3f} "
              f"minFDE {value['min_fde']:.3f} NLL {value['nll']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", help="the ETH/UCY dataset directory (trajflow ingest eth-ucy)")
    parser.add_argument("folds", nargs="+", help="test folds, e.g. eth hotel")
    parser.add_argument("--floors", type=float, nargs="+", default=[0.33, 0.25, 0.2, 0.15, 0.1])
    parser.add_argument("--seed", type=int, default=0, help="which published seed's models (default 0)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for fold in args.folds:
        probe(load_model(MODELS / f"trajflow-{fold}-s{args.seed}" / "final").eval(), args.dataset, fold, args.floors)


if __name__ == "__main__":
    main()
