"""Map rasters of a dataset and heading-aligned grey-scale crops for the model's CNN.

A dataset with maps stores grey-scale PNGs under ``DATA/maps/``; each scene row names its raster
(``map_path``, relative to the dataset), the raster's metres per pixel (``map_m_per_px``) and the world -> pixel
affine ``map_world_to_px`` = [a, b, c, d, e, f] with ``px = a x + b y + c`` (column) and ``py = d x + e y + f``
(row). Pixel coordinates are continuous with integer values at pixel *centres* (pixel (0, 0) covers [-0.5, 0.5]^2;
the levelX / matplotlib ``imshow`` convention).

Crop convention (:func:`heading_aligned_crops`): a crop is ``height`` x ``width`` pixels of
``metres_per_pixel_out`` metres in the agent's frame -- the frame the models normalise to (origin at the agent,
x along its heading, y to its left):

* the heading points to the **right** (increasing column), the agent's left points **up** (decreasing row), so a
  crop with heading 0 shows the map the usual way round (north up when world y is north);
* the agent sits on the middle row, ``ahead_fraction`` of the width ahead of it (0.5, the default, centres the
  crop on the agent as the authors' framework does; at the default 0.5 m per pixel a 156 x 257 crop spans
  78 m x 128.5 m);
* values are bilinear samples of the raster in [0, 1]; everything outside the raster is 0.

Rasters coarser than the crop's resolution are sampled directly; finer rasters are first reduced to the crop's
resolution (Lanczos, as the reference implementation does) so that point sampling does not alias.

Storage: a float32 crop costs 160 KB (1.6 GB per 10k problems), so the loader keeps crops as uint8
(``dtype=np.uint8``: round(255 v), 40 KB each) and the model's CNN divides by 255 on the device -- the same
scaling as the rasters' own grey levels (v = level / 255). A crop whose pixels fall on raster pixel centres is
exact; an interpolated one is rounded to the nearest of the raster's 256 levels (at most 0.5 / 255 off).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import polars as pl
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

from ..errors import DataError
from ..schemas import Dataset, open_dataset

DEFAULT_HEIGHT, DEFAULT_WIDTH = 156, 257
#: metres per crop pixel (the authors' framework resamples rounD backgrounds to 0.5 m per pixel)
DEFAULT_METRES_PER_PIXEL = 0.5
#: share of the crop width that lies ahead of the agent (0.5: the agent is at the centre)
DEFAULT_AHEAD_FRACTION = 0.5
#: crops are computed in chunks of this many problems, bounding the sampling grid's memory (~40 MB)
CHUNK = 128
#: a raster finer than the crop by more than this factor is reduced before sampling
REDUCE_ABOVE = 1.5


@dataclass(frozen=True)
class MapRaster:
    """A grey-scale raster (H, W) float32 in [0, 1] with its resolution and world -> pixel affine."""

    image: np.ndarray
    m_per_px: float
    world_to_px: tuple[float, float, float, float, float, float]

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """World points (..., 2) -> pixel coordinates (..., 2) as (column, row)."""
        return world_to_pixels(xy, self.world_to_px)

    def reduced(self, m_per_px: float) -> "MapRaster":
        """The raster resampled (Lanczos) to about `m_per_px` metres per pixel, with the affine adjusted."""
        image, affine, metres = _resize(Image.fromarray(self.image, mode="F"), self.world_to_px, self.m_per_px,
                                        m_per_px)
        return MapRaster(np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0), metres, affine)


def _resize(image: Image.Image, world_to_px: tuple[float, ...], m_per_px: float,
            target_m_per_px: float) -> tuple[Image.Image, tuple[float, ...], float]:
    """Resample an image (Lanczos) from `m_per_px` to about `target_m_per_px`; the affine and resolution follow."""
    factor = m_per_px / target_m_per_px
    width, height = image.size
    new_width, new_height = max(2, round(width * factor)), max(2, round(height * factor))
    resized = image.resize((new_width, new_height), Image.Resampling.LANCZOS)
    sx, sy = new_width / width, new_height / height
    a, b, c, d, e, f = world_to_px
    # pixel centres: new = (old + 0.5) * scale - 0.5
    affine = (a * sx, b * sx, (c + 0.5) * sx - 0.5, d * sy, e * sy, (f + 0.5) * sy - 0.5)
    return resized, affine, m_per_px / math.sqrt(sx * sy)


def world_to_pixels(xy: np.ndarray, world_to_px: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """Apply the affine [a, b, c, d, e, f] to world points (..., 2): (a x + b y + c, d x + e y + f)."""
    a, b, c, d, e, f = (float(v) for v in world_to_px)
    xy = np.asarray(xy, dtype=np.float64)
    return np.stack((a * xy[..., 0] + b * xy[..., 1] + c, d * xy[..., 0] + e * xy[..., 1] + f), axis=-1)


def read_map(path: str | Path, m_per_px: float, world_to_px: tuple[float, ...] | list[float], *,
             coarsest_m_per_px: float | None = None) -> MapRaster:
    """Load a map PNG (any mode; converted to grey-scale) as a MapRaster; errors name the file.

    With `coarsest_m_per_px`, a raster finer than that by more than REDUCE_ABOVE is reduced to it (in 8 bits,
    before the float copy, which keeps large rasters cheap).
    """
    path = Path(path)
    if len(world_to_px) != 6 or not all(math.isfinite(float(v)) for v in world_to_px):
        raise DataError(f"map_world_to_px must be 6 finite numbers, got {list(world_to_px)}", path=path)
    affine: tuple[float, ...] = tuple(float(v) for v in world_to_px)
    metres = float(m_per_px)
    try:
        with Image.open(path) as image:
            grey = image.convert("L")
    except FileNotFoundError:
        raise DataError("map raster not found", path=path) from None
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as error:
        raise DataError(f"cannot open map raster ({error})", path=path) from None
    if coarsest_m_per_px is not None and coarsest_m_per_px > REDUCE_ABOVE * metres:
        grey, affine, metres = _resize(grey, affine, metres, coarsest_m_per_px)
    return MapRaster(np.asarray(grey, dtype=np.float32) / 255.0, metres, affine)  # type: ignore[arg-type]


def crop_offsets(height: int, width: int, metres_per_pixel: float, ahead_fraction: float) -> np.ndarray:
    """(height, width, 2) positions of the crop's pixel centres in the agent frame (x ahead, y left), metres."""
    if not 0.0 <= ahead_fraction <= 1.0:
        raise ValueError(f"ahead_fraction must lie in [0, 1], got {ahead_fraction}")
    if metres_per_pixel <= 0:
        raise ValueError(f"metres_per_pixel_out must be positive, got {metres_per_pixel}")
    col0 = (1.0 - ahead_fraction) * (width - 1)
    row0 = (height - 1) / 2.0
    rows, cols = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return np.stack(((cols - col0) * metres_per_pixel, (row0 - rows) * metres_per_pixel), axis=-1)


def heading_aligned_crops(raster: np.ndarray, world_to_px: tuple[float, ...] | np.ndarray, positions: np.ndarray,
                          headings: np.ndarray, *, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH,
                          metres_per_pixel_out: float = DEFAULT_METRES_PER_PIXEL,
                          ahead_fraction: float = DEFAULT_AHEAD_FRACTION,
                          dtype: npt.DTypeLike = np.float32) -> np.ndarray:
    """Crops (B, 1, height, width) float32 in [0, 1] of one raster around B agents, rotated to their headings
    (``dtype=np.uint8``: the same crops as grey levels round(255 v), a quarter of the memory; see module doc).

    raster: (H, W) grey values (uint8 0..255 or floats in [0, 1]); world_to_px: its affine [a..f];
    positions: (B, 2) world metres; headings: (B,) radians (0 = world +x, counter-clockwise). See the module
    docstring for the orientation; samples outside the raster are 0. Bilinear sampling (torch grid_sample).
    """
    image = np.asarray(raster)
    if image.ndim != 2 or min(image.shape) < 2:
        raise ValueError(f"raster must be (H, W) with H, W >= 2, got shape {image.shape}")
    values = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else image.astype(np.float32)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    headings = np.asarray(headings, dtype=np.float64).reshape(-1)
    if len(positions) != len(headings):
        raise ValueError(f"{len(positions)} positions but {len(headings)} headings")
    # pixel = A (p + R(heading) o) + c for crop offsets o; folded with the [-1, 1] normalisation of grid_sample
    # into one 2x2 matrix and one shift per problem: per pixel, two float32 multiply-adds per coordinate.
    a, b, c, d, e, f = (float(v) for v in world_to_px)
    norm = np.diag([2.0 / (values.shape[1] - 1), 2.0 / (values.shape[0] - 1)])
    affine = norm @ np.array([[a, b], [d, e]])
    cos, sin = np.cos(headings), np.sin(headings)
    rotation = np.stack((np.stack((cos, -sin), -1), np.stack((sin, cos), -1)), axis=-2)     # (B, 2, 2)
    matrices = (affine @ rotation).astype(np.float32)                                          # (B, 2, 2)
    shifts = (positions @ affine.T + norm @ np.array([c, f]) - 1.0).astype(np.float32)       # (B, 2)
    offsets = crop_offsets(height, width, metres_per_pixel_out, ahead_fraction).reshape(-1, 2).astype(np.float32)
    out = np.zeros((len(positions), 1, height, width), dtype=_crop_dtype(dtype))
    source = torch.from_numpy(np.ascontiguousarray(values))[None, None]                      # (1, 1, H, W)
    # one preallocated grid buffer, filled in place: fresh multi-MB buffers per chunk cost more than the maths
    buffer = np.empty((min(CHUNK, len(positions)), height * width, 2), dtype=np.float32)
    scratch = np.empty(buffer.shape[:2], dtype=np.float32)
    with torch.no_grad():
        for start in range(0, len(positions), CHUNK):
            stop = min(start + CHUNK, len(positions))
            grid = buffer[:stop - start]
            for axis in (0, 1):
                target = grid[..., axis]
                np.multiply(offsets[None, :, 0], matrices[start:stop, axis, 0, None], out=target)
                np.multiply(offsets[None, :, 1], matrices[start:stop, axis, 1, None], out=scratch[:stop - start])
                target += scratch[:stop - start]
                target += shifts[start:stop, axis, None]
            sampled = F.grid_sample(source, torch.from_numpy(grid).reshape(1, -1, width, 2), mode="bilinear",
                                    padding_mode="zeros", align_corners=True)
            out[start:stop, 0] = _store(sampled.reshape(stop - start, height, width).numpy(), out.dtype)
    return out if out.dtype == np.uint8 else np.clip(out, 0.0, 1.0, out=out)


def _crop_dtype(dtype: npt.DTypeLike) -> np.dtype:
    """float32 or uint8, the two storage types of crops (ValueError for anything else)."""
    kind = np.dtype(dtype)
    if kind not in (np.dtype(np.float32), np.dtype(np.uint8)):
        raise ValueError(f"crops are float32 or uint8, not {kind}")
    return kind


def _store(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Sampled values in [0, 1] as the crop dtype: unchanged for float32, grey levels round(255 v) for uint8."""
    if dtype != np.uint8:
        return values
    return np.rint(np.clip(values, 0.0, 1.0) * np.float32(255.0)).astype(np.uint8)


@functools.lru_cache(maxsize=16)
def _prepared_map(path: str, mtime_ns: int, m_per_px: float, world_to_px: tuple[float, ...],
                  metres_per_pixel_out: float) -> MapRaster:
    """A map raster read once per (file version, crop resolution) and reduced when much finer than the crops."""
    del mtime_ns  # part of the cache key only: a rewritten file is read again
    return read_map(path, m_per_px, world_to_px, coarsest_m_per_px=metres_per_pixel_out)


def scene_maps(dataset: str | Path | Dataset) -> pl.DataFrame:
    """scene_id, map_path, map_m_per_px, map_world_to_px of the scenes that have a map (empty when none do)."""
    scenes = (dataset if isinstance(dataset, Dataset) else open_dataset(dataset)).scenes()
    columns = ("scene_id", "map_path", "map_m_per_px", "map_world_to_px")
    if any(name not in scenes.columns for name in columns[1:]):
        return pl.DataFrame(schema={"scene_id": pl.String, "map_path": pl.String, "map_m_per_px": pl.Float64,
                                    "map_world_to_px": pl.List(pl.Float64)})
    return scenes.select(columns).filter(pl.col("map_path").is_not_null())


def crops_for_problems(dataset_dir: str | Path, scene_id: np.ndarray | list[str], position: np.ndarray,
                       heading: np.ndarray, *, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH,
                       metres_per_pixel_out: float = DEFAULT_METRES_PER_PIXEL,
                       ahead_fraction: float = DEFAULT_AHEAD_FRACTION,
                       dtype: npt.DTypeLike = np.float32) -> np.ndarray:
    """Heading-aligned crops (B, 1, height, width) for B problems of a dataset, grouped by scene map: float32 in
    [0, 1], or with ``dtype=np.uint8`` grey levels round(255 v) (what the loader stores; see the module doc).

    scene_id: (B,) scene of each problem; position: (B, 2) world position of the target at t0; heading: (B,)
    radians. Problems whose scene has no map get an all-zero crop. Each map file is read once per process.
    """
    dataset_dir = Path(dataset_dir)
    scene_id = np.asarray(scene_id).astype(str)
    position = np.asarray(position, dtype=np.float64).reshape(-1, 2)
    heading = np.asarray(heading, dtype=np.float64).reshape(-1)
    if not len(scene_id) == len(position) == len(heading):
        raise ValueError(f"scene_id, position and heading differ in length: {len(scene_id)}, {len(position)}, "
                         f"{len(heading)}")
    out = np.zeros((len(scene_id), 1, height, width), dtype=_crop_dtype(dtype))
    dataset = open_dataset(dataset_dir)
    for scene, map_path, m_per_px, affine in scene_maps(dataset).iter_rows():
        index = np.flatnonzero(scene_id == scene)
        if len(index) == 0:
            continue
        path = dataset.map_file(map_path, scene)
        raster = _prepared_map(str(path.resolve()), path.stat().st_mtime_ns, float(m_per_px),
                               tuple(float(v) for v in affine), float(metres_per_pixel_out))
        out[index] = heading_aligned_crops(raster.image, raster.world_to_px, position[index], heading[index],
                                           height=height, width=width, metres_per_pixel_out=metres_per_pixel_out,
                                           ahead_fraction=ahead_fraction, dtype=out.dtype)
    return out


def past_headings(past: np.ndarray) -> np.ndarray:
    """Heading (B,) radians of each problem's last past step, exactly as the models normalise (see
    :func:`trajflow_pipeline.model.normalize.heading`: the latest step longer than 0.1 mm, +x if none)."""
    from ..model.normalize import heading

    cos, sin = heading(torch.from_numpy(np.array(past, dtype=np.float64)))
    return np.arctan2(sin.numpy(), cos.numpy())
