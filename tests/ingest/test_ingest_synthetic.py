"""The synthetic bimodal set: determinism, the two modes, the scale distribution and the single group."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.data import load_problems
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.synthetic import N_FUTURE, N_PAST, base_trajectories, ingest_synthetic_bimodal


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_gives_byte_identical_output(tmp_path: Path) -> None:
    a = ingest_synthetic_bimodal(tmp_path / "a", samples=200, seed=7, quiet=True)
    b = ingest_synthetic_bimodal(tmp_path / "b", samples=200, seed=7, quiet=True)
    c = ingest_synthetic_bimodal(tmp_path / "c", samples=200, seed=8, quiet=True)
    assert files(a) == files(b)
    assert files(a)["samples.parquet"] != files(c)["samples.parquet"]


def test_structure_of_the_bimodal_set(synthetic_dataset: Path) -> None:
    ds = open_dataset(synthetic_dataset)
    samples = ds.samples()
    assert ds.meta.dt == 0.25 and ds.meta.protocol == "train-is-test"
    assert samples.height == 600
    assert samples.get_column("group_id").n_unique() == 1
    assert samples.get_column("mode").value_counts().sort("mode").get_column("count").to_list() == [300, 300]
    assert (samples.get_column("n_past") == N_PAST).all() and (samples.get_column("n_future") == N_FUTURE).all()
    problems = load_problems(synthetic_dataset, None, "test")
    assert len(problems) == 600
    past = problems.batch.past.numpy()
    assert np.allclose(past, past[0], atol=0)
    final = problems.batch.future[:, -1].numpy()
    mode = samples.get_column("mode").to_numpy()
    assert (final[mode == 0, 1] > 0.5).all() and (final[mode == 1, 1] < -0.3).all()
    train, val = load_problems(synthetic_dataset, None, "train"), load_problems(synthetic_dataset, None, "val")
    assert len(train) + len(val) == 600 and len(val) == 60
    assert not set(train.sample_id) & set(val.sample_id)


def test_futures_are_scaled_about_the_last_position(tmp_path: Path) -> None:
    out = ingest_synthetic_bimodal(tmp_path / "big", samples=4000, seed=1, quiet=True)
    samples = open_dataset(out).samples()
    scale = samples.get_column("scale").to_numpy()
    assert scale.mean() == pytest.approx(1.0, abs=0.01)
    assert scale.std() == pytest.approx(0.15, abs=0.01)
    past, modes = base_trajectories()
    problems = load_problems(out, None, "test")
    mode = samples.get_column("mode").to_numpy()
    expected = past[-1] + scale[:, None, None] * (modes[mode] - past[-1])
    assert np.allclose(problems.batch.future.numpy(), expected, atol=1e-5)


def test_cli_and_inspect_json(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["ingest", "synthetic-bimodal", "-o", str(tmp_path / "s"), "--samples", "50",
                                 "--seed", "2"])
    assert result.exit_code == 0, result.output
    assert "50 samples" in result.output
    result = runner.invoke(app, ["inspect", str(tmp_path / "s"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["dataset"] == "synthetic_bimodal" and summary["samples"] == 50 and summary["groups"] == 1
    assert summary["lineage"]["seed"] == 2
    result = runner.invoke(app, ["inspect", str(tmp_path / "s")])
    assert result.exit_code == 0 and "samples by fold and split" in result.output
    result = runner.invoke(app, ["inspect", str(tmp_path / "nothing")])
    assert result.exit_code == 1 and "dataset directory not found" in result.output
    result = runner.invoke(app, ["ingest", "synthetic-bimodal", "-o", str(tmp_path / "t"), "--samples", "1"])
    assert result.exit_code == 2 and "--samples must be at least 2" in result.output
