"""Forking Paths ingest on generated releases: groups, the fork point, the resampling, folds, context agents."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from test_forking_fixture import ORIGIN_PX, PERSON_ID, VEHICLE_ID, Moment, default_moments, true_position, write_release

from trajflow_pipeline.data import list_folds, load_problems
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.forking_paths import (VEHICLE_ID_OFFSET, cam4_metres_per_pixel,
                                                    ingest_forking_paths)
from trajflow_pipeline.ingest.windows import identical_input_groups


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory):
    return write_release(tmp_path_factory.mktemp("fp") / "release")


@pytest.fixture(scope="module")
def dataset(release, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return ingest_forking_paths(release.root, tmp_path_factory.mktemp("fp_out") / "fp", quiet=True)


def moment_of(key: str) -> Moment:
    return next(m for m in default_moments() if f"{m.scene}_{m.moment}_{m.xagent}" == key)


def ingested(moment: Moment, angle: float, raw_frame: float) -> np.ndarray:
    """Where the ingest must put the x-agent: ground truth plus the pixel origin's offset (y flipped)."""
    scale = cam4_metres_per_pixel(moment.scene)
    x, y = true_position(moment, angle, raw_frame)
    return np.array([x + ORIGIN_PX[0] * scale, y - ORIGIN_PX[1] * scale])


def x_agent_track(tracks: pl.DataFrame, scene_id: str, agent_id: int) -> pl.DataFrame:
    return tracks.filter((pl.col("scene_id") == scene_id) & (pl.col("agent_id") == agent_id)).sort("frame")


def test_one_group_per_moment_and_one_sample_per_future(dataset: Path) -> None:
    ds = open_dataset(dataset)
    samples = ds.samples()
    assert ds.meta.dataset == "forking_paths" and ds.meta.protocol == "folds" and ds.meta.dt == 0.4
    moments = default_moments()
    assert samples.height == sum(len(m.futures) for m in moments)
    sizes = dict(samples.group_by("moment").agg(pl.col("group_id").n_unique(), pl.len()).select("moment", "len")
                 .iter_rows())
    assert sizes == {f"{m.scene}_{m.moment}_{m.xagent}": len(m.futures) for m in moments}
    assert samples.group_by("moment").agg(pl.col("group_id").n_unique()).get_column("group_id").to_list() == [1] * 6
    assert samples.get_column("group_id").n_unique() == 6
    assert (samples.get_column("n_past") == 8).all() and (samples.get_column("n_future") == 12).all()
    # each annotated future is its own scene named after its file; the other camera's file is ignored
    assert samples.get_column("scene_id").n_unique() == samples.height
    assert all(sid.endswith("_cam4") for sid in ds.scenes().get_column("scene_id"))
    assert ds.lineage["single_future_groups"] == 1 and ds.lineage["skipped"] == []


def test_groups_agree_with_identical_inputs(dataset: Path) -> None:
    ds = open_dataset(dataset)
    samples, tracks = ds.samples(), ds.tracks()
    recomputed = identical_input_groups(samples, tracks)
    pairs = pl.DataFrame({"a": samples.get_column("group_id"), "b": recomputed}).unique()
    assert pairs.height == samples.get_column("group_id").n_unique() == recomputed.n_unique()


def test_fork_point_is_the_last_shared_position(dataset: Path) -> None:
    ds = open_dataset(dataset)
    samples, tracks = ds.samples(), ds.tracks()
    for moment in default_moments():
        key = f"{moment.scene}_{moment.moment}_{moment.xagent}"
        rows = samples.filter(pl.col("moment") == key)
        expected_fork = moment.fork if len(moment.futures) > 1 else (102 if moment.scene == "zara01" else 124)
        assert rows.get_column("fork_raw_frame").unique().to_list() == [expected_fork]
        t0 = rows.get_column("t0_frame").unique().item()
        paths = [x_agent_track(tracks, sid, moment.xagent) for sid in rows.get_column("scene_id")]
        pasts = [p.filter(pl.col("frame").is_between(t0 - 7, t0)).select("frame", "x", "y") for p in paths]
        assert all(past.height == 8 and past.equals(pasts[0]) for past in pasts)
        if len(paths) > 1:
            after = np.array([p.filter(pl.col("frame") == t0 + 1).select("x", "y").row(0) for p in paths])
            assert np.abs(after - after[0]).max() > 0.1  # the futures really diverge right after the fork


def test_positions_are_resampled_on_the_grid_anchored_at_the_fork(dataset: Path) -> None:
    ds = open_dataset(dataset)
    samples, tracks = ds.samples(), ds.tracks()
    for row in samples.iter_rows(named=True):
        moment = moment_of(row["moment"])
        angle = next(a for d, ann, a in moment.futures if d == row["dest_idx"] and ann == row["annotator"])
        fps = 25.0 if moment.scene == "zara01" else 30.0
        step = int(0.4 * fps)
        fork = row["fork_raw_frame"]
        assert row["t0_frame"] == fork // step
        track = x_agent_track(tracks, row["scene_id"], moment.xagent)
        window = track.filter(pl.col("frame").is_between(row["t0_frame"] - 7, row["t0_frame"] + 12))
        raw_frames = fork + (window.get_column("frame").to_numpy() - row["t0_frame"]) * step
        expected = np.stack([ingested(moment, angle, f) for f in raw_frames])
        assert np.allclose(window.select("x", "y").to_numpy(), expected, atol=1e-9)
        assert np.allclose(window.get_column("t").to_numpy(), raw_frames / fps)
        # consecutive grid points are 0.4 s apart and frame 0 lies within the first 0.4 s
        assert np.allclose(np.diff(track.get_column("t").to_numpy()), 0.4)
        assert track.get_column("t")[0] - 0.4 * (track.get_column("frame")[0]) == pytest.approx(
            (fork % step) / fps)


def test_fractional_frame_steps_are_interpolated(release, tmp_path: Path) -> None:
    out = ingest_forking_paths(release.root, tmp_path / "fp24", fps={"zara01": 24.0}, quiet=True)
    ds = open_dataset(out)
    samples, tracks = ds.samples(), ds.tracks()
    row = samples.filter(pl.col("scene_id") == "zara01_1_252_0_27_cam4").row(0, named=True)
    moment = moment_of(row["moment"])
    step = 0.4 * 24.0
    assert row["fork_raw_frame"] == 107 and row["t0_frame"] == int(107 // step)
    track = x_agent_track(tracks, row["scene_id"], moment.xagent)
    raw_pos = 107 + (track.get_column("frame").to_numpy() - row["t0_frame"]) * step
    assert (raw_pos % 1 > 1e-6).any()  # really between raw frames
    expected = np.stack([ingested(moment, -60.0, r) for r in raw_pos])
    assert np.allclose(track.select("x", "y").to_numpy(), expected, atol=1e-9)
    assert np.allclose(track.get_column("t").to_numpy(), raw_pos / 24.0)
    assert ds.lineage["fps"] == {"0400": 30.0, "zara01": 24.0}


def test_context_agents_and_types(dataset: Path) -> None:
    ds = open_dataset(dataset)
    tracks = ds.tracks()
    one = tracks.filter(pl.col("scene_id") == "0400_1_7_0_27_cam4")
    agents = dict(one.group_by("agent_id").agg(pl.col("agent_type").first()).iter_rows())
    assert agents == {7: "pedestrian", PERSON_ID: "pedestrian", VEHICLE_ID + VEHICLE_ID_OFFSET: "vehicle"}
    vehicle = one.filter(pl.col("agent_type") == "vehicle").sort("frame")
    assert np.allclose(np.diff(vehicle.get_column("x").to_numpy()), -4.0 * 0.4)  # 4 m/s towards -x
    problems = load_problems(dataset, "0", "test")
    assert problems.batch.neighbours_mask.sum(dim=1).min().item() == 2  # the other person and the vehicle


def test_folds_keep_whole_groups(dataset: Path) -> None:
    samples = open_dataset(dataset).samples()
    per_group = samples.group_by("group_id").agg(pl.col("fold").n_unique().alias("folds"),
                                                 pl.col("split").n_unique().alias("splits"))
    assert (per_group.get_column("folds") == 1).all() and (per_group.get_column("splits") == 1).all()
    assert list_folds(dataset) == ["0", "1", "2", "3", "4"]
    assert set(samples.get_column("split")) == {"train", "val"}
    for fold in list_folds(dataset):
        test = load_problems(dataset, fold, "test")
        train = load_problems(dataset, fold, "train")
        test_groups = set(test.group_id)
        assert test_groups and not test_groups & set(train.group_id)
        try:
            val_groups = set(load_problems(dataset, fold, "val").group_id)
        except DataError:  # every val group may lie in the test fold
            val_groups = set()
        assert not test_groups & val_groups
        assert len(test_groups | set(train.group_id) | val_groups) == 6


def test_release_root_next_x_folder_and_bbox_folder_are_equivalent(release, tmp_path: Path) -> None:
    outs = [ingest_forking_paths(path, tmp_path / f"o{i}", quiet=True)
            for i, path in enumerate((release.root, release.root / "next_x_v1_dataset", release.bbox))]
    tables = [(p / "samples.parquet").read_bytes() for p in outs]
    shards = [(p / "tracks" / "part-00000.parquet").read_bytes() for p in outs]
    assert tables[0] == tables[1] == tables[2] and shards[0] == shards[1] == shards[2]


def test_same_input_gives_byte_identical_files_and_seed_moves_folds(release, tmp_path: Path) -> None:
    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    a = ingest_forking_paths(release.root, tmp_path / "a", quiet=True)
    b = ingest_forking_paths(release.root, tmp_path / "b", quiet=True)
    c = ingest_forking_paths(release.root, tmp_path / "c", seed=5, quiet=True)
    assert files(a) == files(b)
    folds = [open_dataset(p).samples().get_column("fold").to_list() for p in (a, c)]
    assert folds[0] != folds[1]


def test_scale_override_and_camera_choice(release, tmp_path: Path) -> None:
    out = ingest_forking_paths(release.root, tmp_path / "scaled", scale=0.05, quiet=True)
    ds = open_dataset(out)
    assert ds.lineage["m_per_px"] == {"0400": 0.05, "zara01": 0.05}
    assert ds.scenes().get_column("m_per_px").unique().to_list() == [0.05]
    with pytest.raises(UsageError, match="no default for scene"):
        ingest_forking_paths(release.root, tmp_path / "cam1", camera="cam1", quiet=True)
    with pytest.raises(UsageError, match="names scene.* zara02 not in the data"):
        ingest_forking_paths(release.root, tmp_path / "cam1", scale={"zara02": 0.02}, quiet=True)
    other = write_release(tmp_path / "other", default_moments()[:2], other_camera=False)
    for moment in other.moments:
        dest, annotator, _ = moment.futures[0]
        other.file(moment, dest, annotator, "cam2").write_bytes(other.file(moment, dest, annotator).read_bytes())
    cam2 = ingest_forking_paths(other.root, tmp_path / "cam2", camera="cam2", scale={"zara01": 0.02}, folds=2,
                                quiet=True)
    assert set(open_dataset(cam2).scenes().get_column("scene_id")) == {"zara01_1_252_0_27_cam2",
                                                                        "zara01_2_40_0_27_cam2"}
