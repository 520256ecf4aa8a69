"""Throughput and memory of `ingest round` on synthetic levelX recordings about the size of real ones.

Generates `--recordings` recordings of random roundabout traffic (vehicles entering on random arms, some yielding,
pedestrians, bicycles; ~1 million raw 25 Hz track rows each by default) with the test suite's levelX writer, then
ingests (a) the first recording alone and (b) all of them, each in a fresh process, and prints the raw rows read
per second and the peak resident memory (getrusage ru_maxrss, which sees polars' and Arrow's native allocations
that tracemalloc does not). Streaming shows as (b) needing about the memory of (a), not `--recordings` times it.

    python bench/round.py [--recordings 4] [--vehicles 2400] [--pedestrians 600] [--minutes 40] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ingest"))
from levelx_measure import print_generated, print_results, run_ingest  # noqa: E402
from test_round_synth import (ARMS_DEG, Track, crossing_path, drive, vehicle_path,  # noqa: E402
                              write_recording)

CLASSES = ("car", "van", "truck", "bus", "motorcycle", "bicycle")
CLASS_SHARE = (0.80, 0.08, 0.04, 0.02, 0.02, 0.04)


def random_traffic(seed: int, vehicles: int, pedestrians: int, minutes: float) -> list[Track]:
    """Vehicles entering on random arms at random times (30 % yield for 0-4 s at the line) and pedestrians."""
    rng = np.random.default_rng(seed)
    duration = minutes * 60
    tracks: list[Track] = []
    classes = rng.choice(CLASSES, size=vehicles, p=CLASS_SHARE)
    for track_id, cls in enumerate(classes, start=1):
        arm_in, arm_out = rng.integers(len(ARMS_DEG), size=2)
        start = float(rng.uniform(0, duration))
        speed = float(rng.uniform(4.0, 5.0) if cls == "bicycle" else rng.uniform(6.0, 10.0))
        path = vehicle_path(int(arm_in), int(arm_out))
        if rng.random() < 0.3:
            tracks.append(drive(track_id, str(cls), path, start, speed, stop_at_distance=18.2,
                                go_at=start + 40.0 / speed + float(rng.uniform(0, 4))))
        else:
            tracks.append(drive(track_id, str(cls), path, start, speed))
    for track_id in range(vehicles + 1, vehicles + pedestrians + 1):
        path = crossing_path(int(rng.integers(len(ARMS_DEG))), float(rng.uniform(22, 40)))
        tracks.append(drive(track_id, "pedestrian", path if rng.random() < 0.5 else path[::-1],
                            float(rng.uniform(0, duration)), float(rng.uniform(1.1, 1.7))))
    return tracks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--vehicles", type=int, default=2400)
    parser.add_argument("--pedestrians", type=int, default=600)
    parser.add_argument("--minutes", type=float, default=40.0)
    parser.add_argument("--keep", type=Path, default=None, help="write the raw recordings here and keep them")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="round-bench-"))
    raw = args.keep or workdir / "raw"
    try:
        start = time.perf_counter()
        rows = []
        for number in range(args.recordings):
            tracks = random_traffic(number, args.vehicles, args.pedestrians, args.minutes)
            write_recording(raw, number, tracks, location_id=number % 3)
            rows.append(sum(len(track.positions) for track in tracks))
        print_generated(rows, raw, time.perf_counter() - start)
        options = {}
        one = run_ingest("round", raw, workdir / "one", ["0"], options)
        every = run_ingest("round", raw, workdir / "all", [], options)
        print_results(rows, one, every)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
