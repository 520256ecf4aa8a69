"""From a dataset directory to model-ready tensors: protocol-aware split selection and batch assembly.

The dataset's protocol (manifest) says how train / val / test are chosen:

* ``folds``          — `--fold F` tests on samples whose `fold` is F; the remaining samples train or validate
                        according to their `split` column (samples with no split there are test-only);
* ``fixed``          — the `split` column is the split (nuScenes challenge);
* ``train-is-test``  — test on every sample; `split` separates train from the validation used for early stopping.

Horizons: every sample of a selection shares ``n_future``, the horizon models train on (``batch.future``). A
samples table may add ``n_future_max`` (rounD: up to 35 steps, the horizon the gap-acceptance decision needs);
``extended=True`` then also reads each sample's ground truth up to its own ``n_future_max`` into
``Problems.extended_future``, NaN-padded to the longest one, with ``Problems.horizon`` saying how many steps of
each are real. Positions are never invented: a sample whose target lacks a position inside its horizon is a
DataError. Map crops are uint8 (see :func:`maps.crops_for_problems`); the map CNN scales them by 1/255.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
import torch

from ..errors import DataError, UsageError
from ..model.batch import SceneBatch
from ..schemas import AGENT_TYPES, PROTOCOL_FIXED, PROTOCOL_FOLDS, PROTOCOL_TRAIN_IS_TEST, Dataset, open_dataset
from ..schemas.tables import SPLITS
from .maps import crops_for_problems, past_headings


@dataclass
class Problems:
    """The prediction problems of one split as tensors, with the identifiers needed to write results back."""

    batch: SceneBatch
    sample_id: np.ndarray
    scene_id: np.ndarray
    agent_id: np.ndarray
    t0_frame: np.ndarray
    group_id: np.ndarray
    joint_id: np.ndarray
    dt: float
    dataset: str
    n_past: int
    n_future: int
    has_map: bool
    fingerprint: dict[str, str]
    #: (B,) steps of ground truth per problem: n_future, or each sample's n_future_max when read `extended`
    horizon: np.ndarray | None = None
    #: (B, max(horizon), 2) float32 ground-truth future up to each problem's horizon, NaN after it (extended only)
    extended_future: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.sample_id)

    @property
    def horizons(self) -> np.ndarray:
        """(B,) ground-truth steps of each problem (n_future for all unless read with `extended`)."""
        return np.full(len(self), self.n_future, dtype=np.int64) if self.horizon is None else self.horizon


def list_folds(dataset: str | Path | Dataset) -> list[str]:
    """The folds a `--fold` option may name; empty when the dataset's protocol has none."""
    ds = dataset if isinstance(dataset, Dataset) else open_dataset(dataset)
    if ds.meta.protocol != PROTOCOL_FOLDS:
        return []
    return ds.samples().get_column("fold").drop_nulls().unique().sort().to_list()


def select_samples(ds: Dataset, fold: str | None, split: str) -> pl.DataFrame:
    """The rows of the samples table that form `split` under the dataset's protocol (and `fold`)."""
    if split not in SPLITS:
        raise UsageError(f"unknown split '{split}'; choose one of {', '.join(SPLITS)}")
    samples = ds.samples()
    if split == "test" and "train_only" in samples.columns:
        # augmented copies (`trajflow augment scale-rotate`) train; they are never test problems
        samples = samples.filter(~pl.col("train_only").fill_null(False))
    protocol = ds.meta.protocol
    if protocol == PROTOCOL_FOLDS:
        folds = list_folds(ds)
        if fold is None:
            raise UsageError(f"dataset '{ds.meta.dataset}' is evaluated by folds; choose --fold from "
                             f"{', '.join(folds)}")
        if fold not in folds:
            raise UsageError(f"fold '{fold}' does not exist in dataset '{ds.meta.dataset}'; choose from "
                             f"{', '.join(folds)}")
        if split == "test":
            return samples.filter(pl.col("fold") == fold)
        return samples.filter(pl.col("fold").ne_missing(fold) & (pl.col("split") == split))
    if fold is not None:
        raise UsageError(f"dataset '{ds.meta.dataset}' has no folds (protocol '{protocol}'); drop --fold")
    if protocol == PROTOCOL_TRAIN_IS_TEST and split == "test":
        return samples
    if protocol in (PROTOCOL_FIXED, PROTOCOL_TRAIN_IS_TEST):
        return samples.filter(pl.col("split") == split)
    raise DataError(f"unknown protocol '{protocol}'", path=ds.path)


def _uniform(samples: pl.DataFrame, column: str, path: Path) -> int:
    values = samples.get_column(column).unique()
    if values.len() != 1:
        raise DataError(f"samples of one split must share {column}; found {sorted(values.to_list())}", path=path)
    return int(values.item())


def _tracks_of(ds: Dataset, scene_ids: pl.Series) -> pl.DataFrame:
    """The validated tracks of the given scenes, reading shard by shard."""
    wanted = scene_ids.unique().implode()
    parts = [frame.filter(pl.col("scene_id").is_in(wanted)) for _, frame in ds.iter_track_shards()]
    return pl.concat(parts, how="diagonal_relaxed").select("scene_id", "agent_id", "agent_type", "frame", "x", "y")


def _type_index() -> pl.Expr:
    return pl.col("agent_type").replace_strict(list(AGENT_TYPES), list(range(len(AGENT_TYPES))),
                                               return_dtype=pl.Int64)


def _target_positions(samples: pl.DataFrame, tracks: pl.DataFrame, n_steps: int | str, n_past: int,
                      path: Path) -> np.ndarray:
    """(B, T, 2) positions of each sample's target from t0 - n_past + 1 on: `n_steps` of them (an int, or the
    name of a column of per-sample step counts, then T is their maximum and later steps are NaN)."""
    count = pl.lit(n_steps) if isinstance(n_steps, int) else pl.col(n_steps)
    steps = (samples.select("__b", "scene_id", "agent_id", "t0_frame", count.alias("__n"))
             .with_columns(step=pl.int_ranges(0, pl.col("__n"))).explode("step")
             .with_columns(frame=pl.col("t0_frame") - (n_past - 1) + pl.col("step"))
             .join(tracks, on=["scene_id", "agent_id", "frame"], how="left")
             .sort("__b", "step"))
    missing = steps.filter(pl.col("x").is_null())
    if missing.height:
        first = missing.row(0, named=True)
        raise DataError(f"sample {first['__b']} of the selection: target {first['agent_id']} of scene "
                        f"'{first['scene_id']}' has no position at frame {first['frame']}", path=path)
    width = int(steps.get_column("step").max()) + 1
    out = np.full((len(samples), width, 2), np.nan)
    out[steps.get_column("__b").to_numpy(), steps.get_column("step").to_numpy()] = steps.select("x", "y").to_numpy()
    return out


def _extended_horizons(samples: pl.DataFrame, n_future: int, path: Path) -> np.ndarray:
    """(B,) each sample's own ground-truth horizon: `n_future_max` where the table has it (null: n_future)."""
    if "n_future_max" not in samples.columns:
        return np.full(samples.height, n_future, dtype=np.int64)
    horizon = samples.get_column("n_future_max").fill_null(n_future).cast(pl.Int64)
    short = samples.filter(horizon < n_future)
    if short.height:
        raise DataError(f"sample {short.get_column('sample_id')[0]} has n_future_max "
                        f"{horizon.filter(horizon < n_future)[0]} below its n_future {n_future}", path=path)
    return horizon.to_numpy()


def _neighbours(samples: pl.DataFrame, tracks: pl.DataFrame, n_past: int) -> dict[str, np.ndarray]:
    """Dense, padded past positions and classes of every other agent present at each sample's t0."""
    batch = samples.height
    present = (samples.select("__b", "scene_id", pl.col("agent_id").alias("target"), "t0_frame")
               .join(tracks.select("scene_id", pl.col("frame").alias("t0_frame"), "agent_id", "agent_type"),
                     on=["scene_id", "t0_frame"], how="inner")
               .filter(pl.col("agent_id") != pl.col("target"))
               .sort("__b", "agent_id")
               .with_columns(slot=pl.int_range(pl.len()).over("__b")))
    n_max = int(present.get_column("slot").max() or -1) + 1 if present.height else 0
    positions = np.zeros((batch, n_max, n_past, 2), dtype=np.float32)
    valid = np.zeros((batch, n_max, n_past), dtype=bool)
    mask = np.zeros((batch, n_max), dtype=bool)
    types = np.zeros((batch, n_max), dtype=np.int64)
    if n_max == 0:
        return {"neighbours": positions, "neighbours_valid": valid, "neighbours_mask": mask, "neighbours_type": types}
    b, slot = present.get_column("__b").to_numpy(), present.get_column("slot").to_numpy()
    mask[b, slot] = True
    types[b, slot] = present.select(_type_index()).to_series().to_numpy()
    history = (present.select("__b", "slot", "scene_id", "agent_id", "t0_frame")
               .with_columns(step=pl.int_ranges(0, n_past)).explode("step")
               .with_columns(frame=pl.col("t0_frame") - (n_past - 1) + pl.col("step"))
               .join(tracks.select("scene_id", "agent_id", "frame", "x", "y"),
                     on=["scene_id", "agent_id", "frame"], how="inner"))
    hb, hs, hstep = (history.get_column(c).to_numpy() for c in ("__b", "slot", "step"))
    positions[hb, hs, hstep] = history.select("x", "y").to_numpy()
    valid[hb, hs, hstep] = True
    return {"neighbours": positions, "neighbours_valid": valid, "neighbours_mask": mask, "neighbours_type": types}


def build_problems(ds: Dataset, samples: pl.DataFrame, *, extended: bool = False) -> Problems:
    """Assemble tensors for the given rows of the samples table (all with the same n_past and n_future).

    `extended` also reads each sample's ground truth up to its own `n_future_max` (see the module docstring).
    """
    path = ds.path / "samples.parquet"
    if samples.height == 0:
        raise DataError("the selected split has no samples", path=path)
    n_past, n_future = _uniform(samples, "n_past", path), _uniform(samples, "n_future", path)
    horizon = _extended_horizons(samples, n_future, path) if extended else None
    samples = samples.with_row_index("__b").with_columns(pl.col("__b").cast(pl.Int64))
    tracks = _tracks_of(ds, samples.get_column("scene_id"))
    if horizon is None:
        window = _target_positions(samples, tracks, n_past + n_future, n_past, path)
    else:
        window = _target_positions(samples.with_columns(__steps=pl.Series(horizon + n_past)), tracks, "__steps",
                                   n_past, path)
    target_type = (samples.select("__b", "scene_id", "agent_id", pl.col("t0_frame").alias("frame"))
                   .join(tracks, on=["scene_id", "agent_id", "frame"], how="left").sort("__b")
                   .select(_type_index()).to_series().to_numpy())
    context = _neighbours(samples, tracks, n_past)
    scenes = ds.scenes()
    has_map = "map_path" in scenes.columns and scenes.get_column("map_path").null_count() < scenes.height
    map_crop = None
    if has_map:
        past = window[:, :n_past]
        map_crop = torch.from_numpy(crops_for_problems(ds.path, samples.get_column("scene_id").to_numpy(),
                                                       past[:, -1], past_headings(past), dtype=np.uint8))
    batch = SceneBatch(
        past=torch.from_numpy(window[:, :n_past].astype(np.float32)),
        future=torch.from_numpy(window[:, n_past:n_past + n_future].astype(np.float32)),
        agent_type=torch.from_numpy(np.array(target_type, dtype=np.int64)),
        **{name: torch.from_numpy(value) for name, value in context.items()},
        map_crop=map_crop,
    )
    joint = samples.get_column("joint_id") if "joint_id" in samples.columns else samples.get_column("sample_id")
    return Problems(
        batch=batch,
        sample_id=samples.get_column("sample_id").to_numpy(),
        scene_id=samples.get_column("scene_id").to_numpy(),
        agent_id=samples.get_column("agent_id").to_numpy(),
        t0_frame=samples.get_column("t0_frame").to_numpy(),
        group_id=samples.get_column("group_id").to_numpy(),
        joint_id=joint.to_numpy(),
        dt=ds.meta.dt, dataset=ds.meta.dataset, n_past=n_past, n_future=n_future, has_map=has_map,
        fingerprint=ds.fingerprint(), horizon=horizon,
        extended_future=None if horizon is None else torch.from_numpy(window[:, n_past:].astype(np.float32)),
    )


def load_problems(dataset_dir: str | Path, fold: str | None = None, split: str = "train", *,
                  extended: bool = False) -> Problems:
    """The prediction problems of `split` (train / val / test) of a dataset, as tensors on the CPU; `extended`
    also reads each sample's ground truth up to its `n_future_max` (evaluation past the trained horizon)."""
    ds = open_dataset(dataset_dir)
    return build_problems(ds, select_samples(ds, fold, split), extended=extended)
