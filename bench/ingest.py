"""Times `trajflow ingest eth-ucy` on the shared copy against a straightforward pandas reference.

The reference reads the eight full sequences with pandas and finds the strict 8 + 12 windows agent by agent
(a Python loop over pedestrians, as such scripts usually do). Both run in this process, one after the other,
several times; the ratio of the medians is the figure to report (this machine is shared and noisy).

    python bench/ingest.py [--data ../shared/data/eth_ucy] [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import pandas as pd

from trajflow_pipeline.stages.ingest_eth_ucy import SEQUENCES, ingest_eth_ucy

N_PAST, N_FUTURE, STEP = 8, 12, 10


def pandas_reference(all_data: Path, out: Path) -> int:
    """The same job done the straightforward way: pandas parsing, a Python loop per pedestrian for the windows,
    and the tracks and samples tables written to Parquet. Returns the number of samples."""
    tracks, samples = [], []
    for name in SEQUENCES:
        frame = pd.read_csv(all_data / f"{name}.txt", sep=r"\s+", header=None, names=["frame", "ped", "x", "y"])
        frame["scene_id"] = name
        frame["agent_id"] = frame["ped"].astype("int64")
        frame["frame"] = (frame["frame"] // STEP).astype("int64")
        frame["t"] = frame["frame"] * 0.4
        frame["agent_type"] = "pedestrian"
        tracks.append(frame.sort_values(["agent_id", "frame"]))
        for ped, track in frame.groupby("agent_id"):
            present = set(track["frame"].tolist())
            for f in sorted(present):
                if all(f + k in present for k in range(-(N_PAST - 1), N_FUTURE + 1)):
                    samples.append({"scene_id": name, "agent_id": ped, "t0_frame": f, "n_past": N_PAST,
                                    "n_future": N_FUTURE})
    table = pd.concat(tracks)[["scene_id", "agent_id", "agent_type", "frame", "t", "x", "y"]]
    out.mkdir(parents=True)
    table.to_parquet(out / "tracks.parquet")
    pd.DataFrame(samples).to_parquet(out / "samples.parquet")
    return len(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[2] / "shared" / "data" / "eth_ucy"
    parser.add_argument("--data", type=Path, default=default)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    ours, reference = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            start = time.perf_counter()
            ingest_eth_ucy(args.data, Path(tmp) / f"run{i}", quiet=True)
            ours.append(time.perf_counter() - start)
            start = time.perf_counter()
            count = pandas_reference(args.data / "all_data", Path(tmp) / f"reference{i}")
            reference.append(time.perf_counter() - start)
    ours_s, reference_s = statistics.median(ours), statistics.median(reference)
    print(f"trajflow ingest eth-ucy (full: parse, validate, samples, groups, Parquet): median {ours_s:.3f} s "
          f"over {args.repeat} runs (min {min(ours):.3f} s)")
    print(f"pandas per-agent reference (parse, windows, tracks + samples Parquet; {count} samples): "
          f"median {reference_s:.3f} s (min {min(reference):.3f} s)")
    print(f"speed-up: {reference_s / ours_s:.1f}x  (targets: < 2 s, >= 5x)")


if __name__ == "__main__":
    main()
