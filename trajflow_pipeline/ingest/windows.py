"""Which (agent, frame) pairs become prediction problems, and which problems share identical inputs.

Shared by the ingest stages whose protocol is "every agent at every frame with a complete window"
(ETH/UCY, bring-your-own CSV) and by anything that needs group ids for JSD.
"""

from __future__ import annotations

import math

import polars as pl

from ..errors import DataError
from .textfile import MAX_MAGNITUDE, in_range, range_problem

#: Past positions closer than this (metres, in the data's own coordinates) count as identical inputs.
GROUP_TOLERANCE_M = 1e-3


def complete_windows(tracks: pl.DataFrame, n_past: int, n_future: int) -> pl.DataFrame:
    """(scene_id, agent_id, t0_frame) of every window of n_past + n_future consecutive frames of one agent.

    `tracks` must be sorted by (scene_id, agent_id, frame) with unique keys, as the contract guarantees; then a
    window is complete exactly when the rows n_past - 1 before and n_future after the t0 row belong to the same
    agent and span n_past + n_future - 1 frames.
    """
    back, ahead = n_past - 1, n_future
    span = n_past + n_future - 1
    same_agent = pl.lit(True)
    for shift in (back, -ahead):
        same_agent = same_agent & (pl.col("scene_id").shift(shift) == pl.col("scene_id")) & (
            pl.col("agent_id").shift(shift) == pl.col("agent_id"))
    complete = same_agent & ((pl.col("frame").shift(-ahead) - pl.col("frame").shift(back)) == span)
    return (tracks.lazy()
            .select("scene_id", "agent_id", pl.col("frame").alias("t0_frame"), complete.alias("complete"))
            .filter(pl.col("complete"))
            .drop("complete")
            .collect())


def _window_hashes(tracks: pl.DataFrame, n_past: int, tolerance: float) -> pl.DataFrame:
    """Per track row: a hash of the agent's class and its positions over the n_past frames ending there.

    Positions are rounded to a `tolerance` grid; frames missing from the window simply do not contribute
    (their offsets are part of the hash, so gaps are told apart).
    """
    same_agent = [(pl.col("scene_id").shift(k) == pl.col("scene_id"))
                  & (pl.col("agent_id").shift(k) == pl.col("agent_id"))
                  & (pl.col("frame").shift(k) > pl.col("frame") - n_past) for k in range(n_past)]
    fields = []
    for k, valid in enumerate(same_agent):
        for name, value in (("offset", pl.col("frame").shift(k) - pl.col("frame")),
                            ("qx", (pl.col("x").shift(k) / tolerance).round().cast(pl.Int64)),
                            ("qy", (pl.col("y").shift(k) / tolerance).round().cast(pl.Int64))):
            fields.append(pl.when(valid).then(value).otherwise(None).alias(f"{name}{k}"))
    return tracks.select("scene_id", "agent_id", "frame",
                         pl.struct("agent_type", *fields).hash(seed=0).alias("window_hash"))


def _check_on_grid(tracks: pl.DataFrame) -> None:
    """Every position is one the tolerance grid holds (finite, within textfile.MAX_MAGNITUDE): an ingest whose reader
    let a 1e300 through gets a DataError naming the row's scene, agent and frame here, not a bare integer-cast error
    from polars."""
    bad = tracks.filter(~(in_range(pl.col("x")) & in_range(pl.col("y"))))
    if bad.height:
        row = bad.row(0, named=True)
        value = row["x"] if not (math.isfinite(row["x"]) and abs(row["x"]) <= MAX_MAGNITUDE) else row["y"]
        why = range_problem(value)
        raise DataError(f"position ({row['x']}, {row['y']}) of agent {row['agent_id']} in scene '{row['scene_id']}' "
                        f"at frame {row['frame']} is {why}: check the raw coordinates and their units")


def identical_input_groups(samples: pl.DataFrame, tracks: pl.DataFrame,
                           tolerance: float = GROUP_TOLERANCE_M) -> pl.Series:
    """A group_id per sample: samples with identical inputs (even across scenes) share it.

    Inputs are identical when the same agents' classes are present at t0 and every past position (target's and
    context agents') agrees after rounding to a `tolerance` grid. `tracks` must be sorted as the contract says.
    A cheap key (the target's class and t0 position) is compared first: samples whose key is unique cannot share
    inputs with anyone, and only the rest (few in real data, all in multi-future sets) get their whole past
    windows and contexts hashed. Each agent window is hashed once, each (scene, frame) context once, so the cost
    is linear in the tracks and samples. Ids are numbered in order of each group's first sample.
    """
    _check_on_grid(tracks)
    base = samples.select("scene_id", "agent_id", "t0_frame", "n_past").with_row_index("__order")
    now = _window_hashes(tracks, 1, tolerance)
    keyed = (base.join(now, left_on=["scene_id", "agent_id", "t0_frame"], right_on=["scene_id", "agent_id", "frame"],
                       how="left")
             .with_columns(now_key=pl.struct("n_past", "window_hash").hash(seed=5))
             .with_columns(__candidate=pl.len().over("now_key") > 1))
    candidates = keyed.filter(pl.col("__candidate"))
    keys = [keyed.filter(~pl.col("__candidate")).select(
        "__order", pl.struct("now_key", pl.lit(None, dtype=pl.UInt64).alias("full_key")).alias("key"))]
    if candidates.height:
        for (n_past,), part in candidates.group_by("n_past"):
            windows = _window_hashes(_rows_in_windows(tracks, part, int(n_past)), int(n_past), tolerance)
            keys.append(_keys(part.select("__order", "scene_id", "agent_id", "t0_frame", "now_key"), windows,
                              "full_key").select("__order", pl.struct("now_key", "full_key").alias("key")))
    ordered = pl.concat(keys).sort("__order")
    first_seen = pl.col("__order").min().over("key")
    return ordered.select(first_seen.rank("dense").cast(pl.Int64).sub(1).alias("group_id")).to_series()


def _rows_in_windows(tracks: pl.DataFrame, samples: pl.DataFrame, n_past: int) -> pl.DataFrame:
    """The tracks rows (still sorted) at the frames of the samples' past windows, for every agent there."""
    frames = (samples.select("scene_id", pl.int_ranges(pl.col("t0_frame") - n_past + 1, pl.col("t0_frame") + 1)
                             .alias("frame"))
              .explode("frame").unique())
    return tracks.join(frames, on=["scene_id", "frame"], how="semi", maintain_order="left")


def _keys(samples: pl.DataFrame, windows: pl.DataFrame, name: str) -> pl.DataFrame:
    """`samples` with column `name`: a hash of the target's window and of the windows of everyone at t0.

    The context (everyone at t0) is keyed as a multiset, order-free: the wrapping sums of the window hashes and
    of a second hash of them, and the count.
    """
    windows_lazy = windows.lazy()
    context = (windows_lazy.group_by("scene_id", "frame")
               .agg(pl.col("window_hash").sum().alias("__sum"), pl.col("window_hash").hash(seed=4).sum().alias("__mix"),
                    pl.len().alias("__count"))
               .select("scene_id", "frame", pl.struct("__sum", "__mix", "__count").hash(seed=1).alias("context_hash")))
    return (samples.lazy()
            .join(windows_lazy, left_on=["scene_id", "agent_id", "t0_frame"],
                  right_on=["scene_id", "agent_id", "frame"], how="left")
            .join(context, left_on=["scene_id", "t0_frame"], right_on=["scene_id", "frame"], how="left")
            .select(*samples.columns, pl.struct("window_hash", "context_hash").hash(seed=2).alias(name))
            .collect())
