"""`augment scale-rotate`: only the chosen split, whole-window rotation / scaling, maps, flags, determinism."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import typer
from typer.testing import CliRunner

from trajflow_pipeline.cli.augment_cmd import augment_scale_rotate_command
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import PROTOCOL_FIXED, DatasetMeta, DatasetWriter, open_dataset
from trajflow_pipeline.stages.augment import augment_scale_rotate, draw_scale_rotate
from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal

runner = CliRunner()
cli = typer.Typer()
cli.command("scale-rotate")(augment_scale_rotate_command)
cli.command("unused")(lambda: None)

N_PAST, N_FUTURE, FRAMES = 3, 4, 12
MAP_AFFINE = [10.0, 0.0, 50.0, 0.0, -10.0, 80.0]  # world -> pixel: 10 px per metre, y down


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def write_mapped_dataset(out: Path) -> Path:
    """Two scenes with a raster map, three agents with heading / velocity / size, samples in train, val, test."""
    rows = []
    for s, scene in enumerate(("a", "b")):
        for agent in range(3):
            for frame in range(FRAMES):
                heading = 0.3 * agent + 0.05 * frame + 2.8 * s
                rows.append({"scene_id": scene, "agent_id": agent, "agent_type": "vehicle" if agent == 2 else
                             "pedestrian", "frame": frame, "t": 0.5 * frame,
                             "x": 10.0 * s + agent + 0.7 * frame, "y": -3.0 + 2.0 * agent + 0.2 * frame * agent,
                             "heading": heading, "vx": math.cos(heading), "vy": math.sin(heading),
                             "length": 4.0 + agent, "width": 2.0})
    tracks = pl.DataFrame(rows)
    samples = pl.DataFrame({
        "sample_id": [0, 1, 2, 3, 4], "scene_id": ["a", "a", "a", "b", "b"], "agent_id": [0, 1, 2, 0, 1],
        "t0_frame": [3, 5, 3, 4, 6], "n_past": [N_PAST] * 5, "n_future": [N_FUTURE] * 5,
        "group_id": [0, 1, 2, 3, 4], "split": ["train", "train", "val", "test", "train"],
        "fold": pl.Series([None] * 5, dtype=pl.String)})
    scenes = pl.DataFrame({"dataset": "mapped", "scene_id": ["a", "b"], "location": "here", "dt": 0.5,
                           "source": "made up", "fold": pl.Series([None, None], dtype=pl.String),
                           "map_path": ["maps/here.png", "maps/here.png"], "map_m_per_px": [0.1, 0.1],
                           "map_world_to_px": [MAP_AFFINE, MAP_AFFINE]})
    with DatasetWriter(out, DatasetMeta(dataset="mapped", dt=0.5, protocol=PROTOCOL_FIXED)) as writer:
        writer.add_tracks(tracks)
        (writer.root / "maps").mkdir()
        (writer.root / "maps" / "here.png").write_bytes(b"\x89PNG fake raster")
        writer.finish(scenes, samples, lineage={"made": "by the test"})
    return out


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_mapped_dataset(tmp_path_factory.mktemp("mapped") / "mapped")


def test_uniform_and_normal_rotation_statistics() -> None:
    uniform = draw_scale_rotate(4000, 51, rot_std_deg=None, scale_std=0.0, seed=1)
    assert np.all(uniform.scale == 1.0)
    assert uniform.angle.min() >= -math.pi and uniform.angle.max() < math.pi
    assert uniform.angle.mean() == pytest.approx(0.0, abs=0.01)
    assert uniform.angle.std() == pytest.approx(math.pi / math.sqrt(3), rel=0.01)
    normal = draw_scale_rotate(4000, 51, rot_std_deg=10.0, scale_std=0.1, seed=1)
    assert np.rad2deg(normal.angle).std() == pytest.approx(10.0, rel=0.01)
    assert normal.scale.mean() == pytest.approx(1.0, abs=0.002) and normal.scale.std() == pytest.approx(0.1, rel=0.01)


def test_only_the_training_split_is_copied_and_flagged(mapped: Path, tmp_path: Path) -> None:
    out = augment_scale_rotate(mapped, tmp_path / "aug", copies=4, scale_std=0.1, seed=3, quiet=True)
    ds = open_dataset(out)
    samples = ds.samples()
    variants = samples.filter(pl.col("aug_copy") > 0)
    assert samples.height == 5 + 3 * 3
    assert sorted(set(variants.get_column("aug_source_sample_id"))) == [0, 1, 4]
    assert (variants.get_column("split") == "train").all() and variants.get_column("train_only").all()
    assert not samples.filter(pl.col("aug_copy") == 0).get_column("train_only").any()
    assert variants.get_column("group_id").n_unique() == variants.height
    assert not set(variants.get_column("group_id")) & set(range(5))
    assert ds.meta.dataset == "mapped_scale_rotate" and ds.meta.protocol == "fixed"
    assert ds.lineage["parameters"] == {"copies": 4, "seed": 3, "rot_std_deg": None, "rotation": "uniform",
                                        "scale_std": 0.1, "splits": ["train"]}
    assert ds.lineage["source"] == open_dataset(mapped).fingerprint()
    both = augment_scale_rotate(mapped, tmp_path / "both", copies=2, splits=("train", "val"), quiet=True)
    assert sorted(open_dataset(both).samples().filter(pl.col("aug_copy") > 0)
                  .get_column("aug_source_sample_id").to_list()) == [0, 1, 2, 4]


def test_whole_window_is_rotated_and_scaled_about_the_target(mapped: Path, tmp_path: Path) -> None:
    out = augment_scale_rotate(mapped, tmp_path / "aug", copies=3, scale_std=0.1, seed=9, quiet=True)
    ds, src = open_dataset(out), open_dataset(mapped)
    tracks, src_tracks = ds.tracks(), src.tracks()
    scenes = ds.scenes()
    for row in ds.samples().filter(pl.col("aug_copy") > 0).iter_rows(named=True):
        source = src.samples().filter(pl.col("sample_id") == row["aug_source_sample_id"]).row(0, named=True)
        s, theta = row["aug_scale"], row["aug_rotation"]
        rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        lo, hi = source["t0_frame"] - N_PAST + 1, source["t0_frame"] + N_FUTURE
        before = src_tracks.filter((pl.col("scene_id") == source["scene_id"]) & pl.col("frame").is_between(lo, hi))
        after = tracks.filter(pl.col("scene_id") == row["scene_id"])
        assert after.height == before.height == 3 * (N_PAST + N_FUTURE)
        centre = before.filter((pl.col("agent_id") == source["agent_id"]) & (pl.col("frame") == source["t0_frame"]))
        c = centre.select("x", "y").to_numpy()[0]
        p, q = before.select("x", "y").to_numpy(), after.select("x", "y").to_numpy()
        assert np.allclose(q, c + s * (p - c) @ rot.T, atol=1e-9)
        v, w = before.select("vx", "vy").to_numpy(), after.select("vx", "vy").to_numpy()
        assert np.allclose(w, s * v @ rot.T, atol=1e-9)
        turned = before.get_column("heading").to_numpy() + theta
        assert np.allclose(after.get_column("heading").to_numpy(), np.arctan2(np.sin(turned), np.cos(turned)))
        assert np.allclose(after.get_column("length").to_numpy(), s * before.get_column("length").to_numpy())
        # the map transform follows: every agent lands on the same map pixel as before
        scene = scenes.filter(pl.col("scene_id") == row["scene_id"]).row(0, named=True)
        a, b = np.array(scene["map_world_to_px"]).reshape(2, 3), np.array(MAP_AFFINE).reshape(2, 3)
        assert np.allclose(q @ a[:, :2].T + a[:, 2], p @ b[:, :2].T + b[:, 2])
        assert scene["map_m_per_px"] == pytest.approx(0.1 * s)
    assert (out / "maps" / "here.png").read_bytes() == b"\x89PNG fake raster"


def test_determinism_and_untouched_input(mapped: Path, tmp_path: Path) -> None:
    before = files(mapped)
    a = augment_scale_rotate(mapped, tmp_path / "a", copies=5, rot_std_deg=15.0, seed=2, quiet=True)
    b = augment_scale_rotate(mapped, tmp_path / "b", copies=5, rot_std_deg=15.0, seed=2, quiet=True)
    assert files(a) == files(b)
    assert files(mapped) == before


def test_cli_and_errors(mapped: Path, tmp_path: Path) -> None:
    syn = ingest_synthetic_bimodal(tmp_path / "syn", samples=40, seed=1, quiet=True)
    result = runner.invoke(cli, ["scale-rotate", str(syn), "-o", str(tmp_path / "s"), "--copies", "3",
                                 "--rot-std-deg", "20", "--scale-std", "0.05", "--seed", "4"])
    assert result.exit_code == 0, result.output
    samples = open_dataset(tmp_path / "s").samples()
    assert samples.filter(pl.col("aug_copy") > 0).height == 2 * 36  # the 36 training samples of 40 (10 % val)
    result = runner.invoke(cli, ["scale-rotate", str(syn), "-o", str(tmp_path / "v"), "--split", "val", "-q"])
    assert result.exit_code == 0, result.output
    assert open_dataset(tmp_path / "v").samples().filter(pl.col("aug_copy") > 0).height == 9 * 4
    result = runner.invoke(cli, ["scale-rotate", str(syn), "-o", str(tmp_path / "x"), "--split", "dev"])
    assert result.exit_code == 2 and "--split must name one or more of train, val, test" in result.output
    with pytest.raises(DataError, match="has no samples whose split is test"):
        augment_scale_rotate(syn, tmp_path / "x", splits=("test",), quiet=True)
    with pytest.raises(UsageError, match="standard deviation must be >= 0"):
        augment_scale_rotate(syn, tmp_path / "x", rot_std_deg=-1.0, quiet=True)
    with pytest.raises(UsageError, match="scales must be positive"):
        augment_scale_rotate(syn, tmp_path / "x", scale_std=2.0, copies=50, quiet=True)
    assert not (tmp_path / "x").exists()
