"""OPTICS-Xi cluster extraction (scikit-learn's cluster_optics_xi) for many reachability plots and xi values at once.

The reference walks each plot's steep points one by one. Here every (plot, xi) pair is a lane and all lanes take
their next steep point together, so the walk costs one array step per steep area instead of one Python step per
point and fit; see docs/rome.md for why the result is the same.
"""

from __future__ import annotations

import numpy as np


def _region_ends(steep: np.ndarray, xward: np.ndarray, min_samples: int) -> np.ndarray:
    """For every position s (L, n): where a steep area that starts at s ends (scikit-learn's _extend_region).

    From s on, the area grows over steep points and over at most `min_samples` consecutive points that are
    neither steep nor going the other way; a point going the other way, or one neutral point too many, stops it.
    The area ends at the last steep point before the stop.
    """
    n_lanes, n = steep.shape
    positions = np.arange(n, dtype=np.int32)  # 32-bit positions: half the memory traffic of int64
    none_before, none_after = np.int32(-1), np.int32(n)
    neutral = ~steep & ~xward
    last_break = np.maximum.accumulate(np.where(neutral, none_before, positions), axis=1)
    stop = (xward & ~steep) | (neutral & (positions - last_break > min_samples))
    first_stop = np.minimum.accumulate(np.where(stop, positions, none_after)[:, ::-1], axis=1)[:, ::-1]
    stop_after = np.concatenate([first_stop[:, 1:], np.full((n_lanes, 1), n, dtype=np.int32)], axis=1)
    last_steep = np.maximum.accumulate(np.where(steep, positions, none_before), axis=1)
    return np.take_along_axis(last_steep, stop_after - 1, axis=1)


class _RangeMax:
    """Maximum of a plot over any inclusive range [a, c], in O(1) per query (a sparse table per plot)."""

    def __init__(self, plots: np.ndarray) -> None:
        levels = [plots]
        width = 1
        while 2 * width <= plots.shape[1]:
            previous = levels[-1]
            level = previous.copy()
            level[:, :-width] = np.maximum(previous[:, :-width], previous[:, width:])
            levels.append(level)
            width *= 2
        self.levels = np.stack(levels)
        lengths = np.arange(plots.shape[1] + 1)
        self.log2 = np.zeros(lengths.size, dtype=np.int64)
        self.log2[1:] = np.floor(np.log2(lengths[1:])).astype(np.int64)

    def __call__(self, plot: np.ndarray, a: np.ndarray, c: np.ndarray) -> np.ndarray:
        k = self.log2[c - a + 1]
        return np.maximum(self.levels[k, plot, a], self.levels[k, plot, c - (1 << k) + 1])


def _first_true_from(flags: np.ndarray) -> np.ndarray:
    """(L, n + 1): for each position i, the first position >= i that is True in flags (L, n); n where none."""
    n_lanes, n = flags.shape
    positions = np.where(flags, np.arange(n), n)
    first = np.minimum.accumulate(positions[:, ::-1], axis=1)[:, ::-1]
    return np.concatenate([first, np.full((n_lanes, 1), n)], axis=1)


def _advance_while(condition, values: np.ndarray, active: np.ndarray, step: int) -> np.ndarray:
    """values + step while condition(values) holds, element-wise, for the `active` elements (a vectorised while)."""
    values = values.copy()
    moving = active & condition(values)
    while moving.any():
        values[moving] += step
        moving &= condition(values)
    return values


def xi_plot_labels(reachability_plot: np.ndarray, predecessor_position: np.ndarray, xis: np.ndarray,
                   min_samples: int, min_cluster_size: int = 2) -> np.ndarray:
    """Xi cluster labels in plot order, (B, X, n), for B reachability plots (B, n) and X values of xi.

    `predecessor_position` (B, n): the plot position of each plot point's predecessor (-1 for none), which is
    what scikit-learn's predecessor correction looks up. Labels are 0, 1, ... in plot order, -1 outside clusters,
    exactly as cluster_optics_xi with predecessor correction gives them (before it maps them to point order).
    """
    n_plots, n = reachability_plot.shape
    n_xi = xis.size
    plots = np.concatenate([reachability_plot, np.full((n_plots, 1), np.inf)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = plots[:, :-1] / plots[:, 1:]
    plot_of = np.repeat(np.arange(n_plots), n_xi)                      # lane -> plot
    complement = np.tile(1 - xis, n_plots)                             # lane -> 1 - xi
    lane_ratio = ratio[plot_of]
    steep_up = lane_ratio <= complement[:, None]
    steep_down = lane_ratio >= (1 / complement)[:, None]
    upward, downward = (ratio < 1)[plot_of], (ratio > 1)[plot_of]
    down_end = _region_ends(steep_down, upward, min_samples)
    up_end = _region_ends(steep_up, downward, min_samples)
    next_steep = _first_true_from(steep_up | steep_down)
    del lane_ratio, upward, downward
    range_max = _RangeMax(plots)

    n_lanes = plot_of.size
    index = np.zeros(n_lanes, dtype=np.int64)
    mib = np.zeros(n_lanes)
    depth = 4
    sda_start = np.zeros((n_lanes, depth), dtype=np.int64)
    sda_end = np.zeros((n_lanes, depth), dtype=np.int64)
    sda_mib = np.zeros((n_lanes, depth))
    count = np.zeros(n_lanes, dtype=np.int64)
    last_end = np.full(n_lanes, -1, dtype=np.int64)
    starts = np.zeros((n_lanes, n), dtype=bool)
    ends = np.zeros((n_lanes, n), dtype=bool)
    live = np.arange(n_lanes)
    while True:
        steep_at = next_steep[live, index[live]]
        going = steep_at < n
        live, steep_at = live[going], steep_at[going]
        if live.size == 0:
            break
        plot, xic = plot_of[live], complement[live]
        m = np.maximum(mib[live], range_max(plot, index[live], steep_at))
        # keep the steep-down areas whose start still stands above the new maximum-in-between (a prefix)
        slots = np.arange(depth)
        kept = (slots < count[live, None]) & (m[:, None] <= plots[plot[:, None], sda_start[live]] * xic[:, None])
        kept &= ~np.isinf(m)[:, None]
        count[live] = kept.sum(axis=1)
        sda_mib[live] = np.where(kept, np.maximum(sda_mib[live], m[:, None]), sda_mib[live])
        is_down = steep_down[live, steep_at]

        down, at = live[is_down], steep_at[is_down]
        if down.size:
            if count[down].max() >= depth:
                grow = depth
                sda_start = np.concatenate([sda_start, np.zeros((n_lanes, grow), dtype=np.int64)], axis=1)
                sda_end = np.concatenate([sda_end, np.zeros((n_lanes, grow), dtype=np.int64)], axis=1)
                sda_mib = np.concatenate([sda_mib, np.zeros((n_lanes, grow))], axis=1)
                depth += grow
            end = down_end[down, at]
            slot = count[down]
            sda_start[down, slot], sda_end[down, slot], sda_mib[down, slot] = at, end, 0.0
            count[down] += 1
            index[down] = end + 1
            mib[down] = plots[plot_of[down], end + 1]

        up, u_start = live[~is_down], steep_at[~is_down]
        if up.size:
            u_end = up_end[up, u_start]
            index[up] = u_end + 1
            mib[up] = plots[plot_of[up], u_end + 1]
            chosen_start, chosen_end, found = _cluster_for_upward_area(
                plots, predecessor_position, plot_of[up], complement[up], u_start, u_end, sda_start[up],
                sda_end[up], sda_mib[up], count[up], min_cluster_size)
            accept = found & (chosen_start > last_end[up])
            lanes = up[accept]
            starts[lanes, chosen_start[accept]] = True
            ends[lanes, chosen_end[accept]] = True
            last_end[lanes] = chosen_end[accept]

    opened = np.cumsum(starts, axis=1)
    closed_before = np.cumsum(ends, axis=1) - ends
    labels = np.where(opened > closed_before, opened - 1, -1)
    return labels.reshape(n_plots, n_xi, n)


def _cluster_for_upward_area(plots: np.ndarray, predecessor_position: np.ndarray, plot: np.ndarray,
                             xic: np.ndarray, u_start: np.ndarray, u_end: np.ndarray, sda_start: np.ndarray,
                             sda_end: np.ndarray, sda_mib: np.ndarray, count: np.ndarray,
                             min_cluster_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The one cluster an upward area can add per lane: (start, end, found), all (U,).

    Every cluster an upward area proposes spans from its steep-down area to the upward area, so they all overlap
    and the reference's label extraction keeps at most the first it sees, the one from the newest steep-down area
    that passes the tests; it keeps that one only if it starts after the last cluster kept.
    """
    n_up, depth = sda_start.shape
    row = plot[:, None]
    valid = np.arange(depth) < count[:, None]
    c_end = np.broadcast_to(u_end[:, None], (n_up, depth)).copy()
    end_level = plots[plot, u_end + 1][:, None]
    valid &= ~(end_level * xic[:, None] < sda_mib)
    d_max = plots[row, sda_start]
    left = valid & (d_max * xic[:, None] >= end_level)
    right = valid & ~left & (end_level * xic[:, None] >= d_max)
    c_start = _advance_while(lambda c: (plots[row, np.minimum(c + 1, plots.shape[1] - 1)] > end_level)
                             & (c < sda_end), sda_start, left, +1)
    c_end = _advance_while(lambda e: (plots[row, np.maximum(e - 1, 0)] > d_max) & (e > u_start[:, None]),
                           c_end, right, -1)
    # predecessor correction: shorten the end until it is lower than the start or its predecessor lies inside
    n = predecessor_position.shape[1]

    def uncorrected(e: np.ndarray) -> np.ndarray:
        e_safe = np.clip(e, 0, n - 1)
        pred = predecessor_position[row, e_safe]
        inside = (c_start <= pred) & (pred < e)
        return (c_start < e) & ~(plots[row, c_start] > plots[row, e_safe]) & ~inside

    c_end = _advance_while(uncorrected, c_end, valid, -1)
    valid &= c_start < c_end
    valid &= (c_end - c_start + 1 >= min_cluster_size) & (c_start <= sda_end) & (c_end >= u_start[:, None])
    found = valid.any(axis=1)
    newest = depth - 1 - np.argmax(valid[:, ::-1], axis=1)
    lanes = np.arange(n_up)
    return c_start[lanes, newest], c_end[lanes, newest], found
