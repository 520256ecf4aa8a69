"""Throughput and memory of `ingest levelx highd` on synthetic highD recordings about the size of real ones.

Generates `--recordings` recordings of random highway traffic (cars and trucks on three lanes per direction, some
changing lanes; ~1 million raw 25 Hz rows each by default) with the test suite's highD writer, then ingests (a)
the first recording alone and (b) all of them, each in a fresh process, and prints the raw rows read per second
and the peak resident memory (getrusage ru_maxrss). Streaming shows as (b) needing about the memory of (a), not
`--recordings` times it.

    python bench/levelx.py [--recordings 4] [--vehicles 3000] [--problems lane-change|all-agents] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ingest"))
from levelx_measure import print_generated, print_results, run_ingest  # noqa: E402
from levelx_fixture import FRAME_RATE, highway_vehicle, write_highd_recording  # noqa: E402

#: a vehicle enters every this many seconds per lane on average
SECONDS_PER_VEHICLE = 0.35


def random_traffic(seed: int, vehicles: int) -> list[pl.DataFrame]:
    """`vehicles` highD vehicles entering at random times on random lanes, a fifth of them changing lanes."""
    rng = np.random.default_rng(seed)
    result = []
    for track_id in range(1, vehicles + 1):
        upper = bool(rng.random() < 0.5)
        lane = int(rng.integers(2, 5) if upper else rng.integers(6, 9))
        speed = float(rng.uniform(22.0, 36.0)) * (-1 if upper else 1)
        cls = "Truck" if rng.random() < 0.15 else "Car"
        change = None
        if rng.random() < 0.2:
            change = lane + (1 if lane in (2, 3, 6, 7) else -1)
        part = highway_vehicle(track_id, cls, 395.0 if upper else 5.0, speed, lane, duration=20.0, change_to=change,
                               change_at=float(rng.uniform(3.0, 9.0)))
        start = int(track_id * SECONDS_PER_VEHICLE * FRAME_RATE)
        result.append(part.with_columns(pl.col("frame") + start))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--vehicles", type=int, default=3000)
    parser.add_argument("--problems", default="lane-change")
    parser.add_argument("--keep", type=Path, default=None, help="write the raw recordings here and keep them")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="levelx-bench-"))
    raw = args.keep or workdir / "raw"
    try:
        start = time.perf_counter()
        rows = []
        for number in range(1, args.recordings + 1):
            vehicles = random_traffic(number, args.vehicles)
            write_highd_recording(raw, number, vehicles, location_id=number % 3 + 1)
            rows.append(sum(part.height for part in vehicles))
        print_generated(rows, raw, time.perf_counter() - start)
        options = {"problems": args.problems}
        one = run_ingest("highd", raw, workdir / "one", ["1"], options)
        every = run_ingest("highd", raw, workdir / "all", [], options)
        print_results(rows, one, every)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
