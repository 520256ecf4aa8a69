"""Times `trajflow augment forking` against a naive per-trajectory Python loop doing the same job.

A Forking-Paths-like dataset is generated: `--futures` annotated futures (groups of 4 sharing a past), each its
own scene with the target and 3 context agents over the 8 + 12 step window. Both implementations make
`--copies` versions of every future (the original plus copies - 1 variants whose post-fork part is scaled and
rotated about the fork point), from the very same draws, and write the result as a dataset with DatasetWriter;
the reference loops over every (future, copy) trajectory with small numpy arrays, as such scripts usually do.
One timed run each after a small untimed warm-up (the machine is shared and noisy); the script checks that
both wrote the same rows (positions equal up to floating-point rounding) and prints the times, the throughput
in trajectories per second and the ratio.

    python bench/augment.py [--futures 1000] [--copies 100] [--skip-reference]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

from trajflow_pipeline.schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter, open_dataset
from trajflow_pipeline.stages.augment import (CX, CY, FORKING, SAMPLE, augment_forking, draw_forking, output_samples,
                                              output_scenes, sample_windows, variant_plan)

N_PAST, N_FUTURE, CONTEXT, PER_GROUP = 8, 12, 3, 4
SCALE_STD, ROT_STD_DEG, SEED = 0.03, 1.0, 0


def generate(out: Path, futures: int, seed: int = 1) -> Path:
    """A folds-protocol dataset of `futures` single-window scenes, PER_GROUP futures sharing each past."""
    rng = np.random.default_rng(seed)
    groups = math.ceil(futures / PER_GROUP)
    steps = N_PAST + N_FUTURE
    frame = np.arange(steps)
    past_dir = rng.uniform(-math.pi, math.pi, groups)
    rows = []
    for agent in range(1 + CONTEXT):
        start = rng.normal(0.0, 5.0, size=(groups, 2)) if agent else np.zeros((groups, 2))
        heading = np.repeat(past_dir[:, None], steps, axis=1) + (0 if agent == 0 else rng.normal(0, 1, (groups, 1)))
        heading = np.repeat(heading, PER_GROUP, axis=0)[:futures]
        if agent == 0:  # the target turns after the fork, differently in each future of a group
            turn = rng.normal(0.0, 0.6, size=(futures, 1)) * (frame[None, :] >= N_PAST)
            heading = heading + turn
        steps_xy = 0.5 * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        steps_xy[:, 0] = 0.0
        xy = np.repeat(start, PER_GROUP, axis=0)[:futures, None, :] + np.cumsum(steps_xy, axis=1)
        rows.append(pl.DataFrame({
            "scene_id": np.repeat([f"s{i:06d}" for i in range(futures)], steps),
            "agent_id": np.full(futures * steps, agent, dtype=np.int64),
            "agent_type": "pedestrian", "frame": np.tile(frame, futures).astype(np.int64),
            "t": np.tile(frame * 0.4, futures), "x": xy[..., 0].ravel(), "y": xy[..., 1].ravel()}))
    tracks = pl.concat(rows).sort("scene_id", "agent_id", "frame")
    scene_ids = [f"s{i:06d}" for i in range(futures)]
    group = np.arange(futures) // PER_GROUP
    samples = pl.DataFrame({"sample_id": np.arange(futures, dtype=np.int64), "scene_id": scene_ids,
                            "agent_id": np.zeros(futures, dtype=np.int64),
                            "t0_frame": np.full(futures, N_PAST - 1, dtype=np.int64),
                            "n_past": np.full(futures, N_PAST, dtype=np.int64),
                            "n_future": np.full(futures, N_FUTURE, dtype=np.int64), "group_id": group.astype(np.int64),
                            "split": "train", "fold": [str(g % 5) for g in group]})
    scenes = pl.DataFrame({"dataset": "bench", "scene_id": scene_ids, "location": "bench", "dt": 0.4,
                           "source": "generated", "fold": [str(g % 5) for g in group]})
    with DatasetWriter(out, DatasetMeta(dataset="bench", dt=0.4, protocol=PROTOCOL_FOLDS)) as writer:
        writer.add_tracks(tracks)
        writer.finish(scenes, samples)
    return out


def naive_reference(data: Path, out: Path, copies: int) -> None:
    """The same augmentation with a Python loop over every (future, copy) trajectory and small numpy arrays."""
    ds = open_dataset(data)
    samples, scenes, tracks = ds.samples(), ds.scenes(), ds.tracks()
    draws = draw_forking(samples.height, copies, SCALE_STD, ROT_STD_DEG, None, None, SEED)
    by_scene = {scene: part for (scene,), part in tracks.group_by("scene_id", maintain_order=True)}
    names, agents, frames, xs, ys = [], [], [], [], []
    width = max(3, len(str(copies - 1)))
    for i, sample in enumerate(samples.iter_rows(named=True)):
        scene = by_scene[sample["scene_id"]]
        t0 = sample["t0_frame"]
        window = scene.filter(pl.col("frame").is_between(t0 - sample["n_past"] + 1, t0 + sample["n_future"]))
        agent, frame = window.get_column("agent_id").to_numpy(), window.get_column("frame").to_numpy()
        xy = window.select("x", "y").to_numpy()
        moving = (agent == sample["agent_id"]) & (frame > t0)
        centre = xy[(agent == sample["agent_id"]) & (frame == t0)][0]
        for k in range(1, copies):
            s, theta = draws.scale[i, k - 1], draws.angle[i, k - 1]
            rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
            moved = xy.copy()
            moved[moving] = centre + s * (xy[moving] - centre) @ rot.T
            names.append(np.full(len(agent), f"{sample['scene_id']}~s{sample['sample_id']}~fork{k:0{width}d}"))
            agents.append(agent)
            frames.append(frame)
            xs.append(moved[:, 0])
            ys.append(moved[:, 1])
    variants = pl.DataFrame({"scene_id": np.concatenate(names), "agent_id": np.concatenate(agents),
                             "frame": np.concatenate(frames), "x": np.concatenate(xs), "y": np.concatenate(ys)})
    variants = variants.join(tracks.select("scene_id", "agent_id", "frame", "agent_type", "t")
                             .rename({"scene_id": "__src"}),
                             left_on=[pl.col("scene_id").str.split("~").list.first(), "agent_id", "frame"],
                             right_on=["__src", "agent_id", "frame"], how="left")
    all_tracks = pl.concat([tracks, variants.select(tracks.columns)]).sort("scene_id", "agent_id", "frame")
    plan = variant_plan(samples.sort("sample_id"), draws, FORKING, copies)
    centres = sample_windows(samples, tracks, ds.path).select(SAMPLE, CX, CY).unique(SAMPLE)
    meta = DatasetMeta(dataset=f"{ds.meta.dataset}_forking_aug", dt=ds.meta.dt, protocol=ds.meta.protocol)
    with DatasetWriter(out, meta) as writer:
        for start in range(0, all_tracks.height, 1_000_000):  # whole scenes per shard are not needed for timing
            writer.add_tracks(all_tracks.slice(start, 1_000_000))
        writer.finish(output_scenes(scenes, plan, centres, FORKING, meta.dataset),
                      output_samples(samples, plan, FORKING))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--futures", type=int, default=1000)
    parser.add_argument("--copies", type=int, default=100)
    parser.add_argument("--skip-reference", action="store_true", help="time only trajflow (for large sizes)")
    args = parser.parse_args()
    trajectories = args.futures * args.copies
    with tempfile.TemporaryDirectory() as tmp:
        warm = generate(Path(tmp) / "warm", 8)  # first calls pay for thread pools and lazy imports: not timed
        augment_forking(warm, Path(tmp) / "warm_ours", copies=3, quiet=True)
        naive_reference(warm, Path(tmp) / "warm_reference", 3)
        data = generate(Path(tmp) / "data", args.futures)
        start = time.perf_counter()
        ours = augment_forking(data, Path(tmp) / "ours", copies=args.copies, scale_std=SCALE_STD,
                               rot_std_deg=ROT_STD_DEG, seed=SEED, quiet=True)
        ours_s = time.perf_counter() - start
        print(f"dataset: {args.futures} futures x {args.copies} copies = {trajectories} trajectories, "
              f"{open_dataset(ours).counts['tracks']} track rows written")
        print(f"trajflow augment forking : {ours_s:7.2f} s  ({trajectories / ours_s:,.0f} trajectories/s)")
        if args.skip_reference:
            return
        start = time.perf_counter()
        naive_reference(data, Path(tmp) / "reference", args.copies)
        ref_s = time.perf_counter() - start
        print(f"naive per-trajectory loop: {ref_s:7.2f} s  ({trajectories / ref_s:,.0f} trajectories/s)")
        a, b = open_dataset(ours).tracks(), open_dataset(Path(tmp) / "reference").tracks()
        assert a.drop("x", "y").equals(b.drop("x", "y"))
        gap = float(np.abs(a.select("x", "y").to_numpy() - b.select("x", "y").to_numpy()).max())
        print(f"speed-up: {ref_s / ours_s:.1f}x   (same rows; largest position difference {gap:.1e} m)")


if __name__ == "__main__":
    main()
