"""`augment forking`: draw statistics, fixed fork point and past, same groups, determinism, lineage, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import typer
from test_forking_fixture import Moment, write_release
from typer.testing import CliRunner

from trajflow_pipeline.cli.augment_cmd import augment_forking_command, augment_scale_rotate_command
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.stages.augment import augment_forking, draw_forking
from trajflow_pipeline.ingest.forking_paths import ingest_forking_paths
from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal
from trajflow_pipeline.ingest.windows import identical_input_groups

runner = CliRunner()
cli = typer.Typer()
cli.command("forking")(augment_forking_command)
cli.command("scale-rotate")(augment_scale_rotate_command)


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def target_windows(path: Path) -> dict[int, np.ndarray]:
    """sample_id -> (n_past + n_future, 2) target positions, read straight from the tables."""
    ds = open_dataset(path)
    samples, tracks = ds.samples(), ds.tracks()
    rows = (samples.select("sample_id", "scene_id", "agent_id", "t0_frame", "n_past", "n_future")
            .with_columns(frame=pl.int_ranges(pl.col("t0_frame") - pl.col("n_past") + 1,
                                              pl.col("t0_frame") + pl.col("n_future") + 1))
            .explode("frame")
            .join(tracks, on=["scene_id", "agent_id", "frame"], how="left")
            .sort("sample_id", "frame"))
    assert rows.get_column("x").null_count() == 0
    return {sid: part.select("x", "y").to_numpy() for (sid,), part in rows.group_by("sample_id")}


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fp")
    write_release(root / "raw")
    return ingest_forking_paths(root / "raw", root / "fp", quiet=True)


@pytest.fixture(scope="module")
def augmented(source: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return augment_forking(source, tmp_path_factory.mktemp("aug") / "aug", copies=200, seed=11, quiet=True)


def test_draw_statistics_match_the_parameters() -> None:
    draws = draw_forking(5000, 41, scale_std=0.03, rot_std_deg=1.0, scale_range=None, rot_range_deg=None, seed=3)
    assert draws.scale.shape == (5000, 40)
    assert draws.scale.mean() == pytest.approx(1.0, abs=5e-4)
    assert draws.scale.std() == pytest.approx(0.03, rel=0.01)
    degrees = np.rad2deg(draws.angle)
    assert degrees.mean() == pytest.approx(0.0, abs=0.02)
    assert degrees.std() == pytest.approx(1.0, rel=0.01)
    assert abs(np.corrcoef(draws.scale.ravel(), draws.angle.ravel())[0, 1]) < 0.01


def test_truncated_draws_stay_in_range_with_the_truncated_normal_spread() -> None:
    draws = draw_forking(5000, 41, scale_std=0.05, rot_std_deg=1.25, scale_range=(0.95, 1.05),
                         rot_range_deg=(-1.25, 1.25), seed=4)
    degrees = np.rad2deg(draws.angle)
    assert draws.scale.min() >= 0.95 and draws.scale.max() <= 1.05
    assert degrees.min() >= -1.25 and degrees.max() <= 1.25
    # N(m, s) truncated at +-1 s has std s * sqrt(1 - 2 phi(1) / (2 Phi(1) - 1))
    phi, mass = math.exp(-0.5) / math.sqrt(2 * math.pi), math.erf(1 / math.sqrt(2))
    factor = math.sqrt(1 - 2 * phi / mass)
    assert draws.scale.std() == pytest.approx(0.05 * factor, rel=0.01)
    assert degrees.std() == pytest.approx(1.25 * factor, rel=0.01)
    # truncating the scales never changes the angles (independent streams)
    untruncated = draw_forking(5000, 41, scale_std=0.05, rot_std_deg=1.25, scale_range=None,
                               rot_range_deg=(-1.25, 1.25), seed=4)
    assert np.array_equal(untruncated.angle, draws.angle)


def test_variants_keep_past_and_fork_and_transform_the_future(source: Path, augmented: Path) -> None:
    original = open_dataset(source).samples()
    samples = open_dataset(augmented).samples()
    assert samples.height == original.height * 200
    assert samples.filter(pl.col("fork_copy") == 0).drop(
        "fork_copy", "fork_scale", "fork_rotation", "fork_source_sample_id").equals(original)
    windows, before = target_windows(augmented), target_windows(source)
    variants = samples.filter(pl.col("fork_copy") > 0)
    for row in variants.iter_rows(named=True):
        got, base = windows[row["sample_id"]], before[row["fork_source_sample_id"]]
        assert np.array_equal(got[:8], base[:8])  # past untouched, fork point (t0) fixed
        s, theta = row["fork_scale"], row["fork_rotation"]
        rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        assert np.allclose(got[8:], base[7] + s * (base[8:] - base[7]) @ rot.T, atol=1e-9)
    # same group, fold and split as the original
    joined = variants.join(original.select("sample_id", "group_id", "fold", "split"),
                           left_on="fork_source_sample_id", right_on="sample_id", suffix="_orig")
    for column in ("group_id", "fold", "split"):
        assert joined.get_column(column).equals(joined.get_column(f"{column}_orig"), check_names=False)
    # variants have exactly the inputs of their originals: the identical-input groups are the group ids
    ds = open_dataset(augmented)
    recomputed = identical_input_groups(samples, ds.tracks())
    assert pl.DataFrame({"a": samples.get_column("group_id"), "b": recomputed}).unique().height == recomputed.n_unique()
    assert recomputed.n_unique() == samples.get_column("group_id").n_unique()
    # the recorded draws follow the parameters
    assert variants.get_column("fork_scale").mean() == pytest.approx(1.0, abs=0.003)
    assert variants.get_column("fork_scale").std() == pytest.approx(0.03, rel=0.05)
    assert np.rad2deg(variants.get_column("fork_rotation").std()) == pytest.approx(1.0, rel=0.05)


def test_context_agents_are_untouched(source: Path, augmented: Path) -> None:
    tracks_src = open_dataset(source).tracks()
    ds = open_dataset(augmented)
    variant = ds.samples().filter(pl.col("fork_copy") == 7).row(0, named=True)
    scene = ds.tracks().filter(pl.col("scene_id") == variant["scene_id"])
    context = scene.filter(pl.col("agent_id") != variant["agent_id"]).drop("scene_id")
    source_scene = variant["scene_id"].split("~")[0]
    expected = (tracks_src.filter((pl.col("scene_id") == source_scene) & (pl.col("agent_id") != variant["agent_id"])
                                  & pl.col("frame").is_between(variant["t0_frame"] - 7, variant["t0_frame"] + 12))
                .drop("scene_id"))
    assert context.height > 0 and context.equals(expected)


def test_determinism_lineage_and_untouched_input(source: Path, tmp_path: Path) -> None:
    before = files(source)
    a = augment_forking(source, tmp_path / "a", copies=4, seed=5, quiet=True)
    b = augment_forking(source, tmp_path / "b", copies=4, seed=5, quiet=True)
    c = augment_forking(source, tmp_path / "c", copies=4, seed=6, quiet=True)
    assert files(a) == files(b)
    assert files(a)["samples.parquet"] != files(c)["samples.parquet"]
    assert files(source) == before
    ds = open_dataset(a)
    assert ds.meta.dataset == "forking_paths_forking_aug" and ds.meta.protocol == "folds"
    assert ds.lineage["augmentation"] == "forking"
    assert ds.lineage["source"] == open_dataset(source).fingerprint()
    assert ds.lineage["source_lineage"] == open_dataset(source).lineage
    assert ds.lineage["parameters"] == {"copies": 4, "seed": 5, "scale_std": 0.03, "rot_std_deg": 1.0,
                                        "scale_range": None, "rot_range_deg": None}
    assert set(ds.scenes().get_column("dataset")) == {"forking_paths_forking_aug"}


def test_cli_with_truncation_ranges(source: Path, tmp_path: Path) -> None:
    result = runner.invoke(cli, ["forking", str(source), "-o", str(tmp_path / "t"), "--copies", "3", "--scale-std",
                                 "0.05", "--rot-std-deg", "1.25", "--scale-range", "0.9", "1.1", "--rot-range-deg",
                                 "-2.5", "2.5", "--seed", "2"])
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output
    ds = open_dataset(tmp_path / "t")
    assert ds.lineage["parameters"]["scale_range"] == [0.9, 1.1]
    assert ds.lineage["parameters"]["rot_range_deg"] == [-2.5, 2.5]
    variants = ds.samples().filter(pl.col("fork_copy") > 0)
    assert variants.get_column("fork_scale").is_between(0.9, 1.1).all()
    assert np.rad2deg(variants.get_column("fork_rotation").abs().max()) <= 2.5


def test_dataset_without_multi_future_groups_is_refused(tmp_path: Path) -> None:
    single = tmp_path / "single"
    moments = [Moment("zara01", 3, 41, ((0, "27", 30.0),), fork=0), Moment("0400", 9, 4, ((0, "27", 10.0),), fork=0)]
    write_release(tmp_path / "raw", moments, other_camera=False)
    ingest_forking_paths(tmp_path / "raw", single, folds=2, quiet=True)
    with pytest.raises(DataError, match="dataset 'forking_paths' has no group with more than one sample"):
        augment_forking(single, tmp_path / "out", quiet=True)
    result = runner.invoke(cli, ["forking", str(single), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1 and "has no group with more than one sample" in result.output
    assert not (tmp_path / "out").exists()


def test_bad_options(source: Path, tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="at least 2"):
        augment_forking(source, tmp_path / "o", copies=1, quiet=True)
    with pytest.raises(UsageError, match="keeps only"):
        augment_forking(source, tmp_path / "o", scale_range=(1.5, 1.6), quiet=True)
    with pytest.raises(UsageError, match="is empty"):
        augment_forking(source, tmp_path / "o", rot_range_deg=(2.0, -2.0), quiet=True)
    with pytest.raises(UsageError, match="never modifies its input"):
        augment_forking(source, source, quiet=True)
    with pytest.raises(DataError, match="dataset directory not found"):
        augment_forking(tmp_path / "missing", tmp_path / "o", quiet=True)
    twice = augment_forking(source, tmp_path / "once", copies=2, quiet=True)
    with pytest.raises(UsageError, match="already augmented with `augment forking`"):
        augment_forking(twice, tmp_path / "twice", copies=2, quiet=True)
    result = runner.invoke(cli, ["forking", str(source), "-o", str(tmp_path / "o"), "--copies", "0"])
    assert result.exit_code == 2 and "must be at least 2" in result.output


def test_works_on_any_grouped_dataset(tmp_path: Path) -> None:
    syn = ingest_synthetic_bimodal(tmp_path / "syn", samples=20, seed=1, quiet=True)
    out = augment_forking(syn, tmp_path / "aug", copies=3, quiet=True)
    samples = open_dataset(out).samples()
    assert samples.height == 60 and samples.get_column("group_id").n_unique() == 1
    assert "scale" in samples.columns and "mode" in samples.columns  # the source's own columns survive
