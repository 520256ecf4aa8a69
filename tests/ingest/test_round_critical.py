"""rounD critical time t_crit: the last frame at which the ego could still stop before the conflict zone, and the
exclusion of gap-acceptance samples predicted at or after it (Schumann et al.'s ``exclude_post_crit``)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from test_round_synth import CENTRE, EGO_REJECT, SIZES, TARGET_REJECT, Track, gap_scenario, write_recording

from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.round import (CRITICAL_DECELERATION, DT, N_PAST, critical_frames,
                                            ingest_round)
from trajflow_pipeline.ingest.round_geometry import RoundaboutGeometry

GEOMETRY = RoundaboutGeometry(centre_x=CENTRE[0], centre_y=CENTRE[1], inner_radius=10.5, outer_radius=13.5)
KEY = ["target_id", "ego_id", "conflict_frame"]


def _approach(speed: float, start_arc: float, frames: int = 30, radius: float = 12.0, length: float = 4.0,
              start_frame: int = 0, decision_frame: int = 30) -> pl.DataFrame:
    """An ego circulating at a constant `speed` on `radius`, `start_arc` metres (arc) upstream of the target's
    arm at frame 0."""
    frame = np.arange(frames)
    arc = start_arc - speed * DT * frame
    return pl.DataFrame({"target_id": 1, "ego_id": 2, "conflict_frame": 99, "frame": frame,
                         "start_frame": start_frame, "decision_frame": decision_frame, "psi": -arc / radius,
                         "r_e": radius, "v_e": speed, "length_e": length})


def _critical(rows: pl.DataFrame) -> int | None:
    found = critical_frames(rows, KEY, GEOMETRY)
    return found.get_column("critical_frame").item() if found.height else None


def test_critical_frame_is_where_the_distance_falls_below_the_braking_distance() -> None:
    # 10 m/s and 4 m/s^2: braking distance 12.5 m; front distance 40 - 2 f - 2 m < 12.5 m first at f = 13
    assert CRITICAL_DECELERATION == 4.0
    assert _critical(_approach(10.0, 40.0)) == 13
    # a gap that opens already critical has t_crit = t_S; one decided before it has none
    assert _critical(_approach(10.0, 40.0, start_frame=20)) == 20
    assert _critical(_approach(10.0, 40.0, decision_frame=13)) is None
    # a slower ego brakes in less distance (5 m/s: 3.125 m; 1 m per frame: 40 - f - 2 < 3.125 first at f = 35)
    assert _critical(_approach(5.0, 40.0, frames=40, decision_frame=40)) == 35
    # standing or reversing egos can always stop -- until their front is in the conflict zone
    assert _critical(_approach(0.0, 10.0)) is None
    assert _critical(_approach(-3.0, 10.0)) is None
    assert _critical(_approach(0.0, 1.0)) == 0
    # past the conflict zone (psi >= conflict_angle) the ego is no longer critical
    beyond = _approach(0.0, -GEOMETRY.conflict_angle * 12.0 - 1.0)
    assert _critical(beyond) is None


def _late(track: Track, first_frame: int) -> Track:
    """The track as recorded from the 5 Hz frame `first_frame` on (as if the recording started then)."""
    skip = first_frame * 5 - track.initial_frame
    return replace(track, initial_frame=first_frame * 5, positions=track.positions[skip:],
                   velocities=track.velocities[skip:], heading=track.heading[skip:])


def _expected_critical_frame(ego: Track) -> int:
    """From the synthetic ego's own positions and velocities: the first 5 Hz frame at which its front's arc
    distance to the target's arm (the arm of 180 degrees, approached along its axis) is below v^2 / (2 a)."""
    frames = ego.initial_frame + np.arange(len(ego.positions))
    keep = frames % 5 == 0
    position, velocity, frame = ego.positions[keep], ego.velocities[keep], frames[keep] // 5
    dx, dy = position[:, 0] - CENTRE[0], position[:, 1] - CENTRE[1]
    theta, r = np.arctan2(dy, dx), np.hypot(dx, dy)
    psi = (theta - math.pi + math.pi) % (2 * math.pi) - math.pi
    speed = velocity[:, 1] * np.cos(theta) - velocity[:, 0] * np.sin(theta)
    distance = r * -psi - SIZES["van"][1] / 2
    critical = (r <= GEOMETRY.outer_radius) & (psi < 0) & (distance < np.clip(speed, 0, None) ** 2
                                                             / (2 * CRITICAL_DECELERATION))
    return int(frame[critical][0])


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> pl.DataFrame:
    """Samples of the scripted recording as it is."""
    raw = write_recording(tmp_path_factory.mktemp("critical_raw"), 0, gap_scenario())
    return open_dataset(ingest_round(raw, tmp_path_factory.mktemp("critical") / "ref", geometry=GEOMETRY,
                                     quiet=True)).samples()


def test_critical_frame_of_the_synthetic_ego(reference: pl.DataFrame) -> None:
    ego = next(track for track in gap_scenario() if track.track_id == EGO_REJECT)
    rejected = reference.filter(pl.col("gap") == "rejected")
    assert rejected.height == 2 and rejected.get_column("critical_frame").n_unique() == 1
    row = rejected.row(0, named=True)
    assert row["critical_frame"] == _expected_critical_frame(ego)
    assert row["t0_frame"] < row["critical_frame"] < row["decision_frame"]
    # the accepting target enters before the ego is too close to stop: no critical time, the sample stays
    assert reference.filter(pl.col("gap") == "accepted").get_column("critical_frame").is_null().all()


def test_samples_at_or_after_the_critical_frame_are_dropped(reference: pl.DataFrame, tmp_path: Path) -> None:
    """The rejecting ego recorded only from 14 frames before t_crit (t0 = t_crit: dropped) or 15 frames
    before it (t0 = t_crit - 1: kept); t0 is then the first frame with a full past of the ego."""
    critical = reference.filter(pl.col("gap") == "rejected").get_column("critical_frame")[0]
    for number, first in ((0, critical - (N_PAST - 1)), (1, critical - N_PAST)):
        tracks = [_late(t, first) if t.track_id == EGO_REJECT else t for t in gap_scenario()]
        write_recording(tmp_path / "raw", number, tracks)
    out = ingest_round(tmp_path / "raw", tmp_path / "out", geometry=GEOMETRY, quiet=True)
    samples = open_dataset(out).samples().filter(pl.col("gap") == "rejected")
    assert samples.get_column("scene_id").unique().to_list() == ["rec01"]
    kept = samples.filter(pl.col("agent_id") == TARGET_REJECT).row(0, named=True)
    assert (kept["t0_frame"], kept["critical_frame"]) == (critical - 1, critical)
    lineage = json.loads((out / "dataset.json").read_text())["lineage"]
    assert [r["excluded_after_critical"] for r in lineage["recordings"]] == [1, 0]
    assert lineage["excluded_after_critical"] == 1 and lineage["critical_deceleration"] == CRITICAL_DECELERATION
    # the accepted gaps of both recordings are unaffected
    assert open_dataset(out).samples().filter(pl.col("gap") == "accepted").height == 4
