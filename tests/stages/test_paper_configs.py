"""The experiment configs in configs/paper: every one parses, names real models, keys and data; the synthetic
quick variant runs end to end (on a smaller set and tinier budgets than it names) through to the report."""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pytest
import torch
from safetensors.torch import load_file

from trajflow_pipeline.model.config import MODEL_NAMES, load_config
from trajflow_pipeline.report.paper import PAPER_TRAJFLOW
from trajflow_pipeline.stages.experiment import run_experiment
from trajflow_pipeline.stages.experiment_config import INGESTS, load_experiment
from trajflow_pipeline.stages.report import report
from trajflow_pipeline.training import train

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "paper"
PAPER = sorted(p for p in CONFIGS.glob("*.toml") if not p.stem.endswith("_quick"))
#: datasets the paper configs may point at, by the directory name they use
KNOWN_DATA = {"synthetic_bimodal", "eth_ucy", "round", "nuscenes", "nuscenes_mini", "forking_paths_augmented", "highd",
              "ind"}


def test_every_paper_config_has_a_quick_variant() -> None:
    assert {p.stem for p in PAPER} == {"synthetic_bimodal", "eth_ucy", "round", "nuscenes", "forking_paths", "highd",
                                       "ind"}
    for config in PAPER:
        assert (CONFIGS / f"{config.stem}_quick.toml").exists(), config


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.toml")), ids=lambda p: p.stem)
def test_config_parses_and_references_what_exists(path: Path) -> None:
    config = load_experiment(path)
    assert set(config.models) <= set(MODEL_NAMES) and "trajflow" in config.models and "cv" in config.models
    assert config.data_path.name in KNOWN_DATA
    # runnable from raw files with one command: the config builds its data (raw pointed at with --set data.raw=)
    assert config.ingest in INGESTS
    if not path.stem.endswith("_quick"):
        assert not config.train_overrides, "paper configs train with the paper's budgets (the defaults)"


def test_the_forking_paths_configs_ingest_then_augment_as_the_paper() -> None:
    for name in ("forking_paths", "forking_paths_quick"):
        config = load_experiment(CONFIGS / f"{name}.toml")
        assert config.ingest == "forking-paths"
        assert [(step.kind, step.options["copies"]) for step in config.augment] == [("forking", 100)]
        assert config.data_path == config.augment[-1].path != config.source_path


def test_paper_seed_and_fold_protocols() -> None:
    assert len(load_experiment(CONFIGS / "synthetic_bimodal.toml").seeds) == 10
    assert load_experiment(CONFIGS / "eth_ucy.toml").folds == "all"
    assert len(load_experiment(CONFIGS / "forking_paths.toml").seeds) == 5
    assert len(load_experiment(CONFIGS / "nuscenes.toml").seeds) == 5


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.toml")), ids=lambda p: p.stem)
def test_configs_evaluate_jsd_only_where_the_paper_reports_it(path: Path) -> None:
    """JSD needs several ground-truth futures per input: the paper reports it for the synthetic sets only. On real
    recordings the few identical-input groups (standing pedestrians) would make a number that means nothing."""
    dataset = load_experiment(path).data_path.name.removesuffix("_augmented")
    metrics = set(load_experiment(path).eval_options.metrics)
    assert ("jsd" in metrics) == ("jsd" in PAPER_TRAJFLOW.get(dataset, {}))
    assert {"min_ade", "min_fde", "nll"} <= metrics


def tiny_runs(epochs: int, samples: int, k: int) -> list[str]:
    """`--set` overrides that shrink a quick config's training and evaluation further, for the suite."""
    return [f'train.set=["train.ae_max_epochs={epochs}", "train.ae_min_epochs=1", "train.flow_max_epochs={epochs}", '
            '"train.flow_min_epochs=1", "model.flow_layers=2"]', f"eval.samples={samples}", f"eval.k={k}",
            "eval.workers=1"]


def test_synthetic_quick_runs_end_to_end(tmp_path: Path) -> None:
    config = CONFIGS / "synthetic_bimodal_quick.toml"
    overrides = [f"data.path={(tmp_path / 'data').as_posix()}", "data.samples=100", *tiny_runs(2, 10, 5)]
    experiment = run_experiment(config, tmp_path / "exp", quiet=True, overrides=overrides)
    assert len(json.loads((experiment / "experiment.json").read_text())["runs"]) == 4
    out = report([experiment], tmp_path / "report", quiet=True)
    markdown = (out / "report.md").read_text()
    for model in ("trajflow", "flomo", "cv"):
        assert model.lower() in markdown.lower()
    assert (out / "report.html").stat().st_size > 10_000


OURS = sorted((CONFIGS.parent / "ours").glob("*.toml"))


@pytest.mark.parametrize("path", OURS, ids=lambda p: p.stem)
def test_our_configs_change_only_the_flow_settings_of_a_paper_protocol(path: Path) -> None:
    """configs/ours: a paper protocol (same data, folds and evaluation; the paper's seeds, more may follow; its
    models, or those of them our change concerns, TrajFlow among them) with changes of ours to the flow model (the
    flow settings, which flow weights training keeps, how the GNN that conditions it aggregates, the scaling
    augmentation it trains with, the pace its scenes are normalised to). configs/ours/NAME.toml or NAME_*.toml
    follows configs/paper/NAME.toml."""
    ours = load_experiment(path)
    protocol = max((p for p in CONFIGS.glob("*.toml") if path.stem == p.stem or path.stem.startswith(p.stem + "_")),
                   key=lambda p: len(p.stem))
    paper = load_experiment(protocol)
    for key in ("data_path", "ingest", "ingest_options", "folds", "eval_options"):
        assert getattr(ours, key) == getattr(paper, key), key
    assert list(ours.seeds[:len(paper.seeds)]) == list(paper.seeds)
    assert "trajflow" in ours.models and set(ours.models) <= set(paper.models)
    assert ours.train_overrides and all(o.startswith(("model.flow_", "train.flow_select", "model.gnn_aggregate",
                                                      "model.scale_augment_", "model.speed_normalize"))
                                          for o in ours.train_overrides)
    load_config(overrides=list(ours.train_overrides))      # every override is a real, valid key


def test_there_are_configs_of_ours() -> None:
    assert OURS, "configs/ours holds our variants of the paper protocols"


def test_the_eth_ucy_deviations_of_ours_change_nothing_on_synthetic_bimodal(synthetic_dataset: Path,
                                                                           tmp_path: Path) -> None:
    """configs/ours/eth_ucy.toml's changes to the network are the identity on the synthetic set, where every
    problem is one agent (nothing to aggregate) with the same past (every scene at the training pace, factor
    exactly 1): the same seed trains bit-identical losses and weights with and without them, so the synthetic
    results of ours hold for a configuration that carries them. Its fitted sampling temperature is not: it is left
    out here (it changes the draws, not the training)."""
    overrides = list(load_experiment(CONFIGS.parent / "ours" / "eth_ucy.toml").train_overrides)
    assert all(o.startswith(("model.gnn_aggregate", "model.speed_normalize", "model.flow_temperature_grid"))
               for o in overrides)
    eth_ucy = [o for o in overrides if not o.startswith("model.flow_temperature_grid")]
    assert eth_ucy
    budget = ["train.ae_min_epochs=0", "train.flow_min_epochs=0", "train.ae_max_epochs=2", "train.flow_max_epochs=2"]
    runs = [train(synthetic_dataset, tmp_path / name, seed=5, quiet=True, overrides=budget + extra)
            for name, extra in (("plain", []), ("eth_ucy", eth_ucy))]
    logs = [pl.read_parquet(run / "train_log.parquet").select("stage", "epoch", "train_loss", "val_loss")
            for run in runs]
    assert logs[0].height == 4 and logs[0].equals(logs[1])
    plain, ours = (load_file(run / "final" / "model.safetensors") for run in runs)
    assert set(ours) - set(plain) == {"speed_reference"}                   # the fitted pace, kept with the weights
    assert all(torch.equal(plain[name], ours[name]) for name in plain)


def test_the_candidate_for_one_configuration_is_one_on_both_benchmarks() -> None:
    """configs/ours/eth_ucy_plus_standardized.toml and its synthetic side carry the same settings: ours for ETH/UCY
    (whose settings before the flow the test above shows to be the identity on synthetic bimodal) plus the
    standardized flow input."""
    ours = CONFIGS.parent / "ours"
    eth_ucy, synthetic = (load_experiment(ours / f"{name}.toml").train_overrides
                          for name in ("eth_ucy_plus_standardized", "synthetic_bimodal_plus_eth_ucy"))
    assert eth_ucy == synthetic
    added = set(eth_ucy) - set(load_experiment(ours / "eth_ucy.toml").train_overrides)
    assert added == {"model.flow_standardize=true", "model.flow_tail_bound=5"}


BUDGET = sorted((CONFIGS.parent / "cpu").glob("*.toml"))


@pytest.mark.parametrize("path", BUDGET, ids=lambda p: p.stem)
def test_cpu_configs_change_only_the_training_budget_of_a_paper_protocol(path: Path) -> None:
    """configs/cpu: a protocol of configs/paper or configs/ours (same data, folds, seeds, evaluation and model
    settings; some of its models, TrajFlow among them) whose training stops earlier, so that it finishes in a
    session of a 2-core CPU. Only epoch limits may be added, and only downwards."""
    budget = load_experiment(path)
    stem = path.stem.removesuffix("_cpu")
    base_path = next(p for p in (CONFIGS / f"{stem}.toml", CONFIGS.parent / "ours" / f"{stem}.toml") if p.exists())
    base = load_experiment(base_path)
    for key in ("data_path", "ingest", "ingest_options", "folds", "seeds", "eval_options"):
        assert getattr(budget, key) == getattr(base, key), key
    assert "trajflow" in budget.models and set(budget.models) <= set(base.models)
    if base_path.parent == CONFIGS:  # the paper protocol at a CPU budget keeps its baseline row
        assert "cv" in budget.models
    assert not budget.model_overrides
    added = [o for o in budget.train_overrides if o not in base.train_overrides]
    assert set(base.train_overrides) <= set(budget.train_overrides)
    keys = {o.split("=", 1)[0] for o in added}
    assert keys and keys <= {"train.ae_max_epochs", "train.ae_min_epochs", "train.flow_max_epochs",
                             "train.flow_min_epochs"}
    reduced, defaults = load_config(overrides=list(budget.train_overrides)).train, load_config().train
    for key in keys:
        name = key.removeprefix("train.")
        assert getattr(reduced, name) <= getattr(defaults, name), key
    assert reduced.ae_min_epochs <= reduced.ae_max_epochs and reduced.flow_min_epochs <= reduced.flow_max_epochs


def test_there_are_cpu_budget_configs() -> None:
    assert BUDGET, "configs/cpu holds the paper protocols at a CPU-session training budget"


@pytest.mark.parametrize("member", ["highd", "ind"])
def test_levelx_quick_configs_run_end_to_end_on_fixtures(tmp_path: Path, member: str) -> None:
    """highd_quick / ind_quick on their generated fixtures (two recordings; TrajFlow and CV only, tinier budgets)."""
    from levelx_fixture import write_members  # tests/ingest, on the path (conftest.py)

    raw = write_members(tmp_path / "raw", member, 2)
    config = CONFIGS / f"{member}_quick.toml"
    # from the raw recordings: the config's ingest, pointed at them from the command line
    overrides = [f"data.raw={raw.as_posix()}", f"data.path={(tmp_path / 'data').as_posix()}",
                 'protocol.models=["trajflow", "cv"]', *tiny_runs(1, 5, 3)]
    experiment = run_experiment(config, tmp_path / "exp", quiet=True, overrides=overrides)
    runs = json.loads((experiment / "experiment.json").read_text())["runs"]
    assert len(runs) == 2


def test_forking_paths_quick_runs_from_the_raw_release_through_ingest_and_augmentation(tmp_path: Path) -> None:
    """forking_paths_quick from a generated release (the real file format): ingest, augment (fewer copies), TrajFlow
    and CV at tinier budgets; the data stages' records say what was built from what."""
    from test_forking_fixture import write_release  # tests/ingest, on the path (conftest.py)

    from trajflow_pipeline.schemas.stage_record import read_stage_record

    write_release(tmp_path / "raw")
    overrides = [f"data.raw={(tmp_path / 'raw').as_posix()}", f"data.path={(tmp_path / 'fp').as_posix()}",
                 f"augment.0.path={(tmp_path / 'fp_aug').as_posix()}", "augment.0.copies=5",
                 'protocol.models=["trajflow", "cv"]', *tiny_runs(1, 5, 3)]
    experiment = run_experiment(CONFIGS / "forking_paths_quick.toml", tmp_path / "exp", quiet=True,
                                overrides=overrides)
    assert len(json.loads((experiment / "experiment.json").read_text())["runs"]) == 2
    ingest, augmented = read_stage_record(tmp_path / "fp"), read_stage_record(tmp_path / "fp_aug")
    assert ingest is not None and augmented is not None
    assert (ingest.kind, ingest.name) == ("ingest", "forking-paths")
    assert (augmented.kind, augmented.name) == ("augment", "forking")
    assert augmented.upstream == ingest.output and augmented.options["copies"] == 5
    assert ingest.inputs and all(entry["path"].endswith("_cam4.json") for entry in ingest.inputs)  # what it reads
