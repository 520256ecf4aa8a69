"""Roundabout geometry for the rounD ingest: the :class:`RoundaboutGeometry` a scenario needs, read from a JSON file
or inferred from circulating traffic (nothing is hard-coded per location); see docs/datasets/round.md.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from ..errors import DataError, UsageError
from ..util import input_files

#: positions of vehicles slower than this (m/s) carry no usable course or curvature
MIN_SPEED = 2.0
#: radii of curvature (m) that can belong to a vehicle circulating in a roundabout
TURN_RADIUS_RANGE = (4.0, 80.0)
#: a curvature centre within this fraction of the turn radius (at least 2 m) of the estimate supports it
SUPPORT_TOLERANCE = 0.15
#: vehicle centres stay about half a vehicle width inside the carriageway's edges (m)
EDGE_CLEARANCE = 1.0
#: quantiles of the circulating vehicles' distances that bound the driven ring
RING_QUANTILES = (0.01, 0.99)
#: inference needs at least this many circulating positions from at least MIN_CIRCULATING_AGENTS vehicles
MIN_SUPPORT = 30
MIN_CIRCULATING_AGENTS = 2
#: cell size (m) of the histogram whose densest cell seeds the centre estimate
MODE_CELL = 2.0
#: crossings into the carriageway closer than this (rad) belong to the same entry arm
ARM_GAP = math.radians(25.0)


class GeometryError(DataError):
    """The roundabout geometry cannot be inferred from a recording (too little circulating traffic)."""


@dataclass(frozen=True)
class RoundaboutGeometry:
    """One roundabout's geometry and the scenario constants tied to it (metres, radians; see the module doc)."""

    centre_x: float
    centre_y: float
    inner_radius: float
    outer_radius: float
    direction: int = 1
    entry_angles: tuple[float, ...] = ()
    approach_margin: float = 10.0
    conflict_angle: float = math.pi / 6
    ego_band: float = 4.0
    source: str = "given"

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.centre_x, self.centre_y, self.inner_radius, self.outer_radius,
                                               self.approach_margin, self.conflict_angle, self.ego_band)):
            raise UsageError("roundabout geometry values must be finite numbers")
        if not 0 <= self.inner_radius < self.outer_radius:
            raise UsageError(f"roundabout geometry needs 0 <= inner_radius < outer_radius, got "
                             f"{self.inner_radius:g} and {self.outer_radius:g}")
        if self.direction not in (1, -1):
            raise UsageError(f"roundabout direction must be 1 (counter-clockwise) or -1, got {self.direction}")
        if not 0 < self.conflict_angle < math.pi:
            raise UsageError(f"conflict_angle must lie in (0, pi), got {self.conflict_angle:g}")
        if self.approach_margin < 0 or self.ego_band <= 0:
            raise UsageError("approach_margin must be >= 0 and ego_band > 0")

    @property
    def centre(self) -> tuple[float, float]:
        return (self.centre_x, self.centre_y)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready values (entry angles as a list)."""
        values = asdict(self)
        values["entry_angles"] = list(self.entry_angles)
        return values

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], where: str = "geometry") -> "RoundaboutGeometry":
        """Build from a mapping; `centre: [x, y]` may replace centre_x / centre_y. Unknown keys are refused."""
        values = dict(values)
        if "centre" in values:
            centre = values.pop("centre")
            if not (isinstance(centre, (list, tuple)) and len(centre) == 2):
                raise UsageError(f"{where}: centre must be [x, y]")
            values["centre_x"], values["centre_y"] = centre
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise UsageError(f"{where}: unknown key(s) {', '.join(unknown)} "
                             f"(known: centre, {', '.join(sorted(known))})")
        missing = [name for name in ("centre_x", "centre_y", "inner_radius", "outer_radius") if name not in values]
        if missing:
            raise UsageError(f"{where}: missing {', '.join(missing)}")
        try:
            floats = {k: float(v) for k, v in values.items() if k not in ("direction", "entry_angles", "source")}
            direction = int(values.get("direction", 1))
            angles = tuple(float(a) for a in values.get("entry_angles", ()))
        except (TypeError, ValueError) as error:
            raise UsageError(f"{where}: {error}") from None
        return cls(**floats, direction=direction, entry_angles=angles, source=str(values.get("source", "given")))


#: geometry configuration accepted by the ingest: one geometry for every recording, or one per locationId
GeometryConfig = RoundaboutGeometry | Mapping[int, RoundaboutGeometry]


def geometry_for(config: GeometryConfig | None, location_id: int) -> RoundaboutGeometry | None:
    """The configured geometry of a location, or None when it is to be inferred from the data."""
    if config is None:
        return None
    if isinstance(config, RoundaboutGeometry):
        return config
    return config.get(int(location_id))


def load_geometry_file(path: str | Path) -> GeometryConfig:
    """Read a JSON geometry file: one geometry object, or an object mapping locationId -> geometry object."""
    path = Path(path)
    try:
        data = json.loads(input_files.read_text(path))
    except OSError as error:
        raise UsageError(f"{path}: cannot read geometry file ({error.strerror})") from None
    except json.JSONDecodeError as error:
        raise UsageError(f"{path}:{error.lineno}: not valid JSON ({error.msg})") from None
    return parse_geometry(data, str(path))


def parse_geometry(data: Any, where: str) -> GeometryConfig:
    """One geometry object, or an object mapping locationId -> geometry object (as a JSON file or a config table
    holds them); `where` names the source in errors."""
    if not isinstance(data, dict):
        raise UsageError(f"{where}: expected a JSON object")
    if "centre" in data or "centre_x" in data:
        return RoundaboutGeometry.from_dict(data, where=where)
    result: dict[int, RoundaboutGeometry] = {}
    for key, value in data.items():
        try:
            location = int(key)
        except ValueError:
            raise UsageError(f"{where}: keys must be locationIds (integers), got {key!r}") from None
        if not isinstance(value, dict):
            raise UsageError(f"{where}: geometry of location {key} must be an object")
        result[location] = RoundaboutGeometry.from_dict(value, where=f"{where} (location {key})")
    return result


def geometry_option(value: Any) -> GeometryConfig:
    """rounD's `geometry` option as a config gives it: the path of a JSON geometry file, or the object itself."""
    if isinstance(value, str):
        return load_geometry_file(value)
    return parse_geometry(value, "the geometry table")


def _wrap(angle: pl.Expr) -> pl.Expr:
    """Angles wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def curvature_centres(motor: pl.DataFrame, dt: float) -> pl.DataFrame:
    """Per position: the signed turn radius (m, > 0 turning left) and the centre of curvature.

    `motor` holds agent_id, frame, x, y, vx, vy sorted by (agent_id, frame). The yaw rate is the centred
    difference of the course (direction of the velocity) between the neighbouring frames of the same agent.
    """
    course = pl.arctan2(pl.col("vy"), pl.col("vx"))
    same_before = (pl.col("frame").shift(1).over("agent_id") == pl.col("frame") - 1)
    same_after = (pl.col("frame").shift(-1).over("agent_id") == pl.col("frame") + 1)
    rate = _wrap(pl.col("course").shift(-1).over("agent_id") - pl.col("course").shift(1).over("agent_id")) / (2 * dt)
    return (motor.lazy()
            .with_columns(course=course, speed=(pl.col("vx") ** 2 + pl.col("vy") ** 2).sqrt())
            .with_columns(rate=pl.when(same_before & same_after).then(rate).otherwise(None))
            .with_columns(turn_radius=pl.col("speed") / pl.col("rate"))
            .with_columns(cx=pl.col("x") - pl.col("turn_radius") * pl.col("course").sin(),
                          cy=pl.col("y") + pl.col("turn_radius") * pl.col("course").cos())
            .filter((pl.col("speed") > MIN_SPEED) & pl.col("turn_radius").abs().is_between(*TURN_RADIUS_RANGE))
            .select("agent_id", "frame", "x", "y", "turn_radius", "cx", "cy")
            .collect())


def _support(points: np.ndarray, radius: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Which curvature centres agree with `centre` (within SUPPORT_TOLERANCE of their turn radius, >= 2 m)."""
    tolerance = np.maximum(2.0, SUPPORT_TOLERANCE * np.abs(radius))
    return np.hypot(*(points - centre).T) < tolerance


def _consensus_centre(centres: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A robust common centre of many curvature centres: the densest 2 m cell (left turns elsewhere in the view
    do not pull it), then the median of its supporters, three times."""
    low, high = centres.min(axis=0), centres.max(axis=0)
    bins = np.maximum(1, np.ceil((high - low) / MODE_CELL)).astype(int)
    counts, x_edges, y_edges = np.histogram2d(centres[:, 0], centres[:, 1], bins=bins,
                                              range=[(low[0], low[0] + bins[0] * MODE_CELL),
                                                     (low[1], low[1] + bins[1] * MODE_CELL)])
    i, j = np.unravel_index(np.argmax(counts), counts.shape)
    centre = np.array([(x_edges[i] + x_edges[i + 1]) / 2, (y_edges[j] + y_edges[j + 1]) / 2])
    support = _support(centres, radius, centre)
    for _ in range(3):
        if not support.any():
            break
        centre = np.median(centres[support], axis=0)
        support = _support(centres, radius, centre)
    return centre, support


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares (Kasa) circle through points: centre x, centre y, radius."""
    design = np.column_stack((x, y, np.ones_like(x)))
    (d, e, f), *_ = np.linalg.lstsq(design, -(x ** 2 + y ** 2), rcond=None)
    cx, cy = -d / 2, -e / 2
    return float(cx), float(cy), float(math.sqrt(max(cx ** 2 + cy ** 2 - f, 0.0)))


def entry_arm_angles(motor: pl.DataFrame, centre: tuple[float, float], outer_radius: float) -> tuple[float, ...]:
    """Polar angles of the entry arms: where vehicles cross into the carriageway, clustered (gaps > ARM_GAP)."""
    r = ((pl.col("x") - centre[0]) ** 2 + (pl.col("y") - centre[1]) ** 2).sqrt()
    crossing = ((pl.col("r") <= outer_radius) & (pl.col("r").shift(1).over("agent_id") > outer_radius)
                & (pl.col("frame").shift(1).over("agent_id") == pl.col("frame") - 1))
    angles = (motor.lazy().with_columns(r=r)
              .filter(crossing)
              .select(pl.arctan2(pl.col("y") - centre[1], pl.col("x") - centre[0]).alias("angle"))
              .collect().to_series().to_numpy())
    if len(angles) == 0:
        return ()
    angles = np.sort(angles)
    gaps = np.diff(np.concatenate((angles, angles[:1] + 2 * np.pi)))
    # start the clusters after the widest gap so that no cluster straddles the +-pi seam
    first = (int(np.argmax(gaps)) + 1) % len(angles)
    ordered = np.concatenate((angles[first:], angles[:first] + 2 * np.pi))
    labels = np.concatenate(([0], np.cumsum(np.diff(ordered) > ARM_GAP)))
    sums = np.stack([np.bincount(labels, np.cos(ordered)), np.bincount(labels, np.sin(ordered))], axis=1)
    means = np.arctan2(sums[:, 1], sums[:, 0])
    return tuple(float(a) for a in np.sort(means))


def infer_geometry(motor: pl.DataFrame, dt: float, *, where: str = "recording") -> RoundaboutGeometry:
    """Infer a roundabout's geometry from its motor vehicles' tracks (agent_id, frame, x, y, vx, vy; sorted).

    Raises GeometryError naming `where` when fewer than MIN_SUPPORT positions of MIN_CIRCULATING_AGENTS
    vehicles circulate.
    """
    turns = curvature_centres(motor, dt)
    candidates = []
    for sign in (1, -1):
        part = turns.filter(pl.col("turn_radius") * sign > 0)
        if part.height == 0:
            continue
        centres = part.select("cx", "cy").to_numpy()
        centre, support = _consensus_centre(centres, part.get_column("turn_radius").to_numpy())
        candidates.append((int(support.sum()), sign, part.filter(pl.Series(support))))
    if not candidates:
        raise GeometryError("cannot infer the roundabout geometry: no vehicle turns steadily "
                            "(pass the geometry explicitly)", path=where)
    count, direction, circulating = max(candidates, key=lambda item: item[0])
    agents = circulating.get_column("agent_id").n_unique()
    if count < MIN_SUPPORT or agents < MIN_CIRCULATING_AGENTS:
        raise GeometryError(f"cannot infer the roundabout geometry: only {count} positions of {agents} vehicle(s) "
                            f"circulate (need {MIN_SUPPORT} of {MIN_CIRCULATING_AGENTS}); pass the geometry "
                            "explicitly", path=where)
    cx, cy, _ = fit_circle(circulating.get_column("x").to_numpy(), circulating.get_column("y").to_numpy())
    distance = np.hypot(circulating.get_column("x").to_numpy() - cx, circulating.get_column("y").to_numpy() - cy)
    low, high = np.quantile(distance, RING_QUANTILES)
    inner, outer = max(float(low) - EDGE_CLEARANCE, 0.0), float(high) + EDGE_CLEARANCE
    return RoundaboutGeometry(centre_x=cx, centre_y=cy, inner_radius=inner, outer_radius=outer,
                              direction=direction, entry_angles=entry_arm_angles(motor, (cx, cy), outer),
                              source="inferred")

