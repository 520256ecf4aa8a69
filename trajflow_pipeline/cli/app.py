"""The `trajflow` command line: the application, its global options, and which module holds each command.

Each command (group) lives in its own module, parses its options and calls one stage; what commands print as
output is drawn in cli/render.py.
"""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from .. import __version__
from ..util.progress import say, stdout
from .augment_cmd import augment_app
from .eval_cmd import eval_command
from .experiment_cmd import demo_command, experiment_command
from .ingest_cmd import ingest_app
from .inspect_cmd import inspect_command
from .report_cmd import report_command
from .status_cmd import status_command
from .train_cmd import train_command

app = typer.Typer(
    name="trajflow",
    help="TrajFlow pipeline: raw trajectory datasets -> unified Parquet scenes -> models -> metrics and reports.",
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_show_locals=False,
)
app.add_typer(ingest_app, name="ingest")
app.add_typer(augment_app, name="augment")
app.command("inspect")(inspect_command)
app.command("train")(train_command)
app.command("eval")(eval_command)
app.command("experiment")(experiment_command)
app.command("demo")(demo_command)
app.command("report")(report_command)
app.command("status")(status_command)

#: commands that run models, whose torch thread count matters
MODEL_COMMANDS = frozenset({"train", "eval", "experiment", "demo"})


def _version(value: bool) -> None:
    if value:
        stdout.print(f"trajflow {__version__}")
        raise typer.Exit()


def _set_threads(command: str | None, threads: int | None, auto: bool) -> None:
    """--threads N as given; otherwise, with `auto` (the console script) and for model commands, as many threads
    as the machine has idle CPUs, so that a second trajflow beside a busy one does not slow both down many times
    over."""
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    elif auto and command in MODEL_COMMANDS:
        from ..model.runtime import fit_threads_to_idle_cpus

        lowered = fit_threads_to_idle_cpus()
        if lowered is not None:
            say(("note:", "yellow"), f" other processes keep CPUs busy: {lowered[1]} torch thread(s) instead of "
                f"{lowered[0]} (set them with trajflow --threads N)")


@app.callback()
def _root(
    ctx: typer.Context,
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks for errors.")] = False,
    threads: Annotated[Optional[int], typer.Option(
        "--threads", min=1, help="torch CPU threads for model commands (default: one per CPU that other processes "
                                 "leave idle; OMP_NUM_THREADS is respected).")] = None,
    version: Annotated[Optional[bool], typer.Option("--version", callback=_version, is_eager=True,
                                                    help="Print the version and exit.")] = None,
) -> None:
    """TrajFlow: from raw trajectory datasets to trained normalizing-flow predictors and paper-grade metrics."""
    del debug  # read where errors are reported (cli.common.debugging)
    _set_threads(ctx.invoked_subcommand, threads, auto=bool((ctx.obj or {}).get("auto_threads")))


def main() -> None:
    """Entry point of the `trajflow` console script: the app, choosing torch's thread count from the idle CPUs
    (not where the app is embedded, e.g. tests' CliRunner)."""
    app(obj={"auto_threads": True})
