"""Model and training-state files: safe loading, exact round trips, one-line errors naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from trajflow_pipeline.errors import TrajflowError
from trajflow_pipeline.model.checkpoint import (load_model, load_training_state, read_model_metadata, save_model,
                                                save_training_state)
from trajflow_pipeline.model.config import DataSpec, ModelConfig
from trajflow_pipeline.model.models import build_model
from trajflow_pipeline.model.toy import crowd_batch

SPEC = DataSpec(n_past=8, n_future=12, dataset="toy", dt=0.4)


@pytest.mark.parametrize("name", ["trajflow", "flomo", "cv"])
def test_round_trip_gives_identical_samples(tmp_path: Path, name: str) -> None:
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name, flow_layers=4), SPEC, seed=3).eval()
    batch = crowd_batch(3)
    if name == "cv":
        model.fit_stage("fit", batch)
    path = save_model(model, tmp_path / "run")
    assert path.name == "model.safetensors"
    loaded = load_model(tmp_path / "run", expected_model=name)
    assert loaded.config == model.config and loaded.spec == SPEC
    a = model.sample(batch, 5, generator=torch.Generator().manual_seed(1))
    b = loaded.sample(batch, 5, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a.trajectories, b.trajectories) and torch.equal(a.log_lik, b.log_lik)
    meta = read_model_metadata(path)
    assert meta["model"] == name and meta["log_lik_space"] == model.log_lik_space


def test_other_model_is_refused(tmp_path: Path) -> None:
    path = save_model(build_model(ModelConfig(name="flomo"), SPEC), tmp_path / "m.safetensors")
    with pytest.raises(TrajflowError, match=r"m\.safetensors.*'flomo' model, not 'trajflow'"):
        load_model(path, expected_model="trajflow")


def test_corrupt_file_is_refused_with_its_name(tmp_path: Path) -> None:
    path = save_model(build_model(ModelConfig(), SPEC), tmp_path / "m.safetensors")
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(TrajflowError, match=r"m\.safetensors: not a readable trajflow checkpoint"):
        load_model(path)
    (tmp_path / "junk.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(TrajflowError, match="junk.safetensors"):
        load_model(tmp_path / "junk.safetensors")
    with pytest.raises(TrajflowError, match="not found"):
        load_model(tmp_path / "missing.safetensors")


def test_other_major_version_is_refused(tmp_path: Path) -> None:
    path = save_model(build_model(ModelConfig(), SPEC), tmp_path / "m.safetensors")
    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata())
        tensors = {k: handle.get_tensor(k) for k in handle.keys()}
    save_file(tensors, str(path), metadata={**metadata, "format_version": "2.0"})
    with pytest.raises(TrajflowError, match="format version 2.0"):
        load_model(path)
    save_file(tensors, str(path), metadata={**metadata, "format": "something-else"})
    with pytest.raises(TrajflowError, match="not a trajflow model"):
        load_model(path)


def test_weights_that_do_not_fit_the_config_are_refused(tmp_path: Path) -> None:
    path = save_model(build_model(ModelConfig(), SPEC), tmp_path / "m.safetensors")
    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata())
        tensors = {k: handle.get_tensor(k) for k in handle.keys()}
    config = json.loads(metadata["config"])
    config["gnn_width"] = 16
    save_file(tensors, str(path), metadata={**metadata, "config": json.dumps(config)})
    with pytest.raises(TrajflowError, match="do not match"):
        load_model(path)


def test_training_state_round_trip_and_errors(tmp_path: Path) -> None:
    model = build_model(ModelConfig(), SPEC)
    optimizer = torch.optim.AdamW(model.parameters())
    model.loss(crowd_batch(4)).backward()
    optimizer.step()
    path = tmp_path / "state.pt"
    save_training_state(path, {"model": "trajflow", "weights": model.state_dict(),
                               "optimizer": optimizer.state_dict(), "log": [{"epoch": 1, "stage": "flow"}]})
    state = load_training_state(path, expected_model="trajflow")
    assert state["log"][0]["stage"] == "flow" and torch.equal(state["weights"]["flow.transform.transforms.1._0"],
                                                              model.state_dict()["flow.transform.transforms.1._0"])
    with pytest.raises(TrajflowError, match="not 'flomo'"):
        load_training_state(path, expected_model="flomo")
    path.write_bytes(b"garbage")
    with pytest.raises(TrajflowError, match=r"state\.pt: not a readable"):
        load_training_state(path)
