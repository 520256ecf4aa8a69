"""The two distance matrices ROME needs, from one pass over the squared coordinate differences: summed in coordinate
order (scipy's cdist, so OPTICS's reachabilities) and in numpy's pairwise order (ROME's silhouettes)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: bytes of one distance plane block (a few sets at a time, so that the running sums stay in a core's cache)
PLANE_BLOCK_BYTES = 1 << 17
#: numpy sums a contiguous float64 axis in eight interleaved running sums up to this length, halving above it
PAIRWISE_BLOCK = 128


def distance_matrices(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(in coordinate order, in numpy's order), each (B, n, n): the Euclidean distances of each point set (B, n, D).

    The first sums the squared coordinate differences in coordinate order, as scipy's cdist (which OPTICS uses
    for reachabilities) and the k-d tree that finds core distances in few dimensions do, so they equal theirs to
    the bit. The second is numpy's sqrt(((x - y)**2).sum(-1)), as ROME computes its silhouettes: the same squared
    differences summed in the order of numpy's pairwise summation for a contiguous axis (docs/rome.md). Each
    coordinate's plane of squared differences is made once and added to both sums, a few sets at a time.
    """
    n_sets, n, n_features = points.shape
    in_order, pairwise = np.empty((n_sets, n, n)), np.empty((n_sets, n, n))
    columns = np.ascontiguousarray(points.transpose(0, 2, 1))  # (B, D, n)
    step = max(1, PLANE_BLOCK_BYTES // (8 * n * n))
    for start in range(0, n_sets, step):
        block = columns[start:start + step]
        running = in_order[start:start + step]

        def plane(k: int) -> np.ndarray:
            """Coordinate k's squared differences, added to the in-order sum (planes come in order, once each)."""
            difference = block[:, k, :, None] - block[:, k, None, :]
            np.multiply(difference, difference, out=difference)
            if k == 0:
                running[...] = difference
            else:
                np.add(running, difference, out=running)
            return difference

        pairwise[start:start + step] = _pairwise_sum(plane, 0, n_features)
    np.sqrt(in_order, out=in_order)
    np.sqrt(pairwise, out=pairwise)
    return in_order, pairwise


def _pairwise_sum(plane: Callable[[int], np.ndarray], start: int, count: int) -> np.ndarray:
    """The sum of planes start .. start + count - 1 in numpy's pairwise order for float64 (`add.reduce` over a
    contiguous axis): sequential below 8 terms; up to PAIRWISE_BLOCK, eight interleaved running sums combined as
    ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), then the remainder in order; above, the two halves (the
    first a multiple of 8 long) summed alike and added. `plane` is called once per index, in increasing order; the
    arrays it returns become running sums."""
    if count < 8:
        total = plane(start)
        for k in range(start + 1, start + count):
            total += plane(k)
        return total
    if count <= PAIRWISE_BLOCK:
        sums = [plane(start + j) for j in range(8)]
        whole = count - count % 8
        for offset in range(8, whole, 8):
            for j in range(8):
                sums[j] += plane(start + offset + j)
        for left, right in ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (4, 6), (0, 4)):
            sums[left] += sums[right]
        for k in range(start + whole, start + count):
            sums[0] += plane(k)
        return sums[0]
    half = count // 2
    half -= half % 8
    total = _pairwise_sum(plane, start, half)
    total += _pairwise_sum(plane, start + half, count - half)
    return total
