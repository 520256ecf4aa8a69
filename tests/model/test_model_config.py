"""Typed run config: the paper's defaults, TOML round trip, overrides, and one-line errors for bad keys."""

from __future__ import annotations

from pathlib import Path

import pytest

from trajflow_pipeline.errors import UsageError
from trajflow_pipeline.model.config import (COMPILE_MIN_STEPS, DataSpec, ModelConfig, RunConfig, StageSchedule,
                                           TrainConfig, load_config)


def test_defaults_are_the_papers_values() -> None:
    model, train = ModelConfig(), TrainConfig()
    assert (model.alpha, model.ae_embed, model.ae_hidden, model.ae_layers, model.latent_dim) == (10.0, 20, 20, 3, 20)
    assert (model.flow_layers, model.flow_bins, model.flow_tail_bound, model.flow_hidden) == (10, 8, 15.0, (32,) * 5)
    assert (model.past_embed, model.past_hidden, model.past_layers, model.past_out) == (16, 16, 3, 64)
    assert (model.gnn_layers, model.gnn_width, model.map_height, model.map_width, model.map_out) == (4, 32, 156,
                                                                                                   257, 64)
    assert (train.ae_lr, train.ae_weight_decay, train.ae_batch_size) == (5e-4, 1e-4, 128)
    assert (train.flow_lr, train.flow_weight_decay, train.flow_batch_size, train.flow_lr_decay) == (1e-3, 1e-5, 128,
                                                                                                   0.98)
    assert (train.ae_max_epochs, train.flow_max_epochs) == (5000, 500)



def test_each_gradient_stage_reads_its_own_settings_as_one_schedule() -> None:
    """TrainConfig.schedule: train.ae_* make the autoencoder's, train.flow_* the flow's (each value distinct, so a
    swapped or shared setting shows); the config's own keys, which config.toml is written from, stay as they are."""
    train = load_config(None, ["train.ae_lr=1e-4", "train.ae_weight_decay=2e-4", "train.ae_batch_size=3",
                               "train.ae_min_epochs=4", "train.ae_max_epochs=5", "train.ae_patience=6",
                               "train.flow_lr=7e-4", "train.flow_weight_decay=8e-4", "train.flow_batch_size=9",
                               "train.flow_lr_decay=0.5", "train.flow_min_epochs=11", "train.flow_max_epochs=12",
                               "train.flow_patience=13"]).train
    assert train.schedule("autoencoder") == StageSchedule(lr=1e-4, weight_decay=2e-4, batch_size=3, lr_decay=None,
                                                          min_epochs=4, max_epochs=5, patience=6)
    assert train.schedule("flow") == StageSchedule(lr=7e-4, weight_decay=8e-4, batch_size=9, lr_decay=0.5,
                                                   min_epochs=11, max_epochs=12, patience=13)
    with pytest.raises(ValueError, match="not a gradient stage"):
        train.schedule("fit")
    assert [key for key in RunConfig().to_dict()["train"] if key[:3] in ("ae_", "flo")] == [
        "ae_lr", "ae_weight_decay", "ae_batch_size", "ae_max_epochs", "ae_min_epochs", "ae_patience", "flow_lr",
        "flow_weight_decay", "flow_batch_size", "flow_lr_decay", "flow_max_epochs", "flow_min_epochs",
        "flow_patience", "flow_select", "flow_select_every", "flow_select_problems", "flow_select_samples",
        "flow_select_max_pooled"]

def test_toml_round_trip(tmp_path: Path) -> None:
    config = load_config(None, ["train.flow_lr=3e-4", "model.flow_hidden=[16, 16]", "model.name='flomo'",
                                "seed=7"])
    assert config.train.flow_lr == 3e-4 and config.model.flow_hidden == (16, 16) and config.train.seed == 7
    path = tmp_path / "cfg.toml"
    path.write_text(config.to_toml())
    assert load_config(path) == config
    assert RunConfig.from_dict(config.to_dict()) == config


def test_file_then_overrides(tmp_path: Path) -> None:
    path = tmp_path / "cfg.toml"
    path.write_text("[train]\nflow_max_epochs = 3\nflow_lr = 1\n[model]\nname = \"cv\"\n")
    config = load_config(path, ["train.flow_max_epochs=4"])
    assert config.train.flow_max_epochs == 4 and config.train.flow_lr == 1.0 and config.model.name == "cv"


@pytest.mark.parametrize("text, message", [
    ("[train]\nflow_lrr = 1e-3\n", "train.flow_lrr"),
    ("[modle]\nname = 'x'\n", "modle"),
    ("[train]\nflow_batch_size = 'big'\n", "train.flow_batch_size"),
    ("[model]\nname = 'nope'\n", "nope"),
    ("[model]\nlatent_dim = 12\n", "latent_dim"),
    ("[train\n", "not valid TOML"),
])
def test_bad_config_files(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "cfg.toml"
    path.write_text(text)
    with pytest.raises(UsageError, match=message):
        load_config(path)


@pytest.mark.parametrize("override, message", [
    ("train.nope=1", "train.nope"), ("nope=1", "nope"), ("flow_lr", "key=value"), ("train.flow_lr=abc", "flow_lr"),
    ("model.use_map=1", "use_map"), ("train.flow_select=best", "flow_select must be one of val_loss, val_nll"),
    ("model.gnn_aggregate=max", "gnn_aggregate must be one of sum, mean, not 'max'"),
    ("train.flow_select_samples=1", "train.flow_select_samples must be an integer >= 2, got 1"),
    ("train.flow_select_every=0", "train.flow_select_every must be an integer >= 1, got 0"),
    ("train.compile_flow=yes", "train.compile_flow must be one of auto, on, off, not 'yes'"),
])
def test_bad_overrides(override: str, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        load_config(None, [override])


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_data_spec_round_trip() -> None:
    spec = DataSpec(n_past=8, n_future=12, has_map=True, dataset="eth", dt=0.4)
    assert DataSpec.from_dict(spec.to_dict()) == spec


def test_shipped_model_configs_load() -> None:
    folder = Path(__file__).resolve().parents[2] / "configs" / "model"
    files = sorted(folder.glob("*.toml"))
    assert files
    for path in files:
        load_config(path)
    assert load_config(folder / "paper.toml") == RunConfig()


def test_the_last_override_of_a_setting_wins_however_it_is_spelled() -> None:
    from trajflow_pipeline.model.config import RunConfig, apply_overrides

    config = apply_overrides(RunConfig(), ["train.flow_lr=0.2", "flow_lr=0.1", "train.flow_lr=0.3"])
    assert config.train.flow_lr == 0.3


def test_compile_flow_auto_compiles_long_cpu_stages_only() -> None:
    auto = load_config(None).train
    assert auto.compile_flow == "auto"
    assert auto.compiles_flow("cpu", COMPILE_MIN_STEPS) and not auto.compiles_flow("cpu", COMPILE_MIN_STEPS - 1)
    assert not auto.compiles_flow("cuda", 10 ** 6)
    assert load_config(None, ["train.compile_flow=on"]).train.compiles_flow("cuda", 1)
    assert not load_config(None, ["train.compile_flow=off"]).train.compiles_flow("cpu", 10 ** 6)
