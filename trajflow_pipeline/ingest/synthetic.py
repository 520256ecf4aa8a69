"""`trajflow ingest synthetic-bimodal`: the paper's synthetic bimodal dataset (section V-A), generated.

One observed past of 10 steps and two future modes of 14 steps at dt 0.25 s; each future is scaled about the
last observed position by s ~ N(1, 0.15), half of the samples per mode. Every sample has the same past, so
all samples form one group (identical inputs) and the true future distribution is known to be bimodal.
The two base pedestrian trajectories are generated procedurally: a smooth walk that veers left in one mode and
right, a little slower, in the other. Same seed, byte-identical output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from ..errors import UsageError
from ..schemas import PROTOCOL_TRAIN_IS_TEST, DatasetMeta, DatasetWriter
from ..util.bounds import check_seed
from .base import Ingest
from .windows import identical_input_groups

DATASET = "synthetic_bimodal"
DT = 0.25
N_PAST, N_FUTURE = 10, 14
SCALE_STD = 0.15
VAL_FRACTION = 0.1


def _walk(speed: np.ndarray, heading: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Positions of a walker starting at `start`, integrating per-step speed (m/s) and heading (rad)."""
    steps = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * (speed * DT)[:, None]
    return start + np.cumsum(steps, axis=0)


def base_trajectories() -> tuple[np.ndarray, np.ndarray]:
    """The shared past (N_PAST, 2) and the two future modes (2, N_FUTURE, 2), ending the past at the origin.

    The past is a walk at 1.3 m/s with a slight drift; the futures turn smoothly (a smoothstep heading profile)
    by +45 degrees at 1.3 m/s and by -35 degrees while slowing to 1.1 m/s.
    """
    past_heading = np.linspace(-0.08, 0.0, N_PAST)
    past = _walk(np.full(N_PAST, 1.3), past_heading, np.zeros(2))
    past = past - past[-1]
    progress = np.arange(1, N_FUTURE + 1) / N_FUTURE
    smooth = progress * progress * (3 - 2 * progress)
    left = _walk(np.full(N_FUTURE, 1.3), np.deg2rad(45.0) * smooth, past[-1])
    right = _walk(1.3 - 0.2 * smooth, np.deg2rad(-35.0) * smooth, past[-1])
    return past, np.stack([left, right])


def generate(samples: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Futures (samples, N_FUTURE, 2), their mode (samples,) and scale factor (samples,), seeded."""
    past, modes = base_trajectories()
    rng = np.random.default_rng(seed)
    mode = np.arange(samples) % 2
    scale = rng.normal(1.0, SCALE_STD, size=samples)
    futures = past[-1] + scale[:, None, None] * (modes[mode] - past[-1])
    return futures, mode, scale


def ingest_synthetic_bimodal(out: str | Path, *, samples: int = 3000, seed: int = 0, overwrite: bool = False,
                             quiet: bool = False) -> Path:
    """Generate the synthetic bimodal dataset into `out`; returns `out`."""
    if samples < 2:
        raise UsageError(f"--samples must be at least 2 (one per mode), got {samples}")
    check_seed(seed, "--seed")
    out = Path(out)
    past, _ = base_trajectories()
    futures, mode, scale = generate(samples, seed)
    positions = np.concatenate([np.broadcast_to(past, (samples, N_PAST, 2)), futures], axis=1)
    n_steps = N_PAST + N_FUTURE
    scene_ids = [f"bimodal-{i:05d}" for i in range(samples)]
    frame = np.tile(np.arange(n_steps, dtype=np.int64), samples)
    tracks = pl.DataFrame({
        "scene_id": np.repeat(scene_ids, n_steps),
        "agent_id": np.zeros(samples * n_steps, dtype=np.int64),
        "agent_type": "pedestrian",
        "frame": frame,
        "t": frame * DT,
        "x": positions[..., 0].ravel(),
        "y": positions[..., 1].ravel(),
    })
    val = np.zeros(samples, dtype=bool)
    val[np.random.default_rng(seed + 1).permutation(samples)[: max(1, round(VAL_FRACTION * samples))]] = True
    table = pl.DataFrame({
        "sample_id": np.arange(samples, dtype=np.int64), "scene_id": scene_ids,
        "agent_id": np.zeros(samples, dtype=np.int64), "t0_frame": np.full(samples, N_PAST - 1, dtype=np.int64),
        "n_past": np.full(samples, N_PAST, dtype=np.int64), "n_future": np.full(samples, N_FUTURE, dtype=np.int64),
        "split": np.where(val, "val", "train"), "fold": pl.Series([None] * samples, dtype=pl.String),
        "joint_id": np.arange(samples, dtype=np.int64), "mode": mode.astype(np.int64), "scale": scale,
    })
    table = table.with_columns(group_id=identical_input_groups(table, tracks))
    scenes = pl.DataFrame({"dataset": DATASET, "scene_id": scene_ids, "location": "synthetic", "dt": DT,
                           "source": f"generated (seed {seed})",
                           "fold": pl.Series([None] * samples, dtype=pl.String)})
    meta = DatasetMeta(dataset=DATASET, dt=DT, protocol=PROTOCOL_TRAIN_IS_TEST)
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        writer.add_tracks(tracks)
        writer.finish(scenes, table, lineage={"generator": "synthetic-bimodal", "seed": seed, "samples": samples,
                                              "scale_std": SCALE_STD, "val_fraction": VAL_FRACTION})
    return out


ADAPTER = Ingest(name="synthetic-bimodal", dataset=DATASET, dt=DT, folds=None, raw=None,
                 function=ingest_synthetic_bimodal, multi_future=True)
