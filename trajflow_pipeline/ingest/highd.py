"""`trajflow ingest levelx highd`: highD (levelX highway recordings) as a unified Parquet dataset, with the image
as the map: lane changes into a gap (the changing vehicle and the vehicle in the target lane it merges in front of,
predicted jointly) or every vehicle (``--problems all-agents``); 15 past / 25 future steps at 0.2 s, 5 folds of
whole episodes. The specification: docs/datasets/levelx.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import polars as pl

from .base import Ingest
from .levelx import LAYOUTS
from .levelx_pipeline import (ALL_AGENTS, FOLDS, STRIDE, Horizons, Scenario, check_problems, ingest_levelx,
                              parse_classes, wrote_line)

DATASET = "highd"
DT = 0.2
N_PAST, N_FUTURE = 15, 25
LANE_CHANGE = "lane-change"
#: the prediction is made this many steps (2 s) before the changing vehicle's centre crosses into the target lane
LEAD_STEPS = 10
LAYOUT = LAYOUTS[DATASET]
CLASSES = ("car", "truck")


def lane_change_pairs(tracks: pl.DataFrame, horizons: Horizons) -> pl.DataFrame:
    """One row per lane change into a gap: the changing vehicle (target) at the first frame its centre is in the
    new lane (decision_frame), and the vehicle then following it in that lane (ego, highD's followingId), which
    was in that lane at t0 = decision_frame - LEAD_STEPS (later if either lacks a full past). Kept when t0 is
    before the change and both vehicles are recorded for n_future steps after t0."""
    rows = tracks.select("agent_id", "frame", "lane_id", "following_id")
    same = (pl.col("agent_id").shift(1) == pl.col("agent_id")) & (pl.col("frame").shift(1) == pl.col("frame") - 1)
    changes = (rows.with_columns(from_lane=pl.col("lane_id").shift(1))
               .filter(same & (pl.col("lane_id") != pl.col("from_lane")) & (pl.col("following_id") > 0))
               .select(pl.col("agent_id").alias("target_id"), pl.col("following_id").alias("ego_id"),
                       pl.col("frame").alias("decision_frame"), "from_lane", pl.col("lane_id").alias("to_lane")))
    spans = rows.group_by("agent_id").agg(first=pl.col("frame").min(), last=pl.col("frame").max())
    back = horizons.n_past - 1
    t0 = pl.max_horizontal(pl.col("decision_frame") - LEAD_STEPS, pl.col("first") + back, pl.col("first_ego") + back)
    ego_lane = rows.select(pl.col("agent_id").alias("ego_id"), pl.col("frame").alias("t0_frame"),
                           pl.col("lane_id").alias("ego_lane"))
    return (changes.join(spans, left_on="target_id", right_on="agent_id")
            .join(spans, left_on="ego_id", right_on="agent_id", suffix="_ego")
            .with_columns(t0_frame=t0)
            .filter((pl.col("t0_frame") < pl.col("decision_frame"))
                    & (pl.col("t0_frame") + horizons.n_future <= pl.min_horizontal("last", "last_ego")))
            .join(ego_lane, on=["ego_id", "t0_frame"], how="left")
            .filter(pl.col("ego_lane") == pl.col("to_lane"))
            .select("target_id", "ego_id", "t0_frame", "decision_frame", "from_lane", "to_lane")
            .sort("t0_frame", "target_id"))


SCENARIO = Scenario(LANE_CHANGE, "lane change into a gap (a vehicle changing lanes in front of a follower in the "
                    "target lane)", lane_change_pairs)


def ingest_highd(raw: str | Path, out: str | Path, *, recordings: Sequence[int | str] | None = None,
                 problems: str = LANE_CHANGE, classes: Sequence[str] | str | None = None, stride: int | None = None,
                 overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest highD recordings from `raw` (a folder, its data/ sub-folder or one recording's file) into `out`:
    lane changes into a gap, or (`problems` "all-agents") every vehicle of `classes` every `stride` frames."""
    scenario = SCENARIO if check_problems(problems, (LANE_CHANGE,), classes, stride) != ALL_AGENTS else None
    return ingest_levelx(LAYOUT, raw, out, horizons=Horizons(DT, N_PAST, N_FUTURE), scenario=scenario,
                         classes=parse_classes(classes, CLASSES), stride=stride or STRIDE, recordings=recordings,
                         overwrite=overwrite, quiet=quiet)


ADAPTER = Ingest(name=DATASET, dataset=DATASET, dt=DT, folds=tuple(str(fold) for fold in range(FOLDS)),
                 raw="the folder of levelX highD recordings", function=ingest_highd, summary=wrote_line)
