"""`trajflow ingest nuscenes`: the command function, registered by the CLI as ``ingest nuscenes``.

Kept in its own module so that the nuscenes-devkit import (slow, optional extra) only happens when the command
runs; a missing devkit is reported as one line saying how to install the extra.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import Overwrite, Quiet, user_errors


def ingest_nuscenes_command(
    dataroot: Annotated[Path, typer.Argument(help="nuScenes root holding the v1.0-*/ tables and maps/ "
                                                  "(maps/prediction/prediction_scenes.json, maps/expansion/).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset directory to write (created atomically).")],
    version: Annotated[str, typer.Option("--version", help="Release folder: v1.0-mini or v1.0-trainval.")
                       ] = "v1.0-mini",
    all_agents: Annotated[bool, typer.Option(
        "--all-agents", help="Samples from every annotated agent with 4 past and 12 future keyframes instead of "
                             "the prediction-challenge entries (needed when prediction_scenes.json is absent).")
                          ] = False,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """nuScenes via nuscenes-devkit: prediction-challenge samples (4 past + 12 future at 0.5 s), ego vehicle, maps."""
    with user_errors():
        from ..ingest.registry import get_ingest

        adapter = get_ingest("nuscenes")
        result = adapter.run(dataroot, out, version=version, all_agents=all_agents, overwrite=overwrite, quiet=quiet)
        adapter.report(result, quiet)
