"""nuScenes through nuscenes-devkit: a small release in the official format, ingested and compared with what was
written into it (positions, timing, agent ids and types, challenge samples and splits, short pasts, maps)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest

pytest.importorskip("nuscenes", reason="nuscenes-devkit is not installed (pip install -e '.[nuscenes]')")

from nuscenes_fixture import (SMALL_CHALLENGE, AgentSpec, MapRects, Release, SceneSpec, map_rects,  # noqa: E402
                              small_scenes, write_expansion, write_release)

from trajflow_pipeline.data import load_problems  # noqa: E402
from trajflow_pipeline.ingest.base import collect_warnings  # noqa: E402
from trajflow_pipeline.ingest.nuscenes import EGO_AGENT_ID, agent_type_of, ingest_nuscenes, quaternion_yaw  # noqa: E402
from trajflow_pipeline.schemas import open_dataset  # noqa: E402
from trajflow_pipeline.stages.inspect import summarize  # noqa: E402


def ingest(release: Release, out: Path, **options) -> tuple[Path, list[str]]:
    """Ingest quietly, returning the dataset path and the messages of the ingest's own warnings."""
    with collect_warnings() as messages:
        path = ingest_nuscenes(release.root, out, version=release.version, quiet=True, **options)
    return path, messages


@pytest.fixture(scope="module")
def mini(tmp_path_factory: pytest.TempPathFactory) -> tuple[Release, Path, list[str]]:
    """The two-scene mini release with challenge entries, no map expansion, ingested once."""
    root = tmp_path_factory.mktemp("nuscenes")
    release = write_release(root / "nuscenes")
    out, messages = ingest(release, root / "data")
    return release, out, messages


def instance_index(release: Release) -> dict[str, int]:
    rows = json.loads((release.table_root / "instance.json").read_text())
    return {row["token"]: index for index, row in enumerate(rows)}


def test_tracks_match_the_release(mini) -> None:
    """Every agent of a mapped category at every keyframe: global positions, real times, yaw, box size, ids."""
    release, out, _ = mini
    tracks = open_dataset(out).tracks().filter(~pl.col("padded"))
    index = instance_index(release)
    expected_rows = 0
    for scene in release.scenes:
        for number, agent in enumerate(scene.agents):
            token = release.instance_token(scene.name, number)
            rows = tracks.filter((pl.col("scene_id") == scene.name) & (pl.col("instance_token") == token))
            if agent_type_of(agent.category) is None:
                assert rows.height == 0, agent.category
                continue
            expected_rows += len(agent.frames())
            assert rows.get_column("frame").to_list() == list(agent.frames())
            assert set(rows.get_column("agent_id")) == {index[token] + 1}
            assert set(rows.get_column("agent_type")) == {agent_type_of(agent.category)}
            assert set(rows.get_column("category")) == {agent.category}
            seconds = [release.seconds(scene.name, f) for f in agent.frames()]
            np.testing.assert_allclose(rows.get_column("t").to_numpy(), seconds, atol=1e-9)
            np.testing.assert_allclose(rows.select("x", "y").to_numpy(),
                                       [agent.position(s)[:2] for s in seconds], atol=1e-9)
            np.testing.assert_allclose(rows.get_column("heading").to_numpy(), agent.yaw, atol=1e-9)
            np.testing.assert_allclose(rows.get_column("length").to_numpy(), agent.size[1])
            np.testing.assert_allclose(rows.get_column("width").to_numpy(), agent.size[0])
            assert rows.get_column("timestamp_us").to_list() == [release.timestamps[scene.name][f]
                                                                 for f in agent.frames()]
        ego = tracks.filter((pl.col("scene_id") == scene.name) & (pl.col("agent_id") == EGO_AGENT_ID))
        expected_rows += scene.n_frames
        assert ego.get_column("frame").to_list() == list(range(scene.n_frames))
        assert set(ego.get_column("instance_token")) == {"ego"} and set(ego.get_column("agent_type")) == {"vehicle"}
        # the LIDAR_TOP keyframe pose, not the camera's (taken 12 ms later) nor a sweep's
        np.testing.assert_allclose(
            ego.select("x", "y").to_numpy(),
            [scene.ego_position(release.seconds(scene.name, f))[:2] for f in range(scene.n_frames)], atol=1e-9)
        np.testing.assert_allclose(ego.get_column("heading").to_numpy(), scene.ego_yaw, atol=1e-9)
    assert tracks.height == expected_rows
    assert set(tracks.get_column("agent_type")) == {"vehicle", "pedestrian", "bicycle", "unknown"}


def test_challenge_samples_splits_and_counts(mini) -> None:
    """Samples are the prediction_scenes.json entries with a full future; mini_train -> train, mini_val -> test."""
    release, out, messages = mini
    ds = open_dataset(out)
    assert ds.meta.protocol == "fixed" and ds.meta.dt == 0.5
    samples = ds.samples()
    assert (samples.get_column("n_past") == 4).all() and (samples.get_column("n_future") == 12).all()
    got = {(row["scene_id"], row["instance_token"], row["t0_frame"]): row for row in samples.iter_rows(named=True)}
    expected = {}
    for scene_name, entries in SMALL_CHALLENGE.items():
        scene = release.scene(scene_name)
        for agent, t0 in entries:
            if t0 + 12 <= scene.agents[agent].last_frame:
                expected[(scene_name, release.instance_token(scene_name, agent), t0)] = (agent, t0)
    assert set(got) == set(expected)
    for key, (agent, t0) in expected.items():
        row = got[key]
        assert row["sample_token"] == release.sample_tokens[key[0]][t0]
        assert row["challenge_split"] == {"scene-0061": "mini_train", "scene-0103": "mini_val"}[key[0]]
        assert row["split"] == {"mini_train": "train", "mini_val": "test"}[row["challenge_split"]]
        first = release.scene(key[0]).agents[agent].first_frame
        assert row["past_available"] == min(4, t0 - first + 1)
    counts = dict(samples.group_by("split").len().iter_rows())
    assert counts == {"train": 5, "test": 2}
    assert ds.lineage["dropped_challenge_entries"] == {"with a future shorter than 12 keyframes": 1}
    assert any("dropped 1 prediction-challenge entry" in m and "prediction_scenes.json" in m for m in messages)
    # samples of one scene and t0 are predicted jointly; all inputs differ here
    assert samples.filter(pl.col("scene_id") == "scene-0061").group_by("t0_frame").agg(
        pl.col("joint_id").n_unique()).get_column("joint_id").to_list() == [1, 1, 1, 1]
    assert samples.get_column("group_id").n_unique() == samples.height


def test_short_pasts_are_padded_with_the_first_position(mini) -> None:
    """A target seen for fewer than 4 keyframes keeps its real past; earlier frames repeat the first position."""
    release, out, _ = mini
    tracks = open_dataset(out).tracks()
    padded = tracks.filter(pl.col("padded"))
    # scene-0061: the pedestrian (first frame 2) at t0 2 and 3 -> frames -1, 0, 1; scene-0103: the child at t0 0
    assert sorted(padded.select("scene_id", "frame").iter_rows()) == [
        ("scene-0061", -1), ("scene-0061", 0), ("scene-0061", 1),
        ("scene-0103", -3), ("scene-0103", -2), ("scene-0103", -1)]
    pedestrian = release.scene("scene-0061").agents[1]
    first = pedestrian.position(release.seconds("scene-0061", 2))
    rows = padded.filter(pl.col("scene_id") == "scene-0061")
    np.testing.assert_allclose(rows.select("x", "y").to_numpy(), [first[:2]] * 3, atol=1e-9)
    assert rows.get_column("t").to_list() == pytest.approx([-0.5, 0.0, release.seconds("scene-0061", 1)])
    assert rows.get_column("timestamp_us").null_count() == 1
    # the model sees 4 past positions for every sample: the padded ones first, then the real ones
    problems = load_problems(out, split="train")
    order = list(problems.t0_frame)
    b = next(i for i, (agent, t0) in enumerate(zip(problems.agent_id, order)) if t0 == 2)
    past = problems.batch.past[b].numpy()
    np.testing.assert_allclose(past[:3], [first[:2]] * 3, atol=1e-4)
    np.testing.assert_allclose(past[3], first[:2], atol=1e-4)
    assert problems.batch.future.shape[1:] == (12, 2)


def test_scenes_table_without_maps(mini) -> None:
    release, out, messages = mini
    scenes = open_dataset(out).scenes()
    assert scenes.get_column("scene_id").to_list() == ["scene-0061", "scene-0103"]
    assert scenes.get_column("location").to_list() == ["singapore-onenorth", "boston-seaport"]
    assert scenes.get_column("split").to_list() == ["train", "test"]
    assert scenes.get_column("keyframes").to_list() == [20, 16]
    assert scenes.get_column("scene_token").to_list() == [release.scene_tokens["scene-0061"],
                                                          release.scene_tokens["scene-0103"]]
    assert scenes.get_column("map_path").null_count() == 2
    assert any("map expansion not found" in m and "maps/expansion" in m for m in messages)
    assert summarize(out)["has_map"] is False


def test_all_agents_makes_samples_from_every_complete_window(tmp_path: Path) -> None:
    """Without prediction_scenes.json, --all-agents: every annotated agent with 4 past + 12 future keyframes."""
    release = write_release(tmp_path / "nuscenes", prediction=False)
    out, _ = ingest(release, tmp_path / "data", all_agents=True)
    ds = open_dataset(out)
    samples = ds.samples()
    expected = set()
    for scene in release.scenes:
        for number, agent in enumerate(scene.agents):
            if agent_type_of(agent.category) is not None:
                expected |= {(scene.name, release.instance_token(scene.name, number), t0)
                             for t0 in range(agent.first_frame + 3, agent.last_frame - 12 + 1)}
    assert set(samples.select("scene_id", "instance_token", "t0_frame").iter_rows()) == expected
    assert dict(samples.group_by("split").len().iter_rows()) == {"train": 8, "test": 1}
    assert (samples.get_column("past_available") == 4).all()
    assert ds.tracks().get_column("padded").sum() == 0
    assert ds.lineage["samples"] == "all-agents"


def test_trainval_maps_challenge_splits_to_train_val_test(tmp_path: Path) -> None:
    """trainval: train -> train, train_val (first 200 train scenes) -> val, val -> test."""
    walker = AgentSpec("vehicle.car", 0, 17, (10.0, 20.0), (5.0, 0.0))
    scenes = [SceneSpec(name, "boston-seaport", 18, (walker,)) for name in ("scene-0001", "scene-0003", "scene-0301")]
    challenge = {name: [(0, 4), (0, 5)] for name in ("scene-0001", "scene-0003", "scene-0301")}
    release = write_release(tmp_path / "nuscenes", scenes, version="v1.0-trainval", challenge=challenge)
    out, _ = ingest(release, tmp_path / "data")
    samples = open_dataset(out).samples()
    by_scene = dict(samples.group_by("scene_id").agg(pl.col("split").unique().first(),
                                                     pl.col("challenge_split").unique().first())
                    .select("scene_id", pl.struct("split", "challenge_split")).iter_rows())
    assert by_scene == {"scene-0001": {"split": "val", "challenge_split": "train_val"},
                        "scene-0003": {"split": "test", "challenge_split": "val"},
                        "scene-0301": {"split": "train", "challenge_split": "train"}}
    assert samples.height == 6


def test_maps_are_rasterised_from_the_expansion(tmp_path: Path) -> None:
    """Grey levels at known world points (through the stored affine), resolution, coverage and loader flag."""
    release = write_release(tmp_path / "nuscenes", expansion=True)
    out, messages = ingest(release, tmp_path / "data")
    assert not [m for m in messages if "map" in m and "expansion" in m]
    ds = open_dataset(out)
    scenes = ds.scenes()
    tracks = ds.tracks()
    assert summarize(out)["has_map"] is True
    from PIL import Image

    for row in scenes.iter_rows(named=True):
        assert row["map_path"] == f"maps/{row['scene_id']}.png" and row["map_m_per_px"] == 0.1
        image = Image.open(out / row["map_path"])
        assert image.mode == "L"
        grey = np.asarray(image)
        a, b, c, d, e, f = row["map_world_to_px"]
        assert (a, b, d, e) == (10.0, 0.0, 0.0, -10.0)

        def level(x: float, y: float) -> int:
            column, line = int(round(a * x + b * y + c)), int(round(d * x + e * y + f))
            assert 0 <= column < grey.shape[1] and 0 <= line < grey.shape[0], (x, y)
            return int(grey[line, column])

        scene = release.scene(row["scene_id"])
        rects: MapRects = map_rects([scene])
        (dx0, dy0, dx1, dy1), = rects.drivable
        (wx0, wy0, wx1, wy1), = rects.walkways
        (cx0, cy0, cx1, cy1), = rects.crossings
        assert level(dx0 + 5, dy0 + 2) == 170
        assert level(cx0 + 3, (cy0 + cy1) / 2) == 255
        assert level(dx0 + 5, (wy0 + wy1) / 2) == 85
        assert level(dx0 + 5, wy1 + 3) == 0 and level(dx0 + 5, dy0 - 3) == 0 and level(dx0 - 3, dy0 + 2) == 0
        # edges within 2 pixels
        assert level(dx0 + 5, dy0 + 0.2) == 170 and level(dx0 + 5, dy0 - 0.2) == 0
        assert level(cx0 - 0.2, dy0 + 2) == 170 and level(cx0 + 0.2, dy0 + 2) == 255
        # every position of the scene lies at least the margin (80 m) inside the raster
        xy = tracks.filter(pl.col("scene_id") == row["scene_id"]).select("x", "y").to_numpy()
        px, py = a * xy[:, 0] + c, e * xy[:, 1] + f
        assert px.min() >= 799 and py.min() >= 799
        assert px.max() <= grey.shape[1] - 800 and py.max() <= grey.shape[0] - 800
    assert load_problems(out, split="test").has_map
    # the model's heading-aligned crops read these rasters: on the road (12 m from any edge) the crop centre is road
    from trajflow_pipeline.data.maps import crops_for_problems

    car = release.scene("scene-0061").agents[0]
    position = np.array([car.position(release.seconds("scene-0061", 7))[:2]])
    crops = crops_for_problems(out, ["scene-0061"], position, np.array([car.yaw]))
    centre = crops[0, 0, crops.shape[2] // 2, crops.shape[3] // 2]
    assert centre == pytest.approx(170 / 255, abs=0.01)
    assert crops.min() == 0.0 and crops.max() > 0.9  # off-road and the crossing are in view too


def test_partial_expansion_maps_only_its_locations(tmp_path: Path) -> None:
    release = write_release(tmp_path / "nuscenes")
    write_expansion(release.root, "boston-seaport", [release.scene("scene-0103")])
    out, messages = ingest(release, tmp_path / "data")
    scenes = open_dataset(out).scenes()
    assert dict(scenes.select("scene_id", "map_path").iter_rows()) == {"scene-0061": None,
                                                                       "scene-0103": "maps/scene-0103.png"}
    assert any("no map expansion for singapore-onenorth" in m and "1 scene(s)" in m for m in messages)


def test_quaternion_yaw_matches_the_devkit() -> None:
    from nuscenes.eval.common.utils import quaternion_yaw as devkit_yaw
    from pyquaternion import Quaternion

    rng = np.random.default_rng(0)
    rotations = rng.normal(size=(50, 4)) * rng.uniform(0.5, 2.0, size=(50, 1))
    expected = [devkit_yaw(Quaternion(q)) for q in rotations]
    np.testing.assert_allclose(quaternion_yaw(rotations), expected, atol=1e-12)
    yaw = np.array([0.3, -2.0, math.pi - 1e-3])
    flat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=1)
    np.testing.assert_allclose(quaternion_yaw(flat), yaw, atol=1e-12)


def test_category_mapping_covers_the_official_categories() -> None:
    from nuscenes_fixture import CATEGORIES

    mapped = {name: agent_type_of(name) for name in CATEGORIES}
    assert mapped["vehicle.bicycle"] == "bicycle" and mapped["vehicle.motorcycle"] == "motorcycle"
    assert {mapped[n] for n in CATEGORIES if n.startswith("vehicle.") and n not in (
        "vehicle.bicycle", "vehicle.motorcycle")} == {"vehicle"}
    assert {mapped[n] for n in CATEGORIES if n.startswith("human.pedestrian.")} == {"pedestrian"}
    assert mapped["animal"] == "unknown"
    assert {n for n, t in mapped.items() if t is None} == {n for n in CATEGORIES if n.startswith(
        ("movable_object.", "static_object."))}


def test_small_scenes_fixture_is_what_the_issue_asks_for() -> None:
    """Two official mini scene names, a car, a pedestrian and the ego vehicle in each (guards the fixture)."""
    scenes = small_scenes()
    assert [s.name for s in scenes] == ["scene-0061", "scene-0103"]
    for scene in scenes:
        kinds = {agent_type_of(a.category) for a in scene.agents}
        assert {"vehicle", "pedestrian"} <= kinds


def test_layer_index_gives_the_devkits_raster(tmp_path: Path) -> None:
    """Handing get_map_mask only the records near a scene changes nothing in the raster."""
    from trajflow_pipeline.ingest import nuscenes_maps
    from trajflow_pipeline.ingest.nuscenes import load_devkit

    rng = np.random.default_rng(1)

    def rects(n: int, size: float) -> tuple[tuple[float, float, float, float], ...]:
        corners = rng.uniform(0.0, 2000.0, size=(n, 2))
        return tuple((x, y, x + size * rng.uniform(0.2, 1.0), y + size * rng.uniform(0.2, 1.0)) for x, y in corners)

    layout = MapRects(drivable=rects(40, 150.0), walkways=rects(200, 30.0), crossings=rects(100, 8.0))
    write_expansion(tmp_path, "singapore-queenstown", [], layout)
    nusc_map = nuscenes_maps.load_expansion(load_devkit().NuScenesMap, tmp_path, "singapore-queenstown")
    index = nuscenes_maps.index_layers(nusc_map)
    for bounds in ((900.0, 800.0, 1100.0, 950.0), (0.0, 0.0, 60.0, 40.0), (1900.0, 1950.0, 2100.0, 2050.0)):
        grid = nuscenes_maps.scene_grid(bounds, m_per_px=0.25)
        plain = nuscenes_maps.rasterize(nusc_map, grid)
        assert (nuscenes_maps.rasterize(nusc_map, grid, index=index) == plain).all()
        assert (plain > 0).any() and (plain == 0).any()
    assert len(nusc_map.walkway) == 200  # the layers are restored afterwards
