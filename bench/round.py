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
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ingest"))
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


def child(raw: str, out: str, recordings: list[str]) -> None:
    """Run one ingest in this process and print its wall time, peak RSS and sample count as JSON."""
    from trajflow_pipeline.schemas import open_dataset
    from trajflow_pipeline.ingest.round import ingest_round

    start = time.perf_counter()
    ingest_round(raw, out, recordings=recordings or None, overwrite=True, quiet=True)
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ds = open_dataset(out)
    print(json.dumps({"seconds": seconds, "peak_rss_mb": peak_mb, "samples": ds.counts["samples"],
                      "track_rows": ds.counts["tracks"]}))


def run_child(raw: Path, out: Path, recordings: list[str]) -> dict:
    command = [sys.executable, __file__, "--child", str(raw), str(out), *recordings]
    result = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--vehicles", type=int, default=2400)
    parser.add_argument("--pedestrians", type=int, default=600)
    parser.add_argument("--minutes", type=float, default=40.0)
    parser.add_argument("--keep", type=Path, default=None, help="write the raw recordings here and keep them")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], args.child[1], args.child[2:])
        return
    workdir = Path(tempfile.mkdtemp(prefix="round-bench-"))
    raw = args.keep or workdir / "raw"
    try:
        start = time.perf_counter()
        rows = []
        for number in range(args.recordings):
            tracks = random_traffic(number, args.vehicles, args.pedestrians, args.minutes)
            write_recording(raw, number, tracks, location_id=number % 3)
            rows.append(sum(len(track.positions) for track in tracks))
        size = sum(p.stat().st_size for p in raw.glob("*_tracks.csv")) / 2 ** 20
        print(f"generated {args.recordings} recordings, {sum(rows):,} raw rows ({', '.join(f'{r:,}' for r in rows)}),"
              f" {size:.0f} MiB of tracks CSV in {time.perf_counter() - start:.1f} s")
        one = run_child(raw, workdir / "one", ["0"])
        every = run_child(raw, workdir / "all", [])
        for label, result, raw_rows in (("1 recording ", one, rows[0]), (f"{args.recordings} recordings", every,
                                                                         sum(rows))):
            print(f"{label}: {raw_rows:,} raw rows -> {result['track_rows']:,} rows at 5 Hz, {result['samples']:,} "
                  f"samples in {result['seconds']:.1f} s = {raw_rows / result['seconds']:,.0f} raw rows/s; "
                  f"peak RSS {result['peak_rss_mb']:.0f} MiB")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
