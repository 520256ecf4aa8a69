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
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ingest"))
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


def child(raw: str, out: str, problems: str, recordings: list[str]) -> None:
    """Run one ingest in this process and print its wall time, peak RSS and counts as JSON."""
    from trajflow_pipeline.ingest.highd import ingest_highd
    from trajflow_pipeline.schemas import open_dataset

    start = time.perf_counter()
    ingest_highd(raw, out, recordings=recordings or None, problems=problems, overwrite=True, quiet=True)
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ds = open_dataset(out)
    print(json.dumps({"seconds": seconds, "peak_rss_mb": peak_mb, "samples": ds.counts["samples"],
                      "track_rows": ds.counts["tracks"]}))


def run_child(raw: Path, out: Path, problems: str, recordings: list[str]) -> dict:
    command = [sys.executable, __file__, "--child", str(raw), str(out), problems, *recordings]
    result = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--vehicles", type=int, default=3000)
    parser.add_argument("--problems", default="lane-change")
    parser.add_argument("--keep", type=Path, default=None, help="write the raw recordings here and keep them")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], args.child[1], args.child[2], args.child[3:])
        return
    workdir = Path(tempfile.mkdtemp(prefix="levelx-bench-"))
    raw = args.keep or workdir / "raw"
    try:
        start = time.perf_counter()
        rows = []
        for number in range(1, args.recordings + 1):
            vehicles = random_traffic(number, args.vehicles)
            write_highd_recording(raw, number, vehicles, location_id=number % 3 + 1)
            rows.append(sum(part.height for part in vehicles))
        size = sum(p.stat().st_size for p in raw.glob("*_tracks.csv")) / 2 ** 20
        print(f"generated {args.recordings} recordings, {sum(rows):,} raw rows ({', '.join(f'{r:,}' for r in rows)}),"
              f" {size:.0f} MiB of tracks CSV in {time.perf_counter() - start:.1f} s")
        one = run_child(raw, workdir / "one", args.problems, ["1"])
        every = run_child(raw, workdir / "all", args.problems, [])
        for label, result, raw_rows in (("1 recording ", one, rows[0]), (f"{args.recordings} recordings", every,
                                                                         sum(rows))):
            print(f"{label}: {raw_rows:,} raw rows -> {result['track_rows']:,} rows at 5 Hz, {result['samples']:,} "
                  f"samples in {result['seconds']:.1f} s = {raw_rows / result['seconds']:,.0f} raw rows/s; "
                  f"peak RSS {result['peak_rss_mb']:.0f} MiB")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
