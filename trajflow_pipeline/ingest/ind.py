"""`trajflow ingest levelx ind`: inD (levelX intersection recordings) as a unified Parquet dataset, with the image
as the map: gap acceptance at the intersections (a vehicle turning left across the oncoming traffic and an
oncoming vehicle it may cut off, predicted jointly) or every road user (``--problems all-agents``); 15 past / 25
future steps at 0.2 s, 5 folds of whole episodes. The specification: docs/datasets/levelx.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import polars as pl

from .base import Ingest
from .levelx import LAYOUTS
from .levelx_pipeline import (ALL_AGENTS, DEFAULT_CLASSES, FOLDS, MOTOR_CLASSES, STRIDE, Horizons, Scenario,
                              check_problems, ingest_levelx, parse_classes, wrote_line)

DATASET = "ind"
DT = 0.2
N_PAST, N_FUTURE = 15, 25
GAP_ACCEPTANCE = "gap-acceptance"
LAYOUT = LAYOUTS[DATASET]
#: a left turn changes the course by this much (degrees, counter-clockwise: right-hand traffic seen from above)
LEFT_TURN_DEG = (45.0, 135.0)
#: an oncoming vehicle goes straight (|course change| below this) against the turner's approach (within this)
STRAIGHT_DEG = 25.0
ONCOMING_DEG = 30.0
#: the two paths cross where they come this close (m); the gap matters when the two pass there within this (steps)
CONFLICT_DISTANCE = 2.0
MAX_GAP_STEPS = 30
#: the prediction is made this many steps (2 s) before the decision (the first of the two to pass the conflict)
LEAD_STEPS = 10
#: below this speed (m/s) a vehicle's course says nothing (its approach and exit courses are taken while moving)
MIN_SPEED = 1.0


def _wrap_deg(angle: pl.Expr) -> pl.Expr:
    return (angle + 180.0) % 360.0 - 180.0


def _courses(tracks: pl.DataFrame) -> pl.DataFrame:
    """Per motor vehicle its span, its approach and exit course (degrees, first and last moving rows) and turn."""
    moving = (pl.col("vx") ** 2 + pl.col("vy") ** 2).sqrt() >= MIN_SPEED
    course = pl.arctan2(pl.col("vy"), pl.col("vx")).degrees()
    return (tracks.filter(pl.col("agent_class").is_in(MOTOR_CLASSES))
            .group_by("agent_id").agg(first=pl.col("frame").min(), last=pl.col("frame").max(),
                                      approach=course.filter(moving).first(), leave=course.filter(moving).last())
            .drop_nulls()
            .with_columns(turn=_wrap_deg(pl.col("leave") - pl.col("approach"))))


def gap_pairs(tracks: pl.DataFrame, horizons: Horizons) -> pl.DataFrame:
    """One row per gap a left-turning vehicle (target) accepts or rejects: an oncoming vehicle (ego) going straight
    whose path crosses the target's (closest approach of the two paths, in space, under CONFLICT_DISTANCE) and
    that passes that conflict point within MAX_GAP_STEPS of the target. Every ego passing first is a rejected
    gap; the first passing after the target is the accepted one. decision_frame: when the first of the two
    passes; t0 = decision - LEAD_STEPS (later if either lacks a full past); kept when t0 is before the decision and
    both are recorded for n_future steps after t0."""
    vehicles = _courses(tracks)
    low, high = LEFT_TURN_DEG
    turners = vehicles.filter(pl.col("turn").is_between(low, high))
    straight = vehicles.filter(pl.col("turn").abs() < STRAIGHT_DEG)
    opposite = _wrap_deg(pl.col("approach_ego") - pl.col("approach") - 180.0).abs() < ONCOMING_DEG
    overlap = (pl.col("first_ego") <= pl.col("last")) & (pl.col("first") <= pl.col("last_ego"))
    candidates = (turners.join(straight, how="cross", suffix="_ego")
                  .filter((pl.col("agent_id") != pl.col("agent_id_ego")) & opposite & overlap)
                  .select(pl.col("agent_id").alias("target_id"), pl.col("agent_id_ego").alias("ego_id"),
                          "first", "last", "first_ego", "last_ego"))
    if candidates.height == 0:
        return pl.DataFrame(schema={"target_id": pl.Int64, "ego_id": pl.Int64, "t0_frame": pl.Int64,
                                    "decision_frame": pl.Int64, "gap": pl.String, "conflict_frame": pl.Int64})
    positions = tracks.select("agent_id", "frame", "x", "y")
    paths = (candidates.select("target_id", "ego_id")
             .join(positions.rename({"agent_id": "target_id", "frame": "frame_t", "x": "xt", "y": "yt"}),
                   on="target_id")
             .join(positions.rename({"agent_id": "ego_id", "frame": "frame_e", "x": "xe", "y": "ye"}), on="ego_id")
             .with_columns(distance=((pl.col("xt") - pl.col("xe")) ** 2 + (pl.col("yt") - pl.col("ye")) ** 2).sqrt()))
    crossing = (paths.sort("distance", "frame_t", "frame_e").group_by("target_id", "ego_id").first()
                .filter(pl.col("distance") < CONFLICT_DISTANCE)
                .filter((pl.col("frame_t") - pl.col("frame_e")).abs() <= MAX_GAP_STEPS)
                .join(candidates, on=["target_id", "ego_id"]))
    rejected = crossing.filter(pl.col("frame_e") <= pl.col("frame_t")).with_columns(gap=pl.lit("rejected"))
    accepted = (crossing.filter(pl.col("frame_e") > pl.col("frame_t")).sort("target_id", "frame_e", "ego_id")
                .group_by("target_id", maintain_order=True).first().with_columns(gap=pl.lit("accepted")))
    back = horizons.n_past - 1
    decision = pl.min_horizontal("frame_t", "frame_e")
    t0 = pl.max_horizontal(pl.col("decision_frame") - LEAD_STEPS, pl.col("first") + back, pl.col("first_ego") + back)
    return (pl.concat([rejected, accepted.select(rejected.columns)])
            .with_columns(decision_frame=decision, conflict_frame=pl.col("frame_t"))
            .with_columns(t0_frame=t0)
            .filter((pl.col("t0_frame") < pl.col("decision_frame"))
                    & (pl.col("t0_frame") + horizons.n_future <= pl.min_horizontal("last", "last_ego")))
            .select("target_id", "ego_id", "t0_frame", "decision_frame", "gap", "conflict_frame")
            .sort("t0_frame", "target_id", "ego_id"))


SCENARIO = Scenario(GAP_ACCEPTANCE, "gap-acceptance situation (a vehicle turning left across an oncoming one)",
                    gap_pairs)


def ingest_ind(raw: str | Path, out: str | Path, *, recordings: Sequence[int | str] | None = None,
               problems: str = GAP_ACCEPTANCE, classes: Sequence[str] | str | None = None, stride: int | None = None,
               overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest inD recordings from `raw` (a folder, its data/ sub-folder or one recording's file) into `out`:
    gap acceptance at the intersections, or (`problems` "all-agents") every road user of `classes` every
    `stride` frames."""
    scenario = SCENARIO if check_problems(problems, (GAP_ACCEPTANCE,), classes, stride) != ALL_AGENTS else None
    return ingest_levelx(LAYOUT, raw, out, horizons=Horizons(DT, N_PAST, N_FUTURE), scenario=scenario,
                         classes=parse_classes(classes, DEFAULT_CLASSES), stride=stride or STRIDE,
                         recordings=recordings, overwrite=overwrite, quiet=quiet)


ADAPTER = Ingest(name=DATASET, dataset=DATASET, dt=DT, folds=tuple(str(fold) for fold in range(FOLDS)),
                 raw="the folder of levelX inD recordings", function=ingest_ind, summary=wrote_line)
