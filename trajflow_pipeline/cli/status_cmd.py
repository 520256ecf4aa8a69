"""`trajflow status`: parse arguments, call :func:`trajflow_pipeline.stages.status.experiment_status`, print its
table (cli/render.py).

Registered in `cli/app.py` as ``app.command("status")(status_command)``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ..util.progress import stdout
from .common import user_errors
from .render import print_status


def status_command(
    ctx: typer.Context,
    experiment: Annotated[Path, typer.Argument(help="An experiment directory (`trajflow experiment ... -o EXP`), "
                                                    "or one run's (`trajflow train ... -o RUN`).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the status as JSON on stdout.")] = False,
) -> None:
    """Where each run of an experiment (or one run) stands: state, stage and epoch against its budget,
    early-stopping patience, time per epoch and the time the stage can still take, training time so far,
    minADE/minFDE when done."""
    from ..stages.status import experiment_status

    with user_errors(ctx):
        status = experiment_status(experiment)
    if as_json:
        typer.echo(json.dumps(status.to_dict(), indent=2, default=str))
        return
    print_status(status, stdout)
