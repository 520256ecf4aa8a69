"""What every command shares: turning user errors into one line and an exit code, and the --quiet flag."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import polars as pl
import pyarrow as pa
import typer

from ..errors import TrajflowError
from ..util.progress import say


def debugging(ctx: typer.Context | None) -> bool:
    """Whether errors show tracebacks: the top-level --debug option of the command's invocation (`ctx`, the
    command's context), or TRAJFLOW_DEBUG=1."""
    flag = bool(ctx is not None and ctx.find_root().params.get("debug"))
    return flag or os.environ.get("TRAJFLOW_DEBUG", "") not in ("", "0")


Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars or summaries (for scripts).")]
Overwrite = Annotated[bool, typer.Option("--overwrite", help="Replace OUT even if it holds something else.")]
OutDir = Annotated[Path, typer.Option("--out", "-o", help="Dataset directory to write (created atomically).")]


@contextlib.contextmanager
def user_errors(ctx: typer.Context | None = None) -> Iterator[None]:
    """Report a TrajflowError as `error: ...` on stderr and exit with its code; --debug (read from the command's
    context `ctx`) re-raises it."""
    try:
        yield
    except TrajflowError as error:
        if debugging(ctx):
            raise
        say(("error:", "bold red"), f" {error}")
        raise typer.Exit(error.exit_code) from None
    except (OSError, pl.exceptions.PolarsError, pa.ArrowException) as error:
        # files that exist but cannot be used (a path component that is a file, corrupt Parquet pages, ...)
        if debugging(ctx):
            raise
        text = f"{error.filename}: {error.strerror}" if isinstance(error, OSError) and error.filename else error
        say(("error:", "bold red"), f" {str(text).splitlines()[0]}")
        raise typer.Exit(1) from None
    except KeyboardInterrupt:
        say(("interrupted", "bold red"), ": outputs in progress were not moved into place (an interrupted training "
            "can be continued with --resume)")
        raise typer.Exit(130) from None
