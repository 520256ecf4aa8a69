"""docs/results/eth_ucy_plus_standardized/latent_width.py: latent draw widths in a standardized flow's units."""

from __future__ import annotations

import copy
from dataclasses import replace
from types import ModuleType

import pytest
import torch
from results_scripts import load_results_script

from trajflow_pipeline.model.config import DataSpec, ModelConfig
from trajflow_pipeline.model.models import build_model
from trajflow_pipeline.model.toy import crowd_batch


def load_script() -> ModuleType:
    return load_results_script("eth_ucy_plus_standardized/latent_width.py")


def test_twins_in_the_standardized_units() -> None:
    """On the problems its standardization was fitted to, the true latents' std is 1 in every dimension; a twin
    that draws at twice the temperature draws wider; a model with another autoencoder is refused."""
    script = load_script()
    batch = crowd_batch(300, neighbours=2)
    torch.manual_seed(0)
    standardized = build_model(ModelConfig(flow_standardize=True), DataSpec(n_past=8, n_future=12)).eval()
    standardized.fit_stage("standardize", batch)
    hotter = copy.deepcopy(standardized)
    hotter.config = replace(hotter.config, flow_temperature=2.0)
    with torch.no_grad():
        truth_std, outside, per_model = script.latent_figures({"a": standardized, "b": hotter}, batch,
                                                              torch.Generator().manual_seed(0))
        assert truth_std == pytest.approx(1.0, abs=1e-3) and 0 <= outside < 0.05
        assert per_model["b"][0] > 1.3 * per_model["a"][0] > 0
        other = copy.deepcopy(standardized)
        torch.nn.init.normal_(next(other.autoencoder.parameters()))
        with pytest.raises(SystemExit, match="autoencoder is not the first run's"):
            script.latent_figures({"a": standardized, "c": other}, batch, torch.Generator().manual_seed(0))
