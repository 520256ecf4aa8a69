"""Rasterised nuScenes maps: each scene's surroundings from the map expansion as one grey-scale PNG (walkway,
drivable area, crossings), one location's expansion in memory at a time; grey levels and the affine in
docs/datasets/nuscenes.md.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from rich.progress import Progress

from ..errors import DataError
from .base import warn

#: metres per pixel of the rasters (the resolution of the official nuScenes semantic maps)
M_PER_PX = 0.1
#: metres added around a scene's track positions, so that heading-aligned crops of agents near the edge stay on the
#: map: the model's default crop (156 x 257 pixels of 0.5 m, agent centred, see data/maps.py) reaches
#: sqrt(39^2 + 64.25^2) = 75.2 m from the agent at worst
MARGIN_M = 80.0
#: the largest raster side in pixels; larger scenes get a coarser resolution
MAX_SIDE_PX = 8192
#: map-expansion layers in painting order and their grey levels (0 is "none of them")
MAP_LAYERS: tuple[str, ...] = ("walkway", "drivable_area", "ped_crossing")
GREY_LEVELS: dict[str, int] = {"walkway": 85, "drivable_area": 170, "ped_crossing": 255}
#: what to do about a missing or unreadable map expansion
EXPANSION_HINT = "download nuScenes-map-expansion-v1.3 into DATAROOT/maps/expansion/"


@dataclass(frozen=True)
class RasterGrid:
    """A north-up pixel grid over a world box: column 0 / row 0 centred on (x_min, y_max)."""

    x_min: float
    y_max: float
    width_px: int
    height_px: int
    m_per_px: float

    @property
    def patch_center(self) -> tuple[float, float]:
        """The centre to give the devkit's ``get_map_mask`` so that its pixels land on this grid.

        The devkit maps x to the canvas coordinate ``(x - cx) / res + W / 2`` and fills the pixels whose centre
        (integer coordinate) lies inside a polygon, with row 0 at the southern edge; the raster is flipped to
        north up afterwards. Column i then sits at ``x_min + i res`` and (flipped) row j at ``y_max - j res``.
        """
        res = self.m_per_px
        return self.x_min + self.width_px * res / 2, self.y_max - (self.height_px / 2 - 1) * res

    def world_to_px(self) -> list[float]:
        """The affine [a, b, c, d, e, f]: px = a x + b y + c, py = d x + e y + f (pixel centres are integers)."""
        scale = 1.0 / self.m_per_px
        return [scale, 0.0, -self.x_min * scale, 0.0, -scale, self.y_max * scale]


def scene_grid(bounds: tuple[float, float, float, float], *, m_per_px: float = M_PER_PX,
               margin_m: float = MARGIN_M, max_side_px: int = MAX_SIDE_PX) -> RasterGrid:
    """The grid covering `bounds` (x_min, y_min, x_max, y_max in metres) plus the margin.

    The box is snapped outwards to whole pixels; when its longer side would need more than `max_side_px` pixels
    the resolution is coarsened just enough to fit.
    """
    x0, y0, x1, y1 = bounds
    x0, y0, x1, y1 = x0 - margin_m, y0 - margin_m, x1 + margin_m, y1 + margin_m
    resolution = max(m_per_px, max(x1 - x0, y1 - y0) / (max_side_px - 1))
    x_min = math.floor(x0 / resolution) * resolution
    y_max = math.ceil(y1 / resolution) * resolution
    width = min(max_side_px, int(math.ceil((x1 - x_min) / resolution)) + 1)
    height = min(max_side_px, int(math.ceil((y_max - y0) / resolution)) + 1)
    return RasterGrid(x_min=x_min, y_max=y_max, width_px=width, height_px=height, m_per_px=resolution)


def expansion_path(dataroot: Path, location: str) -> Path:
    """Where the map expansion of a location lives in an official release."""
    return dataroot / "maps" / "expansion" / f"{location}.json"


def load_expansion(map_class: Any, dataroot: Path, location: str) -> Any:
    """Load one location's map expansion with the devkit's NuScenesMap, errors naming the file.

    `map_class` is the devkit's ``NuScenesMap`` (passed in so this module imports without the devkit).
    """
    path = expansion_path(dataroot, location)
    try:
        return map_class(dataroot=str(dataroot), map_name=location)
    except json.JSONDecodeError as error:
        raise DataError(f"map expansion is not valid JSON ({error}); re-download it ({EXPANSION_HINT})",
                        path=path) from None
    except KeyError as error:
        raise DataError(f"map expansion does not load: layer or record {error} is missing ({EXPANSION_HINT})",
                        path=path) from None
    except Exception as error:  # the devkit raises AssertionError, OSError and bare Exception (outdated version)
        message = str(error).replace("\n", " ").strip() or type(error).__name__
        if "outdated map version" in message:
            message = "outdated map version (the devkit reads version 1.3 or later)"
        raise DataError(f"map expansion does not load: {message} ({EXPANSION_HINT})", path=path) from None


@dataclass(frozen=True)
class LayerIndex:
    """Bounding boxes of every record of the rasterised layers of one map, computed once per location.

    ``get_map_mask`` rebuilds and clips every polygon of a layer on each call, whatever the patch; handing it
    only the records whose box meets the patch gives the same raster (the others clip to nothing) at a fraction
    of the cost on city-sized maps.
    """

    records: dict[str, list[dict]]
    boxes: dict[str, np.ndarray]  # per layer (n, 4): x_min, y_min, x_max, y_max; NaN for empty polygons

    def near(self, layer: str, box: tuple[float, float, float, float]) -> list[dict]:
        """The records of `layer` whose bounding box meets `box` (x_min, y_min, x_max, y_max)."""
        bounds = self.boxes[layer]
        keep = ((bounds[:, 0] <= box[2]) & (bounds[:, 2] >= box[0])
                & (bounds[:, 1] <= box[3]) & (bounds[:, 3] >= box[1]))
        return [record for record, kept in zip(self.records[layer], keep) if kept]


def index_layers(nusc_map: Any) -> LayerIndex:
    """The :class:`LayerIndex` of a loaded NuScenesMap (one pass over its polygons through the devkit)."""
    records, boxes = {}, {}
    for layer in MAP_LAYERS:
        records[layer] = list(getattr(nusc_map, layer))
        layer_boxes = np.full((len(records[layer]), 4), np.nan)
        for row, record in enumerate(records[layer]):
            tokens = record["polygon_tokens"] if layer == "drivable_area" else [record["polygon_token"]]
            bounds = [nusc_map.extract_polygon(token).bounds for token in tokens]
            bounds = np.array([b for b in bounds if len(b) == 4 and all(math.isfinite(v) for v in b)])
            if len(bounds):
                layer_boxes[row] = (*bounds[:, :2].min(axis=0), *bounds[:, 2:].max(axis=0))
        boxes[layer] = layer_boxes
    return LayerIndex(records=records, boxes=boxes)


@contextlib.contextmanager
def _only_records_near(nusc_map: Any, index: LayerIndex | None, box: tuple[float, float, float, float]
                       ) -> Iterator[None]:
    """Temporarily narrow the map's rasterised layers to the records near `box` (no-op without an index)."""
    if index is None:
        yield
        return
    saved = {layer: getattr(nusc_map, layer) for layer in MAP_LAYERS}
    try:
        for layer in MAP_LAYERS:
            setattr(nusc_map, layer, index.near(layer, box))
        yield
    finally:
        for layer, layer_records in saved.items():
            setattr(nusc_map, layer, layer_records)


def rasterize(nusc_map: Any, grid: RasterGrid, path: Path | None = None, index: LayerIndex | None = None
              ) -> np.ndarray:
    """The grey-scale (height, width) uint8 raster of `grid`, north up, painted with :data:`GREY_LEVELS`.

    `index` (from :func:`index_layers`) makes the devkit look only at records near the grid; `path` (the
    expansion file) only serves error messages when the devkit fails on malformed geometry.
    """
    cx, cy = grid.patch_center
    height_m, width_m = grid.height_px * grid.m_per_px, grid.width_px * grid.m_per_px
    patch_box = (cx, cy, height_m, width_m)
    box = (cx - width_m / 2, cy - height_m / 2, cx + width_m / 2, cy + height_m / 2)
    grey = np.zeros((grid.height_px, grid.width_px), dtype=np.uint8)
    with _only_records_near(nusc_map, index, box):
        for layer in MAP_LAYERS:  # one layer at a time: a single canvas in memory besides the result
            try:
                mask = nusc_map.get_map_mask(patch_box, 0.0, layer_names=[layer],
                                             canvas_size=(grid.height_px, grid.width_px))[0]
            except (KeyError, ValueError, TypeError, AttributeError) as error:
                raise DataError(f"map expansion geometry of layer '{layer}' does not rasterise "
                                f"({type(error).__name__}: {error})", path=path) from None
            # the devkit's masks hold 0 / 1 (cv2.fillPoly with 1), so a zero-copy boolean view selects the layer
            np.copyto(grey, np.uint8(GREY_LEVELS[layer]), where=mask.astype(np.uint8, copy=False).view(np.bool_))
            del mask
    # the devkit's canvas has row 0 at the patch's southern edge; store north up like the official rasters
    return np.ascontiguousarray(grey[::-1])


#: zlib level of the PNGs: the rasters hold a few flat grey regions, so fast compression is nearly as small
PNG_COMPRESS_LEVEL = 3


def write_png(grey: np.ndarray, path: Path) -> None:
    """Write an 8-bit grey-scale PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(grey, mode="L").save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


@dataclass(frozen=True)
class MapRef:
    """What the scenes table records about one scene's raster."""

    path: str
    m_per_px: float
    world_to_px: list[float]


def rasterise_scene_maps(map_class: Any, dataroot: Path, locations: dict[str, str],
                         bounds: dict[str, tuple[float, float, float, float]], out_root: Path,
                         progress: Progress | None = None) -> dict[str, MapRef]:
    """Rasterise every scene whose location has a map expansion into ``out_root/maps/<scene_id>.png``.

    `locations` maps scene ids to map locations and `bounds` to the box of their track positions. One location's
    expansion is held in memory at a time. Locations without an expansion produce a warning (:func:`.base.warn`)
    and no map (the whole dataset has none when the expansion is absent).
    """
    by_location: dict[str, list[str]] = {}
    for scene_id, location in sorted(locations.items()):
        by_location.setdefault(location, []).append(scene_id)
    present = [loc for loc in sorted(by_location) if expansion_path(dataroot, loc).is_file()]
    expansion_dir = dataroot / "maps" / "expansion"
    if not present:
        warn(f"{expansion_dir}: map expansion not found; the dataset gets no maps ({EXPANSION_HINT} to rasterise "
             "drivable area, walkways and crossings)")
        return {}
    absent = [loc for loc in sorted(by_location) if loc not in present]
    if absent:
        count = sum(len(by_location[loc]) for loc in absent)
        warn(f"{expansion_dir}: no map expansion for {', '.join(absent)}; its {count} scene(s) get no map")
    task = progress.add_task("rasterising maps", total=sum(len(by_location[loc]) for loc in present)) \
        if progress is not None else None
    refs: dict[str, MapRef] = {}
    for location in present:
        nusc_map = load_expansion(map_class, dataroot, location)
        index = _index_or_fail(nusc_map, expansion_path(dataroot, location))
        for scene_id in by_location[location]:
            grid = scene_grid(bounds[scene_id])
            relative = f"maps/{scene_id}.png"
            write_png(rasterize(nusc_map, grid, expansion_path(dataroot, location), index), out_root / relative)
            refs[scene_id] = MapRef(path=relative, m_per_px=grid.m_per_px, world_to_px=grid.world_to_px())
            if progress is not None and task is not None:
                progress.advance(task)
        del nusc_map, index
    return refs


def _index_or_fail(nusc_map: Any, path: Path) -> LayerIndex:
    """:func:`index_layers`, with malformed records reported against the expansion file."""
    try:
        return index_layers(nusc_map)
    except (KeyError, ValueError, TypeError, AttributeError) as error:
        raise DataError(f"map expansion geometry does not load ({type(error).__name__}: {error}; "
                        f"{EXPANSION_HINT})", path=path) from None
