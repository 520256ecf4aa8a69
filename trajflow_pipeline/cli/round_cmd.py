"""`trajflow ingest round`: parse the options and call the rounD ingest stage (registered by cli/app.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import Overwrite, Quiet, user_errors


def ingest_round_command(
    raw: Annotated[Path, typer.Argument(help="Folder of levelX recordings (XX_tracks.csv, XX_tracksMeta.csv, "
                                             "XX_recordingMeta.csv, XX_background.png; or its data/ sub-folder), "
                                             "or one file of the recording to read.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset directory to write (created atomically).")],
    recording: Annotated[Optional[list[str]], typer.Option(
        "--recording", "-r", help="Recording number to read (e.g. 00); repeat for several. Default: all.")] = None,
    geometry: Annotated[Optional[Path], typer.Option(
        help="JSON roundabout geometry: one object with centre (a list x, y), inner_radius, outer_radius, or an object "
             "mapping locationId to one. Default: inferred per recording from circulating traffic.")] = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """rounD gap-acceptance scenarios: entering target + circulating ego, 15 past / 25 (up to 35) future steps at
    0.2 s, 5 folds, background maps."""
    from ..ingest.registry import get_ingest
    from ..ingest.round_geometry import load_geometry_file

    with user_errors():
        config = load_geometry_file(geometry) if geometry is not None else None
        adapter = get_ingest("round")
        result = adapter.run(raw, out, recordings=recording, geometry=config, overwrite=overwrite, quiet=quiet)
        adapter.report(result, quiet)
