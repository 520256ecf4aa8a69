"""gru_outputs computes torch.nn.GRU's function: values and gradients against nn.GRU with the same parameters."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from trajflow_pipeline.model.gru import gru_outputs


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_values_and_gradients_are_nn_grus(dtype: torch.dtype, tolerance: float) -> None:
    torch.manual_seed(0)
    gru = nn.GRU(5, 16, 3, batch_first=True).to(dtype)
    inputs = torch.randn(40, 7, 5, dtype=dtype, requires_grad=True)
    weights = torch.randn(40, 7, 16, dtype=dtype)          # a loss that reads every step's output
    expected = gru(inputs)[0]
    (expected * weights).sum().backward()
    expected_grads = [inputs.grad.clone(), *(p.grad.clone() for p in gru.parameters())]
    gru.zero_grad()
    inputs.grad = None
    outputs = gru_outputs(gru, inputs)
    (outputs * weights).sum().backward()
    assert torch.allclose(outputs, expected, rtol=tolerance, atol=tolerance)
    for grad, want in zip([inputs.grad, *(p.grad for p in gru.parameters())], expected_grads):
        assert torch.allclose(grad, want, rtol=tolerance, atol=tolerance * 10)


def test_gradcheck_and_frozen_parts() -> None:
    torch.manual_seed(1)
    gru = nn.GRU(2, 4, 2, batch_first=True).double()
    inputs = torch.randn(3, 5, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: gru_outputs(gru, x)[:, -1], (inputs,))
    for p in gru.parameters():                              # frozen weights: gradients reach the inputs only
        p.requires_grad_(False)
    gru_outputs(gru, inputs).sum().backward()
    assert inputs.grad is not None and all(p.grad is None for p in gru.parameters())
    with torch.no_grad():                                   # nothing saved, the same values
        assert torch.allclose(gru_outputs(gru, inputs), gru(inputs)[0], rtol=1e-12, atol=1e-12)


def test_other_gru_layouts_are_refused() -> None:
    with pytest.raises(ValueError, match="unidirectional, batch-first"):
        gru_outputs(nn.GRU(2, 4, bidirectional=True, batch_first=True), torch.zeros(1, 3, 2))
    with pytest.raises(ValueError, match="unidirectional, batch-first"):
        gru_outputs(nn.GRU(2, 4), torch.zeros(3, 1, 2))
