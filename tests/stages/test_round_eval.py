"""rounD past the trained horizon: the loader reads each sample's own n_future_max, `trajflow eval
--extended-horizon` scores every sample over it (TrajFlow rolling out, the others extended at constant velocity),
`--steps` below n_future is explicit, and map crops are stored as uint8 without changing what the CNN sees."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
from test_round_synth import write_gap_recordings
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.data.loader import build_problems, load_problems
from trajflow_pipeline.data.maps import crops_for_problems, past_headings
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.metrics import nll_indep, nll_joint
from trajflow_pipeline.model.autoencoder import TrajectoryAutoencoder
from trajflow_pipeline.model.encoders import MapEncoder
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.stages.evaluate import EvalOptions, evaluate
from trajflow_pipeline.stages.experiment_config import load_experiment
from trajflow_pipeline.ingest.round import N_FUTURE, ingest_round
from trajflow_pipeline.rundir import open_run
from trajflow_pipeline.training import train

#: four scripted recordings: one fold then tests an accepted gap (25 steps) and a rejected one (35 steps)
RECORDINGS = 4
TINY = ["train.ae_max_epochs=2", "train.ae_min_epochs=1", "train.flow_max_epochs=2", "train.flow_min_epochs=1",
        "model.flow_layers=2", "model.flow_hidden=[16, 16]"]
CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "paper"


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    raw = write_gap_recordings(tmp_path_factory.mktemp("round_eval") / "raw", RECORDINGS)
    return ingest_round(raw, tmp_path_factory.mktemp("round_eval_out") / "round", quiet=True)


@pytest.fixture(scope="module")
def fold(data: Path) -> str:
    """A fold whose test samples need 25 steps for one pair and 35 for the other."""
    samples = open_dataset(data).samples()
    mixed = (samples.group_by("fold").agg(pl.col("n_future_max").n_unique().alias("horizons"))
             .filter(pl.col("horizons") == 2).get_column("fold").sort())
    assert mixed.len(), "the fixture must have a fold with both horizons"
    return str(mixed[0])


@pytest.fixture(scope="module")
def runs(data: Path, fold: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("round_runs")
    return {model: train(data, root / model, fold=fold, model=model, overrides=TINY, seed=0, quiet=True)
            for model in ("trajflow", "flomo", "cv")}


def test_loader_reads_each_samples_own_horizon(data: Path) -> None:
    ds = open_dataset(data)
    samples = ds.samples()
    plain = build_problems(ds, samples)
    assert plain.horizon is None and plain.extended_future is None and (plain.horizons == N_FUTURE).all()
    problems = build_problems(ds, samples, extended=True)
    assert problems.horizon.tolist() == samples.get_column("n_future_max").to_list()
    assert set(problems.horizon.tolist()) == {25, 35}
    # the ingest gives both samples of a target / ego pair (one joint_id) the situation's horizon
    assert (samples.group_by("joint_id").agg(pl.col("n_future_max").n_unique()).get_column("n_future_max") == 1).all()
    future = problems.extended_future.numpy()
    assert future.shape == (samples.height, 35, 2) and future.dtype == np.float32
    valid = np.arange(35)[None, :] < problems.horizon[:, None]
    assert np.isfinite(future[valid]).all() and np.isnan(future[~valid]).all()   # padded, never invented
    np.testing.assert_array_equal(future[:, :N_FUTURE], problems.batch.future.numpy())
    assert problems.batch.future.shape[1] == N_FUTURE                              # training keeps n_future
    long = int(np.flatnonzero(problems.horizon == 35)[0])
    row = samples.row(long, named=True)
    last = ds.tracks().filter((pl.col("scene_id") == row["scene_id"]) & (pl.col("agent_id") == row["agent_id"])
                              & (pl.col("frame") == row["t0_frame"] + 35)).row(0, named=True)
    np.testing.assert_allclose(future[long, 34], [last["x"], last["y"]], rtol=1e-6)


def test_loader_refuses_horizons_it_cannot_read(data: Path) -> None:
    ds = open_dataset(data)
    samples = ds.samples()
    without = build_problems(ds, samples.drop("n_future_max"), extended=True)
    assert (without.horizon == N_FUTURE).all() and without.extended_future.shape[1] == N_FUTURE
    short = samples.with_columns(n_future_max=pl.when(pl.col("sample_id") == 1).then(20)
                                 .otherwise(pl.col("n_future_max")))
    with pytest.raises(DataError, match="sample 1 has n_future_max 20 below its n_future 25"):
        build_problems(ds, short, extended=True)
    beyond = samples.with_columns(n_future_max=pl.when(pl.col("sample_id") == 0).then(10_000)
                                  .otherwise(pl.col("n_future_max")))
    with pytest.raises(DataError, match="has no position at frame"):
        build_problems(ds, beyond, extended=True)


def _tables(out: Path) -> tuple[dict, pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    return (json.loads((out / "eval.json").read_text()), pl.read_parquet(out / "predictions.parquet"),
            pl.read_parquet(out / "ground_truth.parquet"), pl.read_parquet(out / "metrics.parquet"))


def _per_sample(metrics: pl.DataFrame, metric: str) -> dict[int, float]:
    rows = metrics.filter((pl.col("metric") == metric) & ~pl.col("aggregate"))
    return dict(rows.select("sample_id", "value").iter_rows())


def _arrays(predictions: pl.DataFrame, truth: pl.DataFrame, sample_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(draws, steps, 2) predictions and (own steps, 2) ground-truth future of one sample."""
    pred = predictions.filter(pl.col("sample_id") == sample_id).sort("draw", "step")
    draws = pred.get_column("draw").n_unique()
    gt = truth.filter((pl.col("sample_id") == sample_id) & (pl.col("step") > 0)).sort("step")
    return pred.select("x", "y").to_numpy().reshape(draws, -1, 2), gt.select("x", "y").to_numpy()


def test_extended_eval_scores_each_sample_over_its_own_horizon(runs: dict[str, Path]) -> None:
    options = EvalOptions(samples=12, k=5, workers=1, extended_horizon=True,
                          metrics=("min_ade", "min_fde", "min_ade_joint", "nll", "nll_joint"))
    info, predictions, truth, metrics = _tables(evaluate(runs["trajflow"], options=options, quiet=True))
    horizon = info["horizon"]
    assert horizon["trained"] == horizon["ground_truth"] == horizon["evaluated"] == 25
    assert horizon["predicted"] == horizon["extended_max"] == 35 and horizon["extended_min"] == 25
    assert horizon["extended_samples"] == 2 and horizon["beyond_trained"] == "autoregressive"
    assert not horizon["extended_by_constant_velocity"] and not horizon["truncated"] and info["warnings"] == []
    # the _ext pass refits only the long samples and their joint partners, and is counted apart
    assert 0 < info["rome_fits_ext"] <= info["rome_fits"] and info["rome_fallback_fits_ext"] == 0
    assert predictions.get_column("step").max() == 35
    own = dict(truth.group_by("sample_id").agg(pl.col("step").max()).iter_rows())
    assert sorted(own.values()) == [25, 25, 35, 35]                    # ground truth only up to each horizon
    ade, ade_ext = _per_sample(metrics, "min_ade"), _per_sample(metrics, "min_ade_ext")
    fde_ext, nll_ext = _per_sample(metrics, "min_fde_ext"), _per_sample(metrics, "nll_ext")
    nll = _per_sample(metrics, "nll")
    for sample_id, steps in own.items():
        pred, gt = _arrays(predictions, truth, sample_id)
        error = np.linalg.norm(pred[:5, :steps] - gt[None], axis=-1)     # first k = 5 draws, own steps
        assert ade_ext[sample_id] == pytest.approx(error.mean(axis=1).min())
        assert fde_ext[sample_id] == pytest.approx(error[:, -1].min())
        assert ade[sample_id] == pytest.approx(error[:, :25].mean(axis=1).min())
        # NLL: a ROME density of the sample's own 12 draws truncated to its horizon (dimension 2 * steps)
        expected = nll_indep(pred[None, :, :steps], gt[None], workers=1, quiet=True)[0]
        assert nll_ext[sample_id] == pytest.approx(expected)
        if steps == 25:
            assert ade_ext[sample_id] == ade[sample_id] and nll_ext[sample_id] == nll[sample_id]
    long = [s for s, steps in own.items() if steps == 35]
    pair = [_arrays(predictions, truth, s) for s in sorted(long)]
    joint_rows = metrics.filter((pl.col("metric") == "nll_joint_ext") & pl.col("sample_id").is_in(long))
    expected = nll_joint(np.stack([p for p, _ in pair]), np.stack([g for _, g in pair]), np.array([0, 0]),
                         workers=1, quiet=True)[1][0]
    assert joint_rows.get_column("value").to_list() == [pytest.approx(expected)]
    aggregates = dict(metrics.filter(pl.col("aggregate")).select("metric", "value").iter_rows())
    assert aggregates["min_ade_ext_long"] == pytest.approx(np.mean([ade_ext[s] for s in long]))
    assert aggregates["min_ade_ext"] == pytest.approx(np.mean(list(ade_ext.values())))


def test_trajflow_rolls_its_decoder_out_past_25_steps(data: Path, fold: str, runs: dict[str, Path],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The extra steps come from the auto-regressive decoder asked for 35 steps (no extension after it), and
    the first 25 of a 35-step draw are the 25-step draw."""
    asked: list[int] = []
    decode = TrajectoryAutoencoder.decode

    def spy(self: TrajectoryAutoencoder, latent: torch.Tensor, steps: int) -> torch.Tensor:
        asked.append(steps)
        return decode(self, latent, steps)

    monkeypatch.setattr(TrajectoryAutoencoder, "decode", spy)
    options = EvalOptions(samples=4, k=2, workers=1, extended_horizon=True, metrics=("min_ade",))
    evaluate(runs["trajflow"], options=options, quiet=True)
    assert asked == [35]
    model = open_run(runs["trajflow"]).load_model(torch.device("cpu")).eval()
    batch = load_problems(data, fold=fold, split="test").batch.without_future()
    long = model.sample(batch, 6, steps=35, generator=torch.Generator().manual_seed(3)).trajectories
    short = model.sample(batch, 6, steps=25, generator=torch.Generator().manual_seed(3)).trajectories
    assert long.shape[2] == 35 and torch.isfinite(long).all()
    torch.testing.assert_close(long[:, :, :25], short)


def test_fixed_horizon_models_are_extended_at_constant_velocity(runs: dict[str, Path]) -> None:
    options = EvalOptions(samples=6, k=3, workers=1, extended_horizon=True, metrics=("min_ade",))
    info, predictions, _, metrics = _tables(evaluate(runs["flomo"], options=options, quiet=True))
    assert info["horizon"]["extended_by_constant_velocity"] and info["horizon"]["beyond_trained"] == (
        "constant-velocity extension")
    steps = predictions.sort("sample_id", "draw", "step").select("x", "y").to_numpy().reshape(4, 6, 35, 2)
    step = np.diff(steps, axis=2)                                       # step[k] = position k+2 - position k+1
    last_trained = step[:, :, 23:24]                                    # position 25 - position 24
    np.testing.assert_allclose(step[:, :, 24:], np.broadcast_to(last_trained, step[:, :, 24:].shape), atol=2e-4)
    assert np.abs(np.diff(step[:, :, :24], axis=2)).max() > 1e-3       # inside the horizon it is no CV
    assert {"min_ade", "min_ade_ext", "min_ade_ext_long"} <= set(metrics.get_column("metric"))
    cv_info, *_ = _tables(evaluate(runs["cv"], options=options, quiet=True))
    assert cv_info["horizon"]["beyond_trained"] == "native"
    assert not cv_info["horizon"]["extended_by_constant_velocity"]


def test_steps_below_n_future_is_a_recorded_warning(runs: dict[str, Path]) -> None:
    runner = CliRunner()
    base = ["eval", str(runs["cv"]), "--samples", "6", "--k", "3", "--workers", "1", "--metric", "min_ade", "-q"]
    result = runner.invoke(app, [*base, "--steps", "10"])
    assert result.exit_code == 0, result.output
    assert "warning: --steps 10 is below the dataset's n_future 25" in " ".join(result.output.split())
    info, predictions, _, _ = _tables(runs["cv"] / "eval")
    assert info["horizon"]["truncated"] and info["horizon"]["evaluated"] == 10 and len(info["warnings"]) == 1
    assert predictions.get_column("step").max() == 10
    result = runner.invoke(app, [*base, "--extended-horizon", "--steps", "30"])
    assert result.exit_code == 2 and "--steps 30 is shorter than the longest ground-truth horizon (35" in (
        " ".join(result.output.split()))
    result = runner.invoke(app, [*base, "--extended-horizon"])
    assert result.exit_code == 0, result.output
    info, *_ = _tables(runs["cv"] / "eval")
    assert info["horizon"]["predicted"] == 35 and not info["horizon"]["truncated"] and info["warnings"] == []


def test_map_crops_are_uint8_and_the_cnn_sees_the_same_values(data: Path, fold: str) -> None:
    problems = load_problems(data, fold=fold, split="test")
    crops = problems.batch.map_crop
    assert crops.dtype == torch.uint8 and crops.shape[1:] == (1, 156, 257)
    past = problems.batch.past.numpy().astype(np.float64)   # float32 positions: the loader crops at float64 ones
    floats = crops_for_problems(data, problems.scene_id, past[:, -1], past_headings(past))
    levels = crops_for_problems(data, problems.scene_id, past[:, -1], past_headings(past), dtype=np.uint8)
    assert floats.dtype == np.float32 and levels.nbytes * 4 == floats.nbytes
    np.testing.assert_array_equal(levels, np.rint(floats * np.float32(255)).astype(np.uint8))   # round(255 v)
    assert np.abs(levels / np.float32(255) - floats).max() <= 0.5 / 255 + 1e-6
    assert np.abs(crops.numpy().astype(np.int16) - levels).max() <= 1
    torch.manual_seed(0)
    encoder = MapEncoder()
    torch.testing.assert_close(encoder(crops), encoder(crops.float() / 255), rtol=0, atol=0)


def test_round_experiments_evaluate_the_extended_horizon(tmp_path: Path) -> None:
    for name in ("round", "round_quick"):
        assert load_experiment(CONFIGS / f"{name}.toml").eval_options.extended_horizon is True
    assert load_experiment(CONFIGS / "eth_ucy.toml").eval_options.extended_horizon is False
    bad = tmp_path / "bad.toml"
    bad.write_text('[data]\npath = "data/round"\n[eval]\nextended_horizon = "yes"\n')
    with pytest.raises(UsageError, match="extended_horizon must be true or false"):
        load_experiment(bad)
