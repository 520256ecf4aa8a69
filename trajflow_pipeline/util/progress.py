"""The consoles messages for humans go through, :func:`say`, and progress bars that go silent under --quiet.

Neither console reads rich markup or emoji codes: text is printed exactly as composed, so a file name such as
``run[1].csv``, a reference such as ``biwi_eth.txt:100:`` or a cell value such as ``[red]`` prints as it is
(rich would drop the first as a tag and turn ``:100:`` into an emoji). Styles come only from (text, style) parts.
"""

from __future__ import annotations

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)
from rich.text import Text

#: Messages for humans go to stderr so that stdout stays clean for `--json` and pipes.
console = Console(stderr=True, markup=False, emoji=False, highlight=False)
#: Tables and summaries that are a command's output.
stdout = Console(markup=False, emoji=False, highlight=False)

Part = str | tuple[str, str]


def styled(*parts: Part) -> Text:
    """Text from plain strings and (string, style) pairs, e.g. ``styled(("error:", "bold red"), " ", message)``;
    nothing in any part is read as markup or as an emoji code."""
    return Text.assemble(*parts)


def say(*parts: Part, out: Console | None = None) -> None:
    """Print one message made of plain strings and (string, style) pairs exactly as composed (on stderr unless
    `out` is given), wrapped only where the terminal must."""
    (out or console).print(styled(*parts), soft_wrap=True)


def make_progress(quiet: bool = False, *extra_columns: object) -> Progress:
    """A progress display with a description, bar, counts and times; disabled when `quiet`."""
    return Progress(
        SpinnerColumn(),
        TextColumn("{task.description}", style="bold", markup=False),
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
