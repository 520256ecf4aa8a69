"""`trajflow ingest nuscenes`: the command function, registered by the CLI as ``ingest nuscenes``.

Kept in its own module so that the nuscenes-devkit import (slow, optional extra) only happens when the command
runs; a missing devkit is reported as one line saying how to install the extra.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from ..util.progress import say, styled
from .common import Overwrite, Quiet, user_errors


@contextlib.contextmanager
def _show_ingest_warnings() -> Iterator[None]:
    """Print the ingest's own warnings (no map expansion, dropped entries) as `warning: ...` lines on stderr."""
    from ..ingest.nuscenes_maps import NuScenesWarning

    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):  # type: ignore[no-untyped-def]
        if issubclass(category, NuScenesWarning):
            say(("warning:", "bold yellow"), f" {message}")
        else:
            previous(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        warnings.simplefilter("always", NuScenesWarning)
        warnings.showwarning = show
        yield


def _summary(out: Path) -> Text:
    """One line saying what was written (scenes, rows, samples per split, maps)."""
    from ..stages.inspect import summarize

    summary = summarize(out)
    splits = ", ".join(f"{row['split']} {row['samples']}" for row in summary["samples_by_fold_and_split"])
    maps = "with maps" if summary["has_map"] else "no maps"
    return styled(("wrote", "green"), f" {out}: {summary['scenes']} scenes, {summary['track_rows']} track rows, "
                  f"{summary['samples']} samples ({splits}), {summary['groups']} groups, {maps}")


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
        from ..ingest.nuscenes import ingest_nuscenes

        with _show_ingest_warnings():
            result = ingest_nuscenes(dataroot, out, version=version, all_agents=all_agents, overwrite=overwrite,
                                     quiet=quiet)
        if not quiet:
            say(_summary(result))
