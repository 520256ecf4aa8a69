"""Synthetic rounD recordings written in exactly the levelX format, and checks that they follow it.

The real rounD data is licensed and absent, so the rounD tests (and ``bench/round.py``) generate recordings:
a four-arm roundabout (centre CENTRE, vehicles circulating counter-clockwise on a ring of LANE_RADIUS), vehicles
that drive in on one arm and out on another along smooth paths, pedestrians crossing arms, bicycles, and a grey
background image drawn to the levelX convention (pixel = metres / (orthoPxToMeter * 10), image y downwards).

:func:`gap_scenario` is the scripted recording the tests reason about:

* ``TARGET_ACCEPT`` (a car on arm 0) enters in front of ``EGO_ACCEPT`` (circulating, coming from arm 3):
  an accepted gap;
* ``TARGET_REJECT`` (a car on arm 2) stops at the yield line and lets ``EGO_REJECT`` (slow, coming from arm 0
  half-way round) pass, then enters: a rejected gap whose decision lies ~7 s ahead, so it needs 35 future steps;
* a truck, pedestrians and bicycles that never form a gap-acceptance pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
from PIL import Image

FRAME_RATE = 25
CENTRE = (65.0, -65.0)
LANE_RADIUS = 12.0
ARMS_DEG = (0.0, 90.0, 180.0, 270.0)
ARM_LENGTH = 58.0
LANE_OFFSET = 2.0
MERGE_DISTANCE = 18.0
MERGE_ANGLE = math.radians(25.0)
ORTHO_PX_TO_METER = 0.025
SCALE_DOWN = 10
IMAGE_SIZE = (520, 520)  # (height, width) in pixels at ORTHO_PX_TO_METER * SCALE_DOWN m/px
MARKER = (CENTRE[0] + 25.0, CENTRE[1] + 25.0)  # a bright 2 m square on the grass, north-east of the centre
MARKER_SIZE = 2.0

TARGET_ACCEPT, EGO_ACCEPT, TARGET_REJECT, EGO_REJECT = 1, 2, 3, 4

TRACKS_COLUMNS = ("recordingId", "trackId", "frame", "trackLifetime", "xCenter", "yCenter", "heading", "width",
                  "length", "xVelocity", "yVelocity", "xAcceleration", "yAcceleration", "lonVelocity",
                  "latVelocity", "lonAcceleration", "latAcceleration")
TRACKS_META_COLUMNS = ("recordingId", "trackId", "initialFrame", "finalFrame", "numFrames", "width", "length",
                       "class")
RECORDING_META_COLUMNS = ("recordingId", "locationId", "frameRate", "speedLimit", "weekday", "startTime",
                          "duration", "numTracks", "numVehicles", "numVRUs", "latLocation", "lonLocation",
                          "xUtmOrigin", "yUtmOrigin", "orthoPxToMeter")
SIZES = {"car": (1.9, 4.6), "van": (2.0, 5.2), "truck": (2.5, 9.0), "bus": (2.6, 12.0), "trailer": (2.5, 7.0),
         "motorcycle": (0.8, 2.2), "bicycle": (0.7, 1.8), "pedestrian": (0.6, 0.6)}


@dataclass
class Track:
    """One road user at FRAME_RATE: positions (n, 2), velocities (n, 2), heading (n,) in degrees."""

    track_id: int
    cls: str
    initial_frame: int
    positions: np.ndarray
    velocities: np.ndarray
    heading: np.ndarray


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _hermite(p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray, n: int = 200) -> np.ndarray:
    """Cubic Hermite curve from p0 (tangent t0) to p1 (tangent t1)."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    h00, h10, h01, h11 = 2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s, -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2
    return h00 * p0 + h10 * t0 + h01 * p1 + h11 * t1


def vehicle_path(arm_in: int, arm_out: int, centre: tuple[float, float] = CENTRE, radius: float = LANE_RADIUS,
                 arm_length: float = ARM_LENGTH) -> np.ndarray:
    """Dense polyline of a vehicle entering on `arm_in`, circulating counter-clockwise, leaving on `arm_out`.

    Lanes keep to the right: the entry lane lies counter-clockwise of the arm's axis, the exit lane clockwise.
    """
    c = np.asarray(centre)
    alpha = math.radians(ARMS_DEG[arm_in])
    beta = math.radians(ARMS_DEG[arm_out])
    while beta - MERGE_ANGLE <= alpha + MERGE_ANGLE:
        beta += 2 * math.pi
    side_in, side_out = _unit(alpha + math.pi / 2), _unit(beta + math.pi / 2)
    approach = np.linspace(arm_length, MERGE_DISTANCE, 200)[:, None] * _unit(alpha) + LANE_OFFSET * side_in + c
    merge_start = approach[-1]
    merge_end = c + radius * _unit(alpha + MERGE_ANGLE)
    chord = float(np.linalg.norm(merge_end - merge_start))
    merge = _hermite(merge_start, -_unit(alpha) * chord, merge_end, _unit(alpha + MERGE_ANGLE + math.pi / 2) * chord)
    ring = c + radius * np.stack([np.cos(a := np.linspace(alpha + MERGE_ANGLE, beta - MERGE_ANGLE, 400)),
                                  np.sin(a)], axis=1)
    exit_end = c + MERGE_DISTANCE * _unit(beta) - LANE_OFFSET * side_out
    chord = float(np.linalg.norm(exit_end - ring[-1]))
    leave = _hermite(ring[-1], _unit(beta - MERGE_ANGLE + math.pi / 2) * chord, exit_end, _unit(beta) * chord)
    depart = np.linspace(MERGE_DISTANCE, arm_length, 200)[:, None] * _unit(beta) - LANE_OFFSET * side_out + c
    return np.concatenate([approach, merge[1:], ring[1:], leave[1:], depart[1:]])


def crossing_path(arm: int, distance: float, length: float = 14.0) -> np.ndarray:
    """A pedestrian crossing `arm` at `distance` from the centre, perpendicular to it."""
    c = np.asarray(CENTRE)
    axis = math.radians(ARMS_DEG[arm])
    middle = c + distance * _unit(axis)
    across = _unit(axis + math.pi / 2)
    return middle + np.linspace(-length / 2, length / 2, 100)[:, None] * across


def _arc_profile(speed: float, frames: int, stop_at: float | None, go_after: float | None,
                 decel: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    """Arc length s and speed ds/dt per frame: cruise at `speed`, optionally braking to stand still at arc
    length `stop_at` and waiting until `go_after` seconds, then accelerating back to cruise speed."""
    t = np.arange(frames) / FRAME_RATE
    if stop_at is None:
        return speed * t, np.full(frames, speed)
    brake = speed ** 2 / (2 * decel)
    t1 = (stop_at - brake) / speed
    t2 = t1 + speed / decel
    go = max(go_after if go_after is not None else t2, t2)
    t3 = go + speed / decel
    s = np.select([t < t1, t < t2, t < go, t < t3],
                  [speed * t, speed * t1 + speed * (t - t1) - decel / 2 * (t - t1) ** 2, np.full_like(t, stop_at),
                   stop_at + decel / 2 * (t - go) ** 2],
                  stop_at + brake + speed * (t - t3))
    v = np.select([t < t1, t < t2, t < go, t < t3], [np.full_like(t, speed), speed - decel * (t - t1),
                                                     np.zeros_like(t), decel * (t - go)], np.full_like(t, speed))
    return s, v


def drive(track_id: int, cls: str, path: np.ndarray, start: float, speed: float, *, stop_at_distance: float | None
          = None, go_at: float | None = None) -> Track:
    """A road user following `path` from time `start` (s) at `speed` (m/s) until the path ends.

    With `stop_at_distance` the user stops where the path first comes that close to the centre and waits until
    the absolute time `go_at`.
    """
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arc = np.concatenate(([0.0], np.cumsum(steps)))
    total = arc[-1]
    stop_at = None
    if stop_at_distance is not None:
        distance = np.linalg.norm(path - np.asarray(CENTRE), axis=1)
        stop_at = float(arc[np.argmax(distance <= stop_at_distance)])
    first = math.ceil(start * FRAME_RATE)
    frames = int(total / max(speed, 0.5) * FRAME_RATE) + 40 * FRAME_RATE
    s, v = _arc_profile(speed, frames, stop_at, None if go_at is None else go_at - first / FRAME_RATE)
    keep = s <= total
    s, v = s[keep], v[keep]
    x, y = np.interp(s, arc, path[:, 0]), np.interp(s, arc, path[:, 1])
    direction = np.unwrap(np.arctan2(np.gradient(path[:, 1]), np.gradient(path[:, 0])))
    course = np.interp(s, arc, direction)
    velocities = v[:, None] * np.stack([np.cos(course), np.sin(course)], axis=1)
    return Track(track_id, cls, first, np.stack([x, y], axis=1), velocities, np.degrees(course) % 360.0)


def gap_scenario(time_shift: float = 0.0, speed_scale: float = 1.0) -> list[Track]:
    """The scripted recording of the module docstring (times shifted by `time_shift`, speeds scaled)."""
    k = speed_scale
    tracks = [
        drive(EGO_ACCEPT, "car", vehicle_path(3, 1), 1.0 + time_shift, 8.0 * k),
        drive(TARGET_ACCEPT, "car", vehicle_path(0, 1), 1.85 + time_shift, 8.0 * k),
        drive(EGO_REJECT, "van", vehicle_path(0, 3), 14.0 + time_shift, 5.0 * k),
        drive(TARGET_REJECT, "car", vehicle_path(2, 3), 17.0 + time_shift, 8.0 * k, stop_at_distance=18.2,
              go_at=31.0 + time_shift),
        drive(5, "truck", vehicle_path(1, 0), 45.0 + time_shift, 7.0 * k),
        drive(6, "pedestrian", crossing_path(1, 30.0), 5.0 + time_shift, 1.4),
        drive(7, "pedestrian", crossing_path(2, 30.0)[::-1], 30.0 + time_shift, 1.2),
        drive(8, "bicycle", vehicle_path(3, 2), 47.0 + time_shift, 4.0),
        drive(9, "bicycle", np.linspace(20.0, ARM_LENGTH, 50)[:, None] * _unit(math.pi)
              - LANE_OFFSET * _unit(math.pi / 2 + math.pi) + np.asarray(CENTRE), 3.0 + time_shift, 4.5),
    ]
    return tracks


def background(marker: tuple[float, float] = MARKER) -> np.ndarray:
    """A grey aerial-like image (uint8) of the roundabout: grass, island, carriageway, arms and a white marker."""
    height, width = IMAGE_SIZE
    metres = ORTHO_PX_TO_METER * SCALE_DOWN
    rows, cols = np.mgrid[0:height, 0:width]
    x, y = cols * metres, -rows * metres                       # pixel centres, levelX convention (y up)
    dx, dy = x - CENTRE[0], y - CENTRE[1]
    r = np.hypot(dx, dy)
    image = np.full((height, width), 150, dtype=np.uint8)      # grass
    for arm in ARMS_DEG:
        axis = _unit(math.radians(arm))
        along, across = dx * axis[0] + dy * axis[1], -dx * axis[1] + dy * axis[0]
        image[(along > 0) & (np.abs(across) < 5.0)] = 60      # arm carriageway
    image[(r >= LANE_RADIUS - 3.5) & (r <= LANE_RADIUS + 3.5)] = 50   # circulating carriageway
    image[r < LANE_RADIUS - 3.5] = 110                          # central island
    image[(np.abs(x - marker[0]) <= MARKER_SIZE / 2) & (np.abs(y - marker[1]) <= MARKER_SIZE / 2)] = 255
    return image


def write_recording(folder: Path, recording_id: int, tracks: list[Track], *, location_id: int = 1,
                    image: np.ndarray | None = None, frame_rate: int = FRAME_RATE) -> Path:
    """Write XX_recordingMeta.csv, XX_tracksMeta.csv, XX_tracks.csv and XX_background.png into `folder`
    (levelx_fixture's writer of the drone layout, with the roundabout image)."""
    from levelx_fixture import write_drone_recording

    return write_drone_recording(folder, recording_id, tracks, member="round", location_id=location_id,
                                 image=background() if image is None else image, frame_rate=frame_rate)


def write_gap_recordings(folder: Path, count: int = 1) -> Path:
    """`count` scripted gap-acceptance recordings (ids 0..count-1), each slightly faster than the previous."""
    for index in range(count):
        write_recording(folder, index, gap_scenario(time_shift=0.4 * index, speed_scale=1.0 + 0.02 * index))
    return folder


def test_written_files_follow_the_levelx_columns(tmp_path: Path) -> None:
    write_gap_recordings(tmp_path)
    assert tuple(pl.read_csv(tmp_path / "00_tracks.csv", n_rows=1).columns) == TRACKS_COLUMNS
    assert tuple(pl.read_csv(tmp_path / "00_tracksMeta.csv").columns) == TRACKS_META_COLUMNS
    assert tuple(pl.read_csv(tmp_path / "00_recordingMeta.csv").columns) == RECORDING_META_COLUMNS
    with Image.open(tmp_path / "00_background.png") as image:
        assert image.size == (IMAGE_SIZE[1], IMAGE_SIZE[0])


def test_tracks_are_contiguous_and_match_their_meta(tmp_path: Path) -> None:
    write_gap_recordings(tmp_path)
    tracks = pl.read_csv(tmp_path / "00_tracks.csv")
    meta = pl.read_csv(tmp_path / "00_tracksMeta.csv")
    spans = tracks.group_by("trackId").agg(pl.col("frame").min().alias("initialFrame"),
                                          pl.col("frame").max().alias("finalFrame"), pl.len().alias("numFrames"))
    joined = meta.join(spans, on="trackId", suffix="_seen")
    assert (joined["initialFrame"] == joined["initialFrame_seen"]).all()
    assert (joined["numFrames"] == joined["numFrames_seen"]).all()
    assert (joined["finalFrame"] - joined["initialFrame"] + 1 == joined["numFrames"]).all()


def test_vehicles_circulate_counter_clockwise_on_the_ring() -> None:
    path = vehicle_path(3, 1)
    r = np.hypot(path[:, 0] - CENTRE[0], path[:, 1] - CENTRE[1])
    assert r.min() > LANE_RADIUS - 0.3                # the merge curves never cut into the island
    on_ring = np.abs(r - LANE_RADIUS) < 1e-6
    angle = np.unwrap(np.arctan2(path[on_ring, 1] - CENTRE[1], path[on_ring, 0] - CENTRE[0]))
    assert np.all(np.diff(angle) > 0)
