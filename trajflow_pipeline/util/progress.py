"""Rich progress bars that go silent under --quiet and when output is not a terminal-friendly stream."""

from __future__ import annotations

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)

#: Messages for humans go to stderr so that stdout stays clean for `--json` and pipes.
console = Console(stderr=True)


def make_progress(quiet: bool = False, *extra_columns: object) -> Progress:
    """A progress display with a description, bar, counts and times; disabled when `quiet`."""
    return Progress(
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *extra_columns,
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=quiet,
        transient=False,
    )


def duration_text(seconds: float) -> str:
    """A readable duration for tables and summaries: seconds, minutes or hours."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
