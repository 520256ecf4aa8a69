"""The CUDA path: training, sampling and evaluation on a GPU, and GPU weights that agree with the CPU.

Skipped where torch sees no CUDA device (CI and the development machines have none): these run in a session that
is lent a GPU, through `bench/gpu_session.sh`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch

from trajflow_pipeline import data as data_module
from trajflow_pipeline.model import load_model
from trajflow_pipeline.stages.evaluate import EvalOptions, evaluate
from trajflow_pipeline.training import train

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: run on a machine with a GPU")

BUDGET = ["train.ae_min_epochs=0", "train.flow_min_epochs=0", "train.ae_max_epochs=2", "train.flow_max_epochs=2"]


@pytest.mark.parametrize("model", ["trajflow", "trajflow-no-ae", "flomo"])
def test_trains_and_evaluates_on_cuda(synthetic_dataset: Path, tmp_path: Path, model: str) -> None:
    run = train(synthetic_dataset, tmp_path / "run", model=model, device="cuda", quiet=True, overrides=BUDGET)
    info = json.loads((run / "run.json").read_text())
    assert info["device"].startswith("cuda") and info["status"] == "finished"
    out = evaluate(run, device="cuda", quiet=True, options=EvalOptions(samples=10, k=5, workers=1, max_pooled=500))
    aggregates = pl.read_parquet(out / "metrics.parquet").filter(pl.col("aggregate"))
    assert {"min_ade", "nll"} <= set(aggregates.get_column("metric"))
    assert np.isfinite(aggregates.get_column("value").to_numpy()).all()


def test_cuda_and_cpu_agree_on_the_same_weights(synthetic_dataset: Path, tmp_path: Path) -> None:
    """One set of trained weights gives the same log-likelihoods of the ground truth on both devices."""
    run = train(synthetic_dataset, tmp_path / "run", model="trajflow", device="cuda", quiet=True, overrides=BUDGET)
    batch = data_module.load_problems(synthetic_dataset, split="test").batch.index(slice(0, 64))
    on_cpu = load_model(run / "final").eval()
    on_gpu = load_model(run / "final").eval().to("cuda")
    with torch.no_grad():
        cpu = on_cpu.log_likelihood(batch)
        gpu = on_gpu.log_likelihood(batch.to(torch.device("cuda"))).cpu()
    assert torch.isfinite(cpu).all()
    torch.testing.assert_close(gpu, cpu, rtol=1e-4, atol=1e-3)
