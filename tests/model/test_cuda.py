"""The CUDA path: training, sampling and evaluation on a GPU, and GPU weights that agree with the CPU.

Skipped where torch sees no CUDA device (CI and the development machines have none): these run in a session that
is lent a GPU, through `bench/gpu_session.sh`.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch

from trajflow_pipeline import data as data_module
from trajflow_pipeline.model import load_model
from trajflow_pipeline.model.gru import gru_outputs
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


@pytest.mark.parametrize("mode", ["train", "eval"])
def test_gru_outputs_on_cuda_are_the_cpu_values_and_gradients(mode: str) -> None:
    """On a GPU, gru_outputs runs cuDNN's GRU in training mode and the written-out recursion in eval mode (where
    cuDNN has no backward pass): both give the CPU's values and gradients."""
    torch.manual_seed(0)
    gru = torch.nn.GRU(5, 16, 3, batch_first=True).double()
    inputs = torch.randn(40, 7, 5, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(40, 7, 16, dtype=torch.float64)
    expected = gru(inputs)[0]
    (expected * weights).sum().backward()
    expected_grads = [inputs.grad, *(p.grad for p in gru.parameters())]
    on_gpu = copy.deepcopy(gru).cuda().train(mode == "train")
    on_gpu.zero_grad()
    gpu_inputs = inputs.detach().cuda().requires_grad_()
    outputs = gru_outputs(on_gpu, gpu_inputs)
    (outputs * weights.cuda()).sum().backward()
    torch.testing.assert_close(outputs.cpu(), expected, rtol=1e-9, atol=1e-9)
    for grad, want in zip([gpu_inputs.grad, *(p.grad for p in on_gpu.parameters())], expected_grads):
        torch.testing.assert_close(grad.cpu(), want, rtol=1e-8, atol=1e-8)
