"""`trajflow augment ...`: derived datasets (scaled / rotated copies), options parsed and the stage called inside
:func:`user_errors`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import OutDir, Overwrite, Quiet, user_errors

augment_app = typer.Typer(help="Scaling / rotation augmentation into a new dataset.", no_args_is_help=True)
DataDir = Annotated[Path, typer.Argument(help="A dataset directory written by `trajflow ingest` (never modified).")]
Seed = Annotated[int, typer.Option(help="Random seed; the same seed gives byte-identical files.")]


@augment_app.command("forking")
def augment_forking_command(
    ctx: typer.Context,
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
    from .render import report_written
    from ..stages.augment import augment_forking

    with user_errors(ctx):
        result = augment_forking(data, out, copies=copies, scale_std=scale_std, rot_std_deg=rot_std_deg,
                                 scale_range=scale_range, rot_range_deg=rot_range_deg, seed=seed,
                                 overwrite=overwrite, quiet=quiet)
        report_written(result, quiet)


@augment_app.command("scale-rotate")
def augment_scale_rotate_command(
    ctx: typer.Context,
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
    from .render import report_written
    from ..stages.augment import augment_scale_rotate

    with user_errors(ctx):
        result = augment_scale_rotate(data, out, copies=copies, rot_std_deg=rot_std_deg, scale_std=scale_std,
                                      splits=tuple(split) if split else ("train",), seed=seed,
                                      overwrite=overwrite, quiet=quiet)
        report_written(result, quiet)
