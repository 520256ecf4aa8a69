"""Heading-aligned map crops: orientation, scale, placement, out-of-map zeros, per-scene maps of a dataset."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from PIL import Image

from trajflow_pipeline.data.maps import (MapRaster, crop_offsets, crops_for_problems, heading_aligned_crops,
                                         past_headings, read_map, world_to_pixels)
from trajflow_pipeline.errors import DataError
from trajflow_pipeline.schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter

M_PER_PX = 0.5
#: levelX-like affine: px = x / 0.5, py = -y / 0.5 (image rows grow downwards, world y upwards)
AFFINE = (1 / M_PER_PX, 0.0, 0.0, 0.0, -1 / M_PER_PX, 0.0)
MARKER = np.array([80.0, -40.0])
AGENT = np.array([70.0, -50.0])


def marker_raster(shape: tuple[int, int] = (200, 300), marker: np.ndarray = MARKER, half: float = 1.25,
                  affine: tuple[float, ...] = AFFINE, metres: float = M_PER_PX) -> np.ndarray:
    """A black raster with a white square of side 2 * half metres centred on `marker`."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    a, b, c, d, e, f = affine
    inverse = np.linalg.inv(np.array([[a, b], [d, e]]))
    world = np.stack((cols - c, rows - f), -1) @ inverse.T
    inside = np.all(np.abs(world - marker) <= half + 1e-9, axis=-1)
    return inside.astype(np.float32)


def expected_cell(heading: float, metres: float = M_PER_PX, ahead: float = 0.5, height: int = 156,
                  width: int = 257, marker: np.ndarray = MARKER, agent: np.ndarray = AGENT) -> tuple[float, float]:
    """(row, col) where `marker` must appear in a crop around `agent` with `heading`."""
    dx, dy = marker - agent
    along = math.cos(heading) * dx + math.sin(heading) * dy
    left = -math.sin(heading) * dx + math.cos(heading) * dy
    return (height - 1) / 2 - left / metres, (1 - ahead) * (width - 1) + along / metres


def centre_of_mass(crop: np.ndarray) -> tuple[float, float]:
    rows, cols = np.mgrid[0:crop.shape[0], 0:crop.shape[1]]
    total = crop.sum()
    return float((rows * crop).sum() / total), float((cols * crop).sum() / total)


HEADINGS = [0.0, math.pi / 2, math.pi, -math.pi / 4, 3.0, -2.2]


def test_marker_lands_where_the_heading_puts_it() -> None:
    raster = marker_raster()
    crops = heading_aligned_crops(raster, AFFINE, np.tile(AGENT, (len(HEADINGS), 1)), np.array(HEADINGS))
    assert crops.shape == (len(HEADINGS), 1, 156, 257) and crops.dtype == np.float32
    for crop, heading in zip(crops[:, 0], HEADINGS):
        # bilinear resampling of a rotated square moves its centre of mass by a small fraction of a pixel
        assert centre_of_mass(crop) == pytest.approx(expected_cell(heading), abs=0.15)
        assert crop.sum() == pytest.approx(raster.sum(), rel=0.02)     # same scale: the square keeps its area


def test_heading_points_right_and_left_points_up() -> None:
    """A marker straight ahead is right of the agent's column; one to the agent's left is above its row."""
    raster = marker_raster()
    heading = math.radians(30)
    ahead = AGENT + 12 * np.array([math.cos(heading), math.sin(heading)])
    left = AGENT + 12 * np.array([-math.sin(heading), math.cos(heading)])
    for marker, check in ((ahead, lambda r, c: c > 128 + 20 and abs(r - 77.5) < 0.5),
                          (left, lambda r, c: r < 77.5 - 20 and abs(c - 128) < 0.5)):
        crop = heading_aligned_crops(marker_raster(marker=marker), AFFINE, AGENT[None], np.array([heading]))[0, 0]
        assert check(*centre_of_mass(crop)), centre_of_mass(crop)
    del raster


def test_heading_zero_is_the_raster_itself_when_pixels_align() -> None:
    rng = np.random.default_rng(0)
    raster = rng.random((400, 400)).astype(np.float32)
    agent = np.array([100.0, -(100 + 77.5) * M_PER_PX])        # crop pixel centres fall on raster pixel centres
    crop = heading_aligned_crops(raster, AFFINE, agent[None], np.zeros(1))[0, 0]
    np.testing.assert_allclose(crop, raster[100:256, 72:329], atol=1e-4)


def test_scale_and_ahead_fraction() -> None:
    raster = marker_raster()
    for metres, ahead in ((1.0, 0.5), (0.25, 0.5), (0.5, 0.8), (0.5, 0.2)):
        crop = heading_aligned_crops(raster, AFFINE, AGENT[None], np.array([0.7]), metres_per_pixel_out=metres,
                                     ahead_fraction=ahead)[0, 0]
        assert centre_of_mass(crop) == pytest.approx(expected_cell(0.7, metres, ahead), abs=0.15)


def test_outside_the_map_is_zero_and_uint8_is_scaled() -> None:
    raster = np.full((200, 300), 200, dtype=np.uint8)
    crops = heading_aligned_crops(raster, AFFINE, np.array([[1000.0, 1000.0], [0.0, -50.0]]), np.zeros(2))
    assert np.all(crops[0] == 0)
    edge = crops[1, 0]                                         # agent on the raster's left edge, heading +x
    assert np.all(edge[:, :127] == 0)
    assert np.allclose(edge[40:110, 129:200], 200 / 255, atol=1e-6)
    assert 0.0 <= crops.min() and crops.max() <= 1.0


def test_custom_crop_size_and_input_checks() -> None:
    crops = heading_aligned_crops(marker_raster(), AFFINE, AGENT[None], np.zeros(1), height=41, width=64)
    assert crops.shape == (1, 1, 41, 64)
    assert heading_aligned_crops(marker_raster(), AFFINE, np.zeros((0, 2)), np.zeros(0)).shape == (0, 1, 156, 257)
    with pytest.raises(ValueError, match="positions but"):
        heading_aligned_crops(marker_raster(), AFFINE, np.zeros((2, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="raster must be"):
        heading_aligned_crops(np.zeros((5, 5, 3)), AFFINE, np.zeros((1, 2)), np.zeros(1))
    with pytest.raises(ValueError, match="ahead_fraction"):
        crop_offsets(10, 10, 0.5, 1.5)


def test_many_problems_are_chunked_consistently() -> None:
    raster = marker_raster()
    headings = np.linspace(-3, 3, 300)
    batch = heading_aligned_crops(raster, AFFINE, np.tile(AGENT, (300, 1)), headings)
    single = heading_aligned_crops(raster, AFFINE, AGENT[None], headings[[257]])
    np.testing.assert_array_equal(batch[257], single[0])


def test_reduced_raster_keeps_the_world_alignment() -> None:
    fine_affine = (10.0, 0.0, 0.0, 0.0, -10.0, 0.0)            # 0.1 m per pixel
    raster = MapRaster(marker_raster((1000, 1500), affine=fine_affine, metres=0.1, half=2.0), 0.1, fine_affine)
    reduced = raster.reduced(0.5)
    assert reduced.image.shape == (200, 300) and reduced.m_per_px == pytest.approx(0.5)
    col, row = reduced.to_pixels(MARKER)
    assert centre_of_mass(reduced.image) == pytest.approx((row, col), abs=0.05)
    np.testing.assert_allclose(world_to_pixels(MARKER, reduced.world_to_px), raster.to_pixels(MARKER) / 5 - 0.4)


def test_past_headings_follow_the_models_normalisation() -> None:
    past = np.zeros((3, 4, 2))
    past[0, :, 1] = np.arange(4)                                # moving along +y
    past[1, :, 0] = [0, -1, -2, -2]                             # moving along -x, standing at the end
    assert past_headings(past) == pytest.approx([math.pi / 2, math.pi, 0.0])


def _write_dataset(root: Path) -> Path:
    """Three scenes: a and b with different marker maps (b at 0.1 m per pixel), c without a map."""
    meta = DatasetMeta(dataset="maps_test", dt=0.2, protocol=PROTOCOL_FOLDS)
    fine = (10.0, 0.0, 0.0, 0.0, -10.0, 0.0)
    scenes = pl.DataFrame({
        "dataset": ["maps_test"] * 3, "scene_id": ["a", "b", "c"], "location": ["l"] * 3, "dt": [0.2] * 3,
        "source": ["x"] * 3, "fold": [None, None, None], "map_path": ["maps/a.png", "maps/b.png", None],
        "map_m_per_px": [M_PER_PX, 0.1, None], "map_world_to_px": [list(AFFINE), list(fine), None]},
        schema_overrides={"fold": pl.String, "map_world_to_px": pl.List(pl.Float64)})
    tracks = pl.DataFrame({"scene_id": ["a", "b", "c"], "agent_id": [1, 1, 1], "agent_type": ["vehicle"] * 3,
                           "frame": [0, 0, 0], "t": [0.0] * 3, "x": [0.0] * 3, "y": [0.0] * 3})
    samples = pl.DataFrame({"sample_id": [0, 1, 2], "scene_id": ["a", "b", "c"], "agent_id": [1, 1, 1],
                            "t0_frame": [0, 0, 0], "n_past": [1] * 3, "n_future": [1] * 3, "group_id": [0, 1, 2],
                            "split": ["train"] * 3, "fold": ["0"] * 3})
    with DatasetWriter(root, meta) as writer:
        (writer.root / "maps").mkdir()
        Image.fromarray((marker_raster() * 255).astype(np.uint8)).save(writer.root / "maps" / "a.png")
        b = marker_raster((1000, 1500), marker=np.array([60.0, -60.0]), affine=fine, metres=0.1, half=2.0)
        Image.fromarray((b * 255).astype(np.uint8)).convert("RGB").save(writer.root / "maps" / "b.png")
        writer.add_tracks(tracks)
        writer.finish(scenes, samples)
    return root


def test_crops_for_problems_use_each_scenes_map(tmp_path: Path) -> None:
    data = _write_dataset(tmp_path / "data")
    scene = np.array(["a", "b", "c", "a", "nowhere"])
    position = np.tile(AGENT, (5, 1))
    heading = np.array([0.0, 0.0, 0.0, math.pi / 2, 0.0])
    crops = crops_for_problems(data, scene, position, heading)
    assert crops.shape == (5, 1, 156, 257)
    assert centre_of_mass(crops[0, 0]) == pytest.approx(expected_cell(0.0), abs=0.05)
    assert centre_of_mass(crops[3, 0]) == pytest.approx(expected_cell(math.pi / 2), abs=0.05)
    assert centre_of_mass(crops[1, 0]) == pytest.approx(expected_cell(0.0, marker=np.array([60.0, -60.0])), abs=0.3)
    assert not crops[2].any() and not crops[4].any()           # no map, unknown scene: zeros


def test_unreadable_or_missing_map_is_named(tmp_path: Path) -> None:
    data = _write_dataset(tmp_path / "data")
    (data / "maps" / "a.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"a\.png: cannot open map raster"):
        crops_for_problems(data, np.array(["a"]), AGENT[None], np.zeros(1))
    (data / "maps" / "b.png").unlink()
    with pytest.raises(DataError, match=r"b\.png: map raster of scene 'b' is missing"):
        crops_for_problems(data, np.array(["b"]), AGENT[None], np.zeros(1))
    with pytest.raises(DataError, match="map_world_to_px must be 6"):
        read_map(data / "maps" / "a.png", 0.5, [1.0, 2.0])


def _set_map_path(data: Path, scene: str, value: str) -> None:
    """Hand-edit one scene's map_path, keeping the file's trajflow metadata."""
    import pyarrow.parquet as pq

    table = pq.read_table(data / "scenes.parquet")
    frame = pl.from_arrow(table).with_columns(
        map_path=pl.when(pl.col("scene_id") == scene).then(pl.lit(value)).otherwise(pl.col("map_path")))
    pq.write_table(frame.to_arrow().replace_schema_metadata(table.schema.metadata), data / "scenes.parquet")


@pytest.mark.parametrize("outside", ["/etc/hostname", "../secret.png", "maps/../../secret.png", "C:\\maps\\a.png"])
def test_map_paths_outside_the_dataset_are_refused_by_the_table_check(tmp_path: Path, outside: str) -> None:
    from trajflow_pipeline.schemas import open_dataset

    data = _write_dataset(tmp_path / "data")
    _set_map_path(data, "a", outside)
    with pytest.raises(DataError, match=r"scenes\.parquet: scenes table: map_path must be a path inside the "
                                        r"dataset directory .* \(rows 0; 0-based\)"):
        open_dataset(data).scenes()


def test_a_map_that_links_out_of_the_dataset_or_is_no_file_is_refused(tmp_path: Path) -> None:
    import os

    data = _write_dataset(tmp_path / "data")
    outside = tmp_path / "elsewhere.png"
    outside.write_bytes((data / "maps" / "a.png").read_bytes())
    (data / "maps" / "a.png").unlink()
    (data / "maps" / "a.png").symlink_to(outside)
    with pytest.raises(DataError, match=r"a\.png: map raster of scene 'a' leads outside the dataset directory"):
        crops_for_problems(data, np.array(["a"]), AGENT[None], np.zeros(1))
    (data / "maps" / "a.png").unlink()
    os.mkfifo(data / "maps" / "a.png")  # would block a reader forever
    with pytest.raises(DataError, match=r"a\.png: is a FIFO, not a file that can be read"):
        crops_for_problems(data, np.array(["a"]), AGENT[None], np.zeros(1))
    inside = data / "maps" / "link.png"
    inside.symlink_to(data / "maps" / "b.png")  # a link within the dataset is fine
    _set_map_path(data, "b", "maps/link.png")
    assert crops_for_problems(data, np.array(["b"]), AGENT[None], np.zeros(1)).any()
