"""Times `trajflow ingest eth-ucy` on the shared copy against straightforward pandas references.

Two references, both reading the eight full sequences with pandas and finding the strict 8 + 12 windows agent by
agent (a Python loop over pedestrians, as such scripts usually do):

* "windows only": parse, windows, tracks + samples Parquet -- less than `ingest eth-ucy` does;
* "same tables": the whole job of `ingest eth-ucy` done the straightforward way -- input checks (non-finite
  values, whole frames and ids, duplicated rows), windows, train/val/fold labels, joint ids, identical-input
  groups (a dict keyed by each sample's rounded past window and those of everyone present at t0) and the
  scenes / tracks / samples Parquet files; its sample and group counts are checked against ours.

All run in this process, alternately, several times; the ratios of the medians are the figures to report (this
machine is shared and noisy).

    python bench/ingest.py [--data ../shared/data/eth_ucy] [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from trajflow_pipeline.ingest.eth_ucy import (FOLDS, SEQUENCES, STANDARD_VAL_START_RAW_FRAME,
                                              ingest_eth_ucy)
from trajflow_pipeline.schemas import open_dataset

N_PAST, N_FUTURE, STEP = 8, 12, 10
TOLERANCE = 1e-3


def _read_and_find_windows(all_data: Path, checked: bool) -> tuple[pd.DataFrame, list[tuple[str, int, int]]]:
    """Both references' common part: each sequence parsed with pandas (its input checked when `checked`), tracks
    columns added, and the strict windows found with a Python loop per pedestrian. Returns the tracks table and
    (scene, pedestrian, t0 frame) per window."""
    tracks, windows = [], []
    for name in SEQUENCES:
        path = all_data / f"{name}.txt"
        frame = pd.read_csv(path, sep=r"\s+", header=None, names=["frame", "ped", "x", "y"])
        if checked:
            _check_input(frame, path)
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
                    windows.append((name, ped, f))
    return pd.concat(tracks)[["scene_id", "agent_id", "agent_type", "frame", "t", "x", "y"]], windows


def _check_input(frame: pd.DataFrame, path: Path) -> None:
    """The ingest's input checks: finite numbers, whole frames and ids on the frame step, no duplicated rows."""
    if not np.isfinite(frame[["frame", "ped", "x", "y"]].to_numpy(dtype=float)).all():
        raise ValueError(f"{path}: non-finite values")
    if (frame["frame"] % 1 != 0).any() or (frame["ped"] % 1 != 0).any() or (frame["frame"] % STEP != 0).any():
        raise ValueError(f"{path}: fractional frame / id or frame off the step")
    if frame.duplicated(["frame", "ped"]).any():
        raise ValueError(f"{path}: duplicated rows")


def pandas_reference(all_data: Path, out: Path) -> int:
    """Windows only: pandas parsing, a Python loop per pedestrian for the windows, and the tracks and samples
    tables written to Parquet. Returns the number of samples."""
    table, windows = _read_and_find_windows(all_data, checked=False)
    samples = pd.DataFrame(windows, columns=["scene_id", "agent_id", "t0_frame"]).assign(n_past=N_PAST,
                                                                                        n_future=N_FUTURE)
    out.mkdir(parents=True)
    table.to_parquet(out / "tracks.parquet")
    samples.to_parquet(out / "samples.parquet")
    return len(samples)


def pandas_reference_same_tables(all_data: Path, out: Path) -> tuple[int, int]:
    """The tables `ingest eth-ucy` writes, made the straightforward way. Returns (samples, groups)."""
    table, samples = _read_and_find_windows(all_data, checked=True)
    table = table.sort_values(["scene_id", "agent_id", "frame"])
    scenes = pd.DataFrame({"scene_id": list(SEQUENCES), "location": list(SEQUENCES.values())})
    scenes["fold"] = scenes["location"].where(scenes["location"].isin(FOLDS))
    scenes["val_start_frame"] = [STANDARD_VAL_START_RAW_FRAME[name] // STEP for name in SEQUENCES]
    frame = pd.DataFrame(samples, columns=["scene_id", "agent_id", "t0_frame"]).merge(scenes, on="scene_id")
    frame = frame.sort_values(["scene_id", "t0_frame", "agent_id"]).reset_index(drop=True)
    frame["split"] = np.where(frame["t0_frame"] + N_FUTURE < frame["val_start_frame"], "train",
                              np.where(frame["t0_frame"] - (N_PAST - 1) >= frame["val_start_frame"], "val", None))
    frame["joint_id"] = frame.groupby(["scene_id", "t0_frame"], sort=True).ngroup()
    positions: dict[tuple[str, int], dict[int, tuple[int, int]]] = {}
    present_at: dict[tuple[str, int], list[int]] = {}
    for scene, ped, f, x, y in table[["scene_id", "agent_id", "frame", "x", "y"]].itertuples(index=False):
        positions.setdefault((scene, ped), {})[f] = (round(x / TOLERANCE), round(y / TOLERANCE))
        present_at.setdefault((scene, f), []).append(ped)

    def window(scene: str, ped: int, t0: int) -> tuple:
        track = positions[(scene, ped)]
        return tuple((f - t0, *track[f]) for f in range(t0 - N_PAST + 1, t0 + 1) if f in track)

    contexts: dict[tuple[str, int], tuple] = {}  # everyone's windows at (scene, t0), built once per frame
    groups: dict[tuple, int] = {}
    group_ids = []
    for scene, ped, t0 in frame[["scene_id", "agent_id", "t0_frame"]].itertuples(index=False):
        if (scene, t0) not in contexts:
            contexts[(scene, t0)] = tuple(sorted(window(scene, p, t0) for p in present_at[(scene, t0)]))
        key = (window(scene, ped, t0), contexts[(scene, t0)])
        group_ids.append(groups.setdefault(key, len(groups)))
    frame["group_id"] = group_ids
    out.mkdir(parents=True)
    table.to_parquet(out / "tracks.parquet")
    scenes.to_parquet(out / "scenes.parquet")
    frame.to_parquet(out / "samples.parquet")
    return len(frame), len(groups)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[2] / "shared" / "data" / "eth_ucy"
    parser.add_argument("--data", type=Path, default=default)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    ours, reference, full = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            start = time.perf_counter()
            ingest_eth_ucy(args.data, Path(tmp) / f"run{i}", quiet=True)
            ours.append(time.perf_counter() - start)
            start = time.perf_counter()
            count = pandas_reference(args.data / "all_data", Path(tmp) / f"reference{i}")
            reference.append(time.perf_counter() - start)
            start = time.perf_counter()
            full_counts = pandas_reference_same_tables(args.data / "all_data", Path(tmp) / f"full{i}")
            full.append(time.perf_counter() - start)
        samples = open_dataset(Path(tmp) / "run0").samples()
        our_counts = (samples.height, samples.get_column("group_id").n_unique())
    ours_s, reference_s, full_s = (statistics.median(times) for times in (ours, reference, full))
    print(f"trajflow ingest eth-ucy (full: parse, validate, samples, groups, Parquet): median {ours_s:.3f} s "
          f"over {args.repeat} runs (min {min(ours):.3f} s)")
    print(f"pandas reference, windows only (parse, windows, tracks + samples Parquet; {count} samples): "
          f"median {reference_s:.3f} s (min {min(reference):.3f} s) -> speed-up {reference_s / ours_s:.1f}x")
    print(f"pandas reference, same tables (checks, windows, labels, groups, 3 Parquet files; "
          f"{full_counts[0]} samples, {full_counts[1]} groups): median {full_s:.3f} s (min {min(full):.3f} s) "
          f"-> speed-up {full_s / ours_s:.1f}x")
    print(f"same counts as trajflow ({our_counts[0]} samples, {our_counts[1]} groups): {full_counts == our_counts}")
    print("targets: < 2 s, >= 5x")


if __name__ == "__main__":
    main()
