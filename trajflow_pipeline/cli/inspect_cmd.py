"""`trajflow inspect DATA`: summarise and validate a dataset (rendered by cli/render.py, or as JSON)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .common import user_errors
from .render import print_dataset_summary


def inspect_command(
    ctx: typer.Context,
    data: Annotated[Path, typer.Argument(help="A dataset directory written by `trajflow ingest`.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")] = False,
    check_tracks: Annotated[bool, typer.Option(
        "--check-tracks/--no-check-tracks",
        help="Read every tracks shard to validate its rows (NaN/inf, duplicated or unsorted keys, unknown scenes, "
             "incomplete sample windows); --no-check-tracks skips this full read for huge datasets.")] = True,
) -> None:
    """Summarise a dataset: scenes, agents, rows, samples per fold and split, dt, agent types; validate its rows."""
    from ..stages.inspect import summarize

    with user_errors(ctx):
        summary = summarize(data, check_tracks_contents=check_tracks)
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    print_dataset_summary(summary)
