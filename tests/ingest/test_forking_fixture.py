"""Small Forking Paths releases written in exactly the release's file-name and JSON format, for the tests.

`write_release` renders moments (one x-agent past, several annotated futures that turn in different directions
after a known fork frame) plus a context person and a vehicle whose track id equals the person's, as
``next_x_v1_dataset/bbox/<scene>_<moment>_<xagent>_<dest>_<annotator>_<cam>.json`` with boxes in pixels.
Ground truth is generated in metres and converted with the ingest's default cam4 scale, so tests can compare
ingested positions with `true_position`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from trajflow_pipeline.ingest.forking_paths import cam4_metres_per_pixel, default_fps

BOX_W, BOX_H = 20.0, 40.0
ORIGIN_PX = (900.0, 600.0)
SPEED = 1.3  # m/s, x-agent
PERSON_ID, VEHICLE_ID = 3, 3


@dataclass(frozen=True)
class Moment:
    """One observed past and its annotated futures: (dest, annotator, turn angle in degrees) each."""

    scene: str
    moment: int
    xagent: int
    futures: tuple[tuple[int, str, float], ...]
    fork: int  # last raw frame shared by all futures (ignored for a single future)
    extra_frames: int = 15


def default_moments() -> list[Moment]:
    """Two scenes (25 and 30 fps), six moments, one with a single future."""
    return [
        Moment("zara01", 1, 252, ((0, "27", -60.0), (1, "28", 0.0), (1, "29", 60.0)), fork=107),
        Moment("zara01", 2, 40, ((0, "27", -45.0), (2, "30", 45.0)), fork=112),
        Moment("zara01", 3, 41, ((0, "27", 30.0),), fork=0),
        Moment("0400", 1, 7, ((0, "27", -50.0), (1, "28", 10.0), (2, "31", 70.0)), fork=130),
        Moment("0400", 5, 12, ((0, "27", -30.0), (1, "28", 40.0)), fork=126),
        Moment("0400", 6, 13, ((3, "29", 90.0), (0, "27", -90.0)), fork=140),
    ]


def fork_frame(moment: Moment) -> int:
    """The raw frame the ingest should find as the fork."""
    if len(moment.futures) > 1:
        return moment.fork
    return 102 if moment.scene.startswith(("zara", "eth", "hotel")) else 124


def true_position(moment: Moment, angle_deg: float, frame: int | float) -> tuple[float, float]:
    """x-agent ground position (metres, right-handed) at a raw frame: straight walk, then a turn at the fork."""
    fps = default_fps(moment.scene)
    fork = fork_frame(moment)
    x0, y0 = 2.0 + moment.moment, 1.0 + 0.1 * moment.xagent % 3
    if frame <= fork:
        return x0 + SPEED * frame / fps, y0 + 0.2 * frame / fps
    fx, fy = true_position(moment, angle_deg, fork)
    heading = math.atan2(0.2, SPEED) + math.radians(angle_deg)
    dt = (frame - fork) / fps
    return fx + SPEED * dt * math.cos(heading), fy + SPEED * dt * math.sin(heading)


def _box(x_m: float, y_m: float, scale: float) -> list[float]:
    u, v = ORIGIN_PX[0] + x_m / scale, ORIGIN_PX[1] - y_m / scale
    return [u - BOX_W / 2, v - BOX_H, BOX_W, BOX_H]


def records(moment: Moment, angle_deg: float) -> list[dict]:
    """The JSON records of one annotated future: x-agent, a context person and a vehicle, frame by frame."""
    fps = default_fps(moment.scene)
    scale = cam4_metres_per_pixel(moment.scene)
    n_frames = fork_frame(moment) + int(round(12 * 0.4 * fps)) + moment.extra_frames
    out: list[dict] = []
    for frame in range(n_frames):
        x, y = true_position(moment, angle_deg, frame)
        out.append({"class_name": "Person", "is_x_agent": 1, "bbox": _box(x, y, scale), "frame_id": frame,
                    "track_id": float(moment.xagent)})
        out.append({"class_name": "Person", "is_x_agent": 0, "bbox": _box(1.0 + 0.5 * frame / fps, 6.0, scale),
                    "frame_id": frame, "track_id": float(PERSON_ID)})
        if frame >= 20:
            out.append({"class_name": "Vehicle", "is_x_agent": 0,
                        "bbox": _box(15.0 - 4.0 * frame / fps, -3.0, scale), "frame_id": frame,
                        "track_id": float(VEHICLE_ID)})
    return out


@dataclass
class Release:
    """Where a generated release lies and what it holds."""

    root: Path
    moments: list[Moment] = field(default_factory=list)

    @property
    def bbox(self) -> Path:
        return self.root / "next_x_v1_dataset" / "bbox"

    def file(self, moment: Moment, dest: int, annotator: str, camera: str = "cam4") -> Path:
        return self.bbox / f"{moment.scene}_{moment.moment}_{moment.xagent}_{dest}_{annotator}_{camera}.json"


def write_release(root: Path, moments: list[Moment] | None = None, other_camera: bool = True) -> Release:
    """Write the moments as a release under `root` (plus, by default, one cam1 file that must be ignored)."""
    release = Release(root, moments if moments is not None else default_moments())
    release.bbox.mkdir(parents=True, exist_ok=True)
    for moment in release.moments:
        for dest, annotator, angle in moment.futures:
            release.file(moment, dest, annotator).write_text(json.dumps(records(moment, angle)))
    if other_camera:
        first = release.moments[0]
        dest, annotator, angle = first.futures[0]
        shifted = [{**r, "bbox": [r["bbox"][0] * 0.5, r["bbox"][1] * 0.3, 50.0, 80.0]} for r in records(first, angle)]
        release.file(first, dest, annotator, "cam1").write_text(json.dumps(shifted))
    return release
