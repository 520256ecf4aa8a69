"""What the levelX ingest benches (round.py, levelx.py) share: one registered ingest timed in a fresh process (wall
time, peak resident memory by getrusage, counts), and the lines they print.

    python bench/levelx_measure.py INGEST RAW OUT OPTIONS_JSON [RECORDING ...]   # what run_ingest starts
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def run_ingest(ingest: str, raw: Path, out: Path, recordings: list[str], options: dict[str, Any]) -> dict[str, Any]:
    """Ingest `recordings` (all when empty) of `raw` into `out` in a child process; its figures."""
    command = [sys.executable, __file__, ingest, str(raw), str(out), json.dumps(options), *recordings]
    result = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def print_generated(rows: list[int], raw: Path, seconds: float) -> None:
    """The line about the generated recordings: raw rows per recording and the size of their tracks CSVs."""
    size = sum(p.stat().st_size for p in raw.glob("*_tracks.csv")) / 2 ** 20
    print(f"generated {len(rows)} recordings, {sum(rows):,} raw rows ({', '.join(f'{r:,}' for r in rows)}),"
          f" {size:.0f} MiB of tracks CSV in {seconds:.1f} s")


def print_results(rows: list[int], one: dict[str, Any], every: dict[str, Any]) -> None:
    """Raw rows per second and peak memory of the first recording alone and of all of them."""
    for label, result, raw_rows in (("1 recording ", one, rows[0]), (f"{len(rows)} recordings", every, sum(rows))):
        print(f"{label}: {raw_rows:,} raw rows -> {result['track_rows']:,} rows at 5 Hz, {result['samples']:,} "
              f"samples in {result['seconds']:.1f} s = {raw_rows / result['seconds']:,.0f} raw rows/s; "
              f"peak RSS {result['peak_rss_mb']:.0f} MiB")


def _child(ingest: str, raw: str, out: str, options: str, recordings: list[str]) -> None:
    """Run one ingest in this process and print its wall time, peak RSS and counts as JSON."""
    from trajflow_pipeline.ingest.registry import get_ingest
    from trajflow_pipeline.schemas import open_dataset

    start = time.perf_counter()
    get_ingest(ingest).run(raw, out, recordings=recordings or None, overwrite=True, quiet=True,
                           **json.loads(options))
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ds = open_dataset(out)
    print(json.dumps({"seconds": seconds, "peak_rss_mb": peak_mb, "samples": ds.counts["samples"],
                      "track_rows": ds.counts["tracks"]}))


if __name__ == "__main__":
    _child(*sys.argv[1:5], sys.argv[5:])
