"""`trajflow augment forking` and `trajflow augment scale-rotate`: seeded scaling / rotation augmentation.

Both stages read a dataset, never modify it, and write a new one (atomically, with :class:`DatasetWriter`) that
holds the source dataset unchanged (scenes, tracks, samples: the "original" copy of every sample) plus
``copies - 1`` variants of each selected sample. A variant is a new scene, named
``<scene_id>~s<sample_id>~<kind><k>``, holding every agent of the source scene over the sample's window
(``t0 - n_past + 1 .. t0 + n_future``, the frames a prediction problem reads) with the transformation applied, and
one new sample pointing at it. All draws come from one seed (``numpy.random.SeedSequence(seed)``, one stream for
scales and one for angles, in sample-id order), so the same input and seed give byte-identical files. The work is
vectorised: one join builds the windows of all selected samples, one more expands them to all variants of a
chunk of output scenes, and polars expressions transform every row at once (the output is streamed in sorted
chunks of about a million rows).

``forking`` (the paper's augmented Forking Paths)
    For every sample (annotated future), the post-fork part of the target's trajectory (frames after ``t0``) is
    scaled by s ~ N(1, scale_std) and rotated by theta ~ N(0, rot_std_deg) about the fork point (the target's
    position at ``t0``), optionally truncated to ``scale_range`` / ``rot_range_deg`` (the reference
    implementation's truncated variant, by redrawing outside values: an exact truncated normal). The past and all
    context agents are untouched, so a variant has the same inputs as its original and keeps its ``group_id``,
    ``fold`` and ``split``: the variants are extra ground-truth futures of the same group (needed by the JSD).
    Requires a dataset with at least one group of several samples. Samples gain ``fork_copy`` (0 = original),
    ``fork_scale``, ``fork_rotation`` (rad) and ``fork_source_sample_id``.

``scale-rotate`` (generic training-time augmentation)
    Only samples whose ``split`` is among ``splits`` (default train) get variants. A variant rotates the whole
    window (all agents, past and future, headings and velocities) by theta about the target's last observed
    position: uniform in [-pi, pi) by default or N(0, rot_std_deg); with ``scale_std > 0`` it is also scaled by
    s ~ N(1, scale_std) (positions, velocities, lengths and widths). Map transforms are updated to match. A variant
    keeps the original's ``fold`` and ``split`` but gets a new ``group_id`` (its inputs differ from every other
    sample) and ``train_only = true``: it is training data only, never a test problem. Samples gain ``aug_copy``,
    ``aug_scale``, ``aug_rotation`` (rad), ``aug_source_sample_id`` and ``train_only``.

Lineage (manifest): the kind, the source dataset's fingerprint and lineage, every parameter and the seed.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from ..errors import DataError, UsageError
from ..schemas import Dataset, DatasetMeta, DatasetWriter, open_dataset
from ..schemas.tables import SPLITS
from ..util.bounds import check_seed
from ..util.progress import make_progress

#: output rows per chunk of scenes generated, sorted and handed to the writer at once
CHUNK_ROWS = 1_000_000
#: a truncation range must keep at least this fraction of the distribution (else redrawing would crawl)
MIN_ACCEPTANCE = 0.01


@dataclass(frozen=True)
class Kind:
    """What distinguishes the two augmentations: naming, which rows move, and group / split policy."""

    name: str  # "forking" or "scale-rotate"
    prefix: str  # column prefix and scene-name tag
    dataset_suffix: str
    whole_window: bool  # transform every agent over the whole window (else the target after t0 only)
    new_groups: bool  # variants get fresh group ids (their inputs differ)
    train_only: bool  # variants are training data only
    needs_groups: bool  # the source must hold groups of several futures of one input (multi-future data)


FORKING = Kind("forking", "fork", "forking_aug", whole_window=False, new_groups=False, train_only=False,
               needs_groups=True)
SCALE_ROTATE = Kind("scale-rotate", "aug", "scale_rotate", whole_window=True, new_groups=True, train_only=True,
                    needs_groups=False)


@dataclass(frozen=True)
class Draws:
    """Scale factors and rotation angles (radians) of every variant, shape (selected samples, copies - 1)."""

    scale: np.ndarray
    angle: np.ndarray


# --- random draws ----------------------------------------------------------------------------------------------

def _normal_cdf(z: float) -> float:
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def truncated_normal(rng: np.random.Generator, mean: float, std: float, shape: tuple[int, ...],
                     bounds: tuple[float, float] | None, what: str) -> np.ndarray:
    """N(mean, std) draws of `shape`, redrawn (vectorised) wherever they fall outside `bounds` (inclusive)."""
    if std < 0 or not math.isfinite(std):
        raise UsageError(f"{what}: the standard deviation must be >= 0, got {std}")
    values = rng.normal(mean, std, size=shape) if std > 0 else np.full(shape, float(mean))
    if bounds is None:
        return values
    lo, hi = (float(b) for b in bounds)
    if not lo <= hi:
        raise UsageError(f"{what}: range ({lo:g}, {hi:g}) is empty (the lower bound must not exceed the upper)")
    if std == 0:
        if not lo <= mean <= hi:
            raise UsageError(f"{what}: range ({lo:g}, {hi:g}) excludes the mean {mean:g} and the std is 0")
        return values
    acceptance = _normal_cdf((hi - mean) / std) - _normal_cdf((lo - mean) / std)
    if acceptance < MIN_ACCEPTANCE:
        raise UsageError(f"{what}: range ({lo:g}, {hi:g}) keeps only {acceptance:.2%} of N({mean:g}, {std:g}); "
                         f"widen it (at least {MIN_ACCEPTANCE:.0%} is needed)")
    outside = (values < lo) | (values > hi)
    while outside.any():
        values[outside] = rng.normal(mean, std, size=int(outside.sum()))
        outside = (values < lo) | (values > hi)
    return values


def _streams(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Independent generators for scales and angles, so truncating one never changes the other's draws."""
    scale_seq, angle_seq = np.random.SeedSequence(seed).spawn(2)
    return np.random.default_rng(scale_seq), np.random.default_rng(angle_seq)


def _check_scales(scale: np.ndarray) -> None:
    if scale.size and scale.min() <= 0:
        raise UsageError(f"a scale factor of {scale.min():.3g} was drawn; scales must be positive: lower the scale "
                         "std or give a scale range with a positive lower bound")


def draw_forking(n: int, copies: int, scale_std: float, rot_std_deg: float,
                 scale_range: tuple[float, float] | None, rot_range_deg: tuple[float, float] | None,
                 seed: int) -> Draws:
    """s ~ N(1, scale_std) and theta ~ N(0, rot_std_deg), each optionally truncated, for n x (copies - 1)."""
    scale_rng, angle_rng = _streams(seed)
    shape = (n, copies - 1)
    scale = truncated_normal(scale_rng, 1.0, scale_std, shape, scale_range, "scale")
    angle = truncated_normal(angle_rng, 0.0, rot_std_deg, shape, rot_range_deg, "rotation (degrees)")
    _check_scales(scale)
    return Draws(scale=scale, angle=np.deg2rad(angle))


def draw_scale_rotate(n: int, copies: int, rot_std_deg: float | None, scale_std: float, seed: int) -> Draws:
    """theta uniform in [-pi, pi) (rot_std_deg None) or N(0, rot_std_deg); s ~ N(1, scale_std) (1 when 0)."""
    scale_rng, angle_rng = _streams(seed)
    shape = (n, copies - 1)
    scale = truncated_normal(scale_rng, 1.0, scale_std, shape, None, "scale")
    if rot_std_deg is None:
        angle = angle_rng.uniform(-math.pi, math.pi, size=shape)
    else:
        angle = np.deg2rad(truncated_normal(angle_rng, 0.0, rot_std_deg, shape, None, "rotation (degrees)"))
    _check_scales(scale)
    return Draws(scale=scale, angle=angle)


# --- windows, variants, transformation -------------------------------------------------------------------------
# Working columns carry a "__" prefix so that they never collide with a dataset's own extra columns.
SAMPLE, SOURCE_SCENE, NEW_SCENE, VARIANT = "__sample", "__source_scene", "__new_scene", "__variant"
COPY, SCALE, ANGLE, CX, CY, MOVING, ROWS = "__copy", "__scale", "__angle", "__cx", "__cy", "__moving", "__rows"
POSITION = "__position"


def sample_windows(selected: pl.DataFrame, tracks: pl.DataFrame, path: Path) -> pl.DataFrame:
    """Every track row of each selected sample's scene inside its window, with the centre (target at t0).

    Columns: all track columns plus SAMPLE, CX, CY (the target's position at t0) and MOVING (target after t0);
    sorted by (SAMPLE, agent_id, frame).
    """
    keys = selected.select(pl.col("sample_id").alias(SAMPLE), "scene_id", pl.col("agent_id").alias("__target"),
                           pl.col("t0_frame").alias("__t0"), pl.col("n_past").alias("__past"),
                           pl.col("n_future").alias("__future"))
    centre = keys.join(tracks.select("scene_id", "agent_id", "frame", pl.col("x").alias(CX), pl.col("y").alias(CY)),
                       left_on=["scene_id", "__target", "__t0"], right_on=["scene_id", "agent_id", "frame"],
                       how="left")
    missing = centre.filter(pl.col(CX).is_null())
    if missing.height:
        first = missing.sort(SAMPLE).row(0, named=True)
        raise DataError(f"sample {first[SAMPLE]}: target {first['__target']} of scene '{first['scene_id']}' has no "
                        f"position at its t0_frame {first['__t0']}", path=path / "samples.parquet")
    frames = (keys.with_columns(frame=pl.int_ranges(pl.col("__t0") - pl.col("__past") + 1,
                                                    pl.col("__t0") + pl.col("__future") + 1))
              .explode("frame"))
    return (frames.join(tracks, on=["scene_id", "frame"], how="inner")
            .join(centre.select(SAMPLE, CX, CY), on=SAMPLE)
            .with_columns(((pl.col("agent_id") == pl.col("__target")) & (pl.col("frame") > pl.col("__t0")))
                          .alias(MOVING))
            .drop("__target", "__t0", "__past", "__future")
            .sort(SAMPLE, "agent_id", "frame"))


def variant_plan(selected: pl.DataFrame, draws: Draws, kind: Kind, copies: int) -> pl.DataFrame:
    """One row per (selected sample, copy k >= 1): new scene id, scale and angle, in (sample_id, k) order."""
    n = selected.height
    width = max(3, len(str(copies - 1)))
    plan = pl.DataFrame({
        SAMPLE: np.repeat(selected.get_column("sample_id").to_numpy(), copies - 1),
        SOURCE_SCENE: np.repeat(selected.get_column("scene_id").to_numpy(), copies - 1),
        COPY: np.tile(np.arange(1, copies, dtype=np.int64), n),
        SCALE: draws.scale.ravel(), ANGLE: draws.angle.ravel(),
    }, schema_overrides={SOURCE_SCENE: pl.String})
    return plan.with_columns(
        pl.format("{}~s{}~{}{}", SOURCE_SCENE, SAMPLE, pl.lit(kind.prefix),
                  pl.col(COPY).cast(pl.String).str.zfill(width)).alias(NEW_SCENE),
        pl.int_range(pl.len(), dtype=pl.Int64).alias(VARIANT))


def transform(rows: pl.DataFrame, kind: Kind) -> pl.DataFrame:
    """Apply p' = c + s R(theta) (p - c) to the moving rows (all rows, or the target after t0), vectorised.

    Headings turn by theta; velocities are rotated and scaled; for scale-rotate, lengths and widths scale too.
    """
    moving = pl.lit(True) if kind.whole_window else pl.col(MOVING)
    cos, sin, s = pl.col(ANGLE).cos(), pl.col(ANGLE).sin(), pl.col(SCALE)
    dx, dy = pl.col("x") - pl.col(CX), pl.col("y") - pl.col(CY)
    updates = {
        "x": pl.col(CX) + s * (cos * dx - sin * dy),
        "y": pl.col(CY) + s * (sin * dx + cos * dy),
    }
    if "heading" in rows.columns:
        turned = pl.col("heading") + pl.col(ANGLE)
        updates["heading"] = pl.arctan2(turned.sin(), turned.cos())
    if "vx" in rows.columns and "vy" in rows.columns:
        updates["vx"] = s * (cos * pl.col("vx") - sin * pl.col("vy"))
        updates["vy"] = s * (sin * pl.col("vx") + cos * pl.col("vy"))
    if kind.whole_window:
        for size in ("length", "width"):
            if size in rows.columns:
                updates[size] = pl.col(size) * s
    return rows.with_columns(*[pl.when(moving).then(value).otherwise(pl.col(name)).alias(name)
                               for name, value in updates.items()])


# --- tables of the output --------------------------------------------------------------------------------------

def _new_ids(count: int, existing: pl.Series) -> pl.Series:
    """`count` fresh ids after the largest existing one."""
    start = int(existing.max()) + 1 if existing.drop_nulls().len() else 0  # type: ignore[arg-type]
    return pl.Series(np.arange(start, start + count, dtype=np.int64))


def output_samples(samples: pl.DataFrame, plan: pl.DataFrame, kind: Kind) -> pl.DataFrame:
    """The source samples (copy 0) followed by one sample per variant, with the kind's augmentation columns."""
    p = kind.prefix
    originals = samples.with_columns(
        pl.lit(0, dtype=pl.Int64).alias(f"{p}_copy"), pl.lit(1.0).alias(f"{p}_scale"),
        pl.lit(0.0).alias(f"{p}_rotation"), pl.col("sample_id").alias(f"{p}_source_sample_id"))
    if kind.train_only:
        originals = originals.with_columns(train_only=pl.lit(False))
    fresh = {"sample_id": _new_ids(plan.height, samples.get_column("sample_id"))}
    if kind.new_groups:
        fresh["group_id"] = _new_ids(plan.height, samples.get_column("group_id"))
    if "joint_id" in samples.columns:  # a variant is alone in its scene, so it is its own joint problem
        fresh["joint_id"] = _new_ids(plan.height, samples.get_column("joint_id"))
    variants = (plan.select(SAMPLE, COPY, SCALE, ANGLE, NEW_SCENE)
                .join(samples.rename({"sample_id": SAMPLE}), on=SAMPLE, how="left", maintain_order="left")
                .with_columns(pl.col(SAMPLE).alias(f"{p}_source_sample_id"), pl.col(COPY).alias(f"{p}_copy"),
                              pl.col(SCALE).alias(f"{p}_scale"), pl.col(ANGLE).alias(f"{p}_rotation"),
                              pl.col(NEW_SCENE).alias("scene_id"),
                              *[series.alias(name) for name, series in fresh.items()]))
    if kind.train_only:
        variants = variants.with_columns(train_only=pl.lit(True))
    return pl.concat([originals, variants.select(originals.columns)], how="vertical")


def _moved_maps(rows: pl.DataFrame) -> pl.DataFrame:
    """World-to-pixel affines composed with the inverse augmentation, so maps stay aligned with the agents."""
    affine = rows.get_column("map_world_to_px")
    has = affine.is_not_null().to_numpy()
    if not has.any():
        return rows
    a = np.array([v if v is not None else [np.nan] * 6 for v in affine.to_list()], dtype=np.float64)
    s, th = rows.get_column(SCALE).to_numpy(), rows.get_column(ANGLE).to_numpy()
    cx, cy = rows.get_column(CX).to_numpy(), rows.get_column(CY).to_numpy()
    # inverse augmentation: p = c + M (p' - c) with M = R(-theta) / s
    m00, m01, m10, m11 = np.cos(th) / s, np.sin(th) / s, -np.sin(th) / s, np.cos(th) / s
    tx, ty = cx - m00 * cx - m01 * cy, cy - m10 * cx - m11 * cy
    new = np.stack([a[:, 0] * m00 + a[:, 1] * m10, a[:, 0] * m01 + a[:, 1] * m11,
                    a[:, 0] * tx + a[:, 1] * ty + a[:, 2],
                    a[:, 3] * m00 + a[:, 4] * m10, a[:, 3] * m01 + a[:, 4] * m11,
                    a[:, 3] * tx + a[:, 4] * ty + a[:, 5]], axis=1)
    values = [row.tolist() if ok else None for row, ok in zip(new, has)]
    updated = rows.with_columns(pl.Series("map_world_to_px", values, dtype=pl.List(pl.Float64)))
    if "map_m_per_px" in rows.columns:
        updated = updated.with_columns(pl.col("map_m_per_px") * pl.col(SCALE))
    return updated


def output_scenes(scenes: pl.DataFrame, plan: pl.DataFrame, centres: pl.DataFrame, kind: Kind,
                  dataset: str) -> pl.DataFrame:
    """The source scenes followed by one scene per variant (a copy of its source scene's row)."""
    variants = (plan.select(SOURCE_SCENE, NEW_SCENE, SAMPLE, SCALE, ANGLE)
                .join(scenes.rename({"scene_id": SOURCE_SCENE}), on=SOURCE_SCENE, how="left", maintain_order="left"))
    if kind.whole_window and "map_world_to_px" in scenes.columns:
        variants = _moved_maps(variants.join(centres, on=SAMPLE, how="left", maintain_order="left"))
    variants = variants.with_columns(pl.col(NEW_SCENE).alias("scene_id"))
    return (pl.concat([scenes, variants.select(scenes.columns)], how="vertical")
            .with_columns(pl.lit(dataset).alias("dataset")))


def _copy_maps(ds: Dataset, scenes: pl.DataFrame, root: Path) -> None:
    """Copy the raster maps the scenes reference (paths relative to the dataset) into the new dataset."""
    if "map_path" not in scenes.columns:
        return
    for relative in scenes.get_column("map_path").drop_nulls().unique().sort().to_list():
        source, target = ds.map_file(relative), root / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)


# --- the shared driver -----------------------------------------------------------------------------------------

def scene_chunks(tracks: pl.DataFrame, scenes: pl.DataFrame, plan: pl.DataFrame,
                 windows: pl.DataFrame) -> list[pl.DataFrame]:
    """All output scenes in sorted scene_id order (VARIANT null for a source scene), cut into chunks of rows.

    Writing the chunks in this order keeps every tracks shard sorted by scene, however the writer groups them.
    """
    original_rows = tracks.group_by("scene_id").len(ROWS)
    window_rows = windows.group_by(SAMPLE).len(ROWS)
    originals = (scenes.select("scene_id").join(original_rows, on="scene_id", how="left")
                 .select("scene_id", pl.lit(None, dtype=pl.Int64).alias(VARIANT), pl.col(ROWS).fill_null(0)))
    variants = (plan.join(window_rows, on=SAMPLE, how="left")
                .select(pl.col(NEW_SCENE).alias("scene_id"), VARIANT, pl.col(ROWS).fill_null(0)))
    order = pl.concat([originals, variants], how="vertical_relaxed").sort("scene_id")
    order = order.with_columns((pl.col(ROWS).cum_sum() // CHUNK_ROWS).alias("__chunk"))
    return order.partition_by("__chunk", maintain_order=True, include_key=False)


def _chunk_tracks(chunk: pl.DataFrame, tracks: pl.DataFrame, plan: pl.DataFrame, windows: pl.DataFrame,
                  kind: Kind) -> pl.DataFrame:
    """The tracks of one chunk of output scenes: source scenes as they are, variants transformed; sorted.

    Source scenes are sorted already and `windows` is sorted by (sample, agent, frame), so a stable sort on the
    scene's position in the chunk (an integer) puts every row in place without comparing strings.
    """
    chunk = chunk.with_row_index(POSITION)
    originals = tracks.join(chunk.filter(pl.col(VARIANT).is_null()).select("scene_id", POSITION), on="scene_id",
                            maintain_order="left")
    wanted = chunk.filter(pl.col(VARIANT).is_not_null()).select(POSITION, VARIANT).join(
        plan.select(VARIANT, SAMPLE, SCALE, ANGLE, NEW_SCENE), on=VARIANT, maintain_order="left")
    moved = (transform(wanted.join(windows, on=SAMPLE, maintain_order="left_right"), kind)
             .with_columns(pl.col(NEW_SCENE).alias("scene_id")))
    columns = [*tracks.columns, POSITION]
    return (pl.concat([originals.select(columns), moved.select(columns)])
            .sort(POSITION, maintain_order=True)
            .drop(POSITION))


def _augment(data: str | Path, out: str | Path, kind: Kind, select: Any, draw: Any, parameters: dict[str, Any],
             copies: int, seed: int, overwrite: bool, quiet: bool) -> Path:
    """Read, draw, transform and write; `select(ds, samples)` picks the samples, `draw(n)` their draws."""
    if copies < 2:
        raise UsageError(f"--copies counts the original too, so it must be at least 2, got {copies}")
    check_seed(seed, "--seed")
    ds = open_dataset(data)
    out = Path(out)
    if out.resolve() == ds.path.resolve():
        raise UsageError("the output must be a new directory: augmentation never modifies its input dataset")
    samples, scenes = ds.samples(), ds.scenes()
    if f"{kind.prefix}_copy" in samples.columns:
        raise UsageError(f"{ds.path}: dataset '{ds.meta.dataset}' was already augmented with `augment {kind.name}` "
                         f"(samples.{kind.prefix}_copy exists); augment its source dataset instead")
    selected = select(ds, samples).sort("sample_id")
    draws: Draws = draw(selected.height)
    tracks = ds.tracks()
    windows = sample_windows(selected, tracks, ds.path)
    plan = variant_plan(selected, draws, kind, copies)
    dataset = f"{ds.meta.dataset}_{kind.dataset_suffix}"
    centres = windows.select(SAMPLE, CX, CY).unique(SAMPLE)
    new_scenes = output_scenes(scenes, plan, centres, kind, dataset)
    new_samples = output_samples(samples, plan, kind)
    chunks = scene_chunks(tracks, scenes, plan, windows)
    meta = DatasetMeta(dataset=dataset, dt=ds.meta.dt, protocol=ds.meta.protocol)
    lineage = {"augmentation": kind.name, "source": ds.fingerprint(), "source_lineage": ds.lineage,
               "parameters": {**parameters, "copies": copies, "seed": seed},
               "augmented_samples": selected.height, "new_samples": plan.height}
    with make_progress(quiet) as progress, DatasetWriter(out, meta, overwrite=overwrite) as writer:
        task = progress.add_task(f"augment {kind.name}: {new_scenes.height} scenes", total=len(chunks))
        for chunk in chunks:
            writer.add_tracks(_chunk_tracks(chunk, tracks, plan, windows, kind))
            progress.advance(task)
        _copy_maps(ds, new_scenes, writer.root)
        writer.finish(new_scenes, new_samples, lineage=lineage)
    return out


def _range(value: tuple[float, float] | None) -> list[float] | None:
    return None if value is None else [float(value[0]), float(value[1])]


def augment_forking(data: str | Path, out: str | Path, *, copies: int = 100, scale_std: float = 0.03,
                    rot_std_deg: float = 1.0, scale_range: tuple[float, float] | None = None,
                    rot_range_deg: tuple[float, float] | None = None, seed: int = 0, overwrite: bool = False,
                    quiet: bool = False) -> Path:
    """The paper's augmented Forking Paths: every annotated future plus copies - 1 scaled / rotated variants.

    Variants scale and rotate the target's trajectory after t0 (the fork) about its position at t0 and keep the
    original's group, fold and split. Returns `out`.
    """
    def select(ds: Dataset, samples: pl.DataFrame) -> pl.DataFrame:
        if samples.height == 0 or samples.get_column("group_id").value_counts().get_column("count").max() < 2:
            raise DataError(f"dataset '{ds.meta.dataset}' has no group with more than one sample (no multi-future "
                            "data); `augment forking` needs groups of annotated futures, e.g. from "
                            "`ingest forking-paths`; use `augment scale-rotate` for other datasets", path=ds.path)
        return samples

    parameters = {"scale_std": scale_std, "rot_std_deg": rot_std_deg, "scale_range": _range(scale_range),
                  "rot_range_deg": _range(rot_range_deg)}
    return _augment(data, out, FORKING, select,
                    lambda n: draw_forking(n, copies, scale_std, rot_std_deg, scale_range, rot_range_deg, seed),
                    parameters, copies, seed, overwrite, quiet)


def augment_scale_rotate(data: str | Path, out: str | Path, *, copies: int = 10, rot_std_deg: float | None = None,
                         scale_std: float = 0.0, splits: tuple[str, ...] = ("train",), seed: int = 0,
                         overwrite: bool = False, quiet: bool = False) -> Path:
    """Training-time augmentation of any dataset: copies - 1 rotated (and optionally scaled) variants per sample.

    Only samples whose split is in `splits` get variants; variants are marked `train_only`. Returns `out`.
    """
    unknown = [split for split in splits if split not in SPLITS]
    if unknown or not splits:
        raise UsageError(f"--split must name one or more of {', '.join(SPLITS)}, got {', '.join(splits) or 'none'}")

    def select(ds: Dataset, samples: pl.DataFrame) -> pl.DataFrame:
        chosen = samples.filter(pl.col("split").is_in(list(splits)))
        if chosen.height == 0:
            raise DataError(f"dataset '{ds.meta.dataset}' has no samples whose split is {' or '.join(splits)}",
                            path=ds.path / "samples.parquet")
        return chosen

    parameters = {"rot_std_deg": rot_std_deg, "rotation": "uniform" if rot_std_deg is None else "normal",
                  "scale_std": scale_std, "splits": list(splits)}
    return _augment(data, out, SCALE_ROTATE, select,
                    lambda n: draw_scale_rotate(n, copies, rot_std_deg, scale_std, seed),
                    parameters, copies, seed, overwrite, quiet)


#: the augmentations by the name `trajflow augment` and an experiment config's ``[[augment]] kind`` use
AUGMENTATIONS = {FORKING.name: (FORKING, augment_forking), SCALE_ROTATE.name: (SCALE_ROTATE, augment_scale_rotate)}
