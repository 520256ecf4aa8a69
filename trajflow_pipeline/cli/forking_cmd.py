"""Typer commands for `ingest forking-paths`, `augment forking` and `augment scale-rotate`.

Plain functions with Typer-annotated parameters; `cli/app.py` registers them. They only parse options and call
the stages inside :func:`user_errors`, so every problem ends as one line and an exit code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import UsageError
from .common import Overwrite, Quiet, user_errors

OutDir = Annotated[Path, typer.Option("--out", "-o", help="Dataset directory to write (created atomically).")]
DataDir = Annotated[Path, typer.Argument(help="A dataset directory written by `trajflow ingest` (never modified).")]
Seed = Annotated[int, typer.Option(help="Random seed; the same seed gives byte-identical files.")]


def parse_per_scene(option: str, text: Optional[str]) -> float | dict[str, float] | None:
    """`30` (every scene) or `zara01=25,0400=30` (per scene; others keep their default) -> float, dict or None."""
    if text is None or not text.strip():
        return None
    try:
        if "=" not in text:
            return float(text)
        values: dict[str, float] = {}
        for item in text.split(","):
            scene, sep, value = item.partition("=")
            if not sep or not scene.strip():
                raise ValueError(item)
            values[scene.strip()] = float(value)
        return values
    except ValueError:
        raise UsageError(f"{option}: expected a number or scene=number pairs separated by commas, got {text!r}") \
            from None


def ingest_forking_paths_command(
    raw: Annotated[Path, typer.Argument(help="The Forking Paths release root, its next_x_v1_dataset/ folder or "
                                             "the bbox/ folder of <scene>_<moment>_<xagent>_<dest>_<annotator>_<cam>"
                                             ".json files.")],
    out: OutDir,
    camera: Annotated[str, typer.Option(help="Camera whose files are read (cam4 is the top-down view).")] = "cam4",
    fps: Annotated[Optional[str], typer.Option(
        help="Frame rate: one number for all scenes or scene=fps pairs (default 25 for zara/eth/hotel, 30 "
             "otherwise).")] = None,
    scale: Annotated[Optional[str], typer.Option(
        help="Metres per pixel: one number or scene=value pairs (defaults exist for cam4, derived from the "
             "release's camera set-up).")] = None,
    folds: Annotated[int, typer.Option(help="Cross-validation folds (whole groups per fold).")] = 5,
    seed: Annotated[int, typer.Option(help="Seed of the fold and train/val assignment.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Forking Paths: several annotated futures per past, 8 past + 12 future steps at 0.4 s, 5-fold CV."""
    from ..ingest.registry import get_ingest

    with user_errors():
        adapter = get_ingest("forking-paths")
        result = adapter.run(raw, out, camera=camera, fps=parse_per_scene("--fps", fps),
                             scale=parse_per_scene("--scale", scale), folds=folds, seed=seed, overwrite=overwrite,
                             quiet=quiet)
        adapter.report(result, quiet)


def augment_forking_command(
    data: DataDir,
    out: OutDir,
    copies: Annotated[int, typer.Option(help="Versions per annotated future, the original included.")] = 100,
    scale_std: Annotated[float, typer.Option(help="Std of the scale factor s ~ N(1, std).")] = 0.03,
    rot_std_deg: Annotated[float, typer.Option(help="Std of the rotation theta ~ N(0, std), in degrees.")] = 1.0,
    scale_range: Annotated[Optional[tuple[float, float]], typer.Option(
        help="Truncate s to LO HI (e.g. 0.9 1.1).")] = None,
    rot_range_deg: Annotated[Optional[tuple[float, float]], typer.Option(
        help="Truncate theta to LO HI degrees (e.g. -2.5 2.5).")] = None,
    seed: Seed = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Augmented Forking Paths: each future plus scaled / rotated variants of its post-fork part (same group)."""
    from ..ingest.base import report_written
    from ..stages.augment import augment_forking

    with user_errors():
        result = augment_forking(data, out, copies=copies, scale_std=scale_std, rot_std_deg=rot_std_deg,
                                 scale_range=scale_range, rot_range_deg=rot_range_deg, seed=seed,
                                 overwrite=overwrite, quiet=quiet)
        report_written(result, quiet)


def augment_scale_rotate_command(
    data: DataDir,
    out: OutDir,
    copies: Annotated[int, typer.Option(help="Versions per selected sample, the original included.")] = 10,
    rot_std_deg: Annotated[Optional[float], typer.Option(
        help="Std of the rotation theta ~ N(0, std) in degrees (default: uniform over the full circle).")] = None,
    scale_std: Annotated[float, typer.Option(help="Std of the scene scale s ~ N(1, std); 0 = no scaling.")] = 0.0,
    split: Annotated[Optional[list[str]], typer.Option(
        "--split", help="Split whose samples get variants (repeatable; default train).")] = None,
    seed: Seed = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Training-time augmentation of any dataset: rotated (and scaled) copies of the training samples.

    Variants are marked train_only; evaluate on the source dataset.
    """
    from ..ingest.base import report_written
    from ..stages.augment import augment_scale_rotate

    with user_errors():
        result = augment_scale_rotate(data, out, copies=copies, rot_std_deg=rot_std_deg, scale_std=scale_std,
                                      splits=tuple(split) if split else ("train",), seed=seed,
                                      overwrite=overwrite, quiet=quiet)
        report_written(result, quiet)
