"""The unified Parquet scene dataset, contract version 1: the one place that knows column names and types.

A dataset directory holds three tables (SPEC section 2):

* ``scenes``  — one row per scene (a continuous recording window), with the protocol's split tags;
* ``tracks``  — one row per (scene, agent, frame), sorted by scene, agent, frame; sharded in ``tracks/``;
* ``samples`` — one row per prediction problem (target agent, last observed frame, horizons, group, split).

Column names are fixed because users script against them; extra columns are allowed and kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import polars as pl

SCHEMA_VERSION = 1

#: Agent classes allowed in `tracks.agent_type`; models index classes in this order.
AGENT_TYPES: tuple[str, ...] = ("pedestrian", "vehicle", "bicycle", "motorcycle", "unknown")

#: Key-value metadata keys carried by every Parquet file of a dataset.
META_SCHEMA_VERSION = "trajflow.schema_version"
META_DATASET = "trajflow.dataset"
META_DT = "trajflow.dt"
META_VERSION = "trajflow.version"
META_TABLE = "trajflow.table"
META_PROTOCOL = "trajflow.protocol"

#: Evaluation protocols a dataset can declare (how train / val / test are selected from `samples`).
PROTOCOL_FOLDS = "folds"  # a `fold` option picks the test fold; the others train (leave-one-out, k-fold)
PROTOCOL_FIXED = "fixed"  # the `split` column says train / val / test (nuScenes challenge)
PROTOCOL_TRAIN_IS_TEST = "train-is-test"  # test on every sample; `split` holds train / val for fitting
PROTOCOLS = (PROTOCOL_FOLDS, PROTOCOL_FIXED, PROTOCOL_TRAIN_IS_TEST)

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class TableSpec:
    """Required and optional columns of one table, its key and its sort order."""

    name: str
    required: dict[str, pl.DataType]
    optional: dict[str, pl.DataType] = field(default_factory=dict)
    key: tuple[str, ...] = ()
    sort: tuple[str, ...] = ()
    #: float columns that must be finite wherever they are not null
    finite: tuple[str, ...] = ()
    #: columns that may hold nulls (all others must not)
    nullable: tuple[str, ...] = ()

    @property
    def columns(self) -> dict[str, pl.DataType]:
        return {**self.required, **self.optional}


SCENES = TableSpec(
    name="scenes",
    required={
        "dataset": pl.String(),
        "scene_id": pl.String(),
        "location": pl.String(),
        "dt": pl.Float64(),
        "source": pl.String(),
        "fold": pl.String(),
    },
    optional={
        # first frame (at the scene's dt) of the validation part of a training scene (ETH/UCY time cut)
        "val_start_frame": pl.Int64(),
        # map raster: path relative to the dataset dir, metres per pixel, world->pixel affine [a, b, c, d, e, f]
        # with px = a*x + b*y + c, py = d*x + e*y + f
        "map_path": pl.String(),
        "map_m_per_px": pl.Float64(),
        "map_world_to_px": pl.List(pl.Float64()),
    },
    key=("scene_id",),
    finite=("dt", "map_m_per_px"),
    nullable=("fold", "val_start_frame", "map_path", "map_m_per_px", "map_world_to_px"),
)

TRACKS = TableSpec(
    name="tracks",
    required={
        "scene_id": pl.String(),
        "agent_id": pl.Int64(),
        "agent_type": pl.String(),
        "frame": pl.Int64(),
        "t": pl.Float64(),
        "x": pl.Float64(),
        "y": pl.Float64(),
    },
    optional={
        "heading": pl.Float64(),
        "vx": pl.Float64(),
        "vy": pl.Float64(),
        "length": pl.Float64(),
        "width": pl.Float64(),
    },
    key=("scene_id", "agent_id", "frame"),
    sort=("scene_id", "agent_id", "frame"),
    finite=("t", "x", "y", "heading", "vx", "vy", "length", "width"),
    nullable=("heading", "vx", "vy", "length", "width"),
)

SAMPLES = TableSpec(
    name="samples",
    required={
        "sample_id": pl.Int64(),
        "scene_id": pl.String(),
        "agent_id": pl.Int64(),
        "t0_frame": pl.Int64(),
        "n_past": pl.Int64(),
        "n_future": pl.Int64(),
        "group_id": pl.Int64(),
        "split": pl.String(),
        "fold": pl.String(),
    },
    optional={
        # several agents predicted together (same scene and t0) share it; joint metrics group by it
        "joint_id": pl.Int64(),
    },
    key=("sample_id",),
    sort=("sample_id",),
    nullable=("split", "fold"),
)

TABLES: dict[str, TableSpec] = {spec.name: spec for spec in (SCENES, TRACKS, SAMPLES)}


def empty_frame(spec: TableSpec) -> pl.DataFrame:
    """An empty table with the spec's required columns, for datasets that legitimately have no rows."""
    return pl.DataFrame(schema=spec.required)


def _widening(source: pl.DataType, target: pl.DataType) -> bool:
    """Whether casting `source` to `target` loses nothing (narrower ints or floats to the contract's)."""
    if target == pl.Int64:
        return source.is_integer() and source != pl.UInt64
    if target == pl.Float64:
        return source.is_float() or source.is_integer()
    return False


def conform(frame: pl.DataFrame, spec: TableSpec) -> pl.DataFrame:
    """Put the spec's columns first in contract order (extra columns after them), widening number types.

    Writers may build tables with narrower integers or floats (Int32, Float32); they are widened losslessly to
    the contract's Int64 / Float64 here. Anything else that differs is left for validation to report.
    """
    ordered = [name for name in spec.columns if name in frame.columns]
    extra = [name for name in frame.columns if name not in spec.columns]
    widened = [pl.col(name).cast(spec.columns[name]) if frame.schema[name] != spec.columns[name]
               and _widening(frame.schema[name], spec.columns[name]) else pl.col(name) for name in ordered]
    return frame.select(widened + extra)
