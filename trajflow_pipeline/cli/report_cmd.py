"""`trajflow report`: parse arguments and call :func:`trajflow_pipeline.stages.report.report`.

Registered in `cli/app.py` as ``app.command("report")(report_command)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..util.progress import say
from .common import Quiet, user_errors


def report_command(
    ctx: typer.Context,
    runs: Annotated[list[Path], typer.Argument(
        metavar="RUN_OR_EXPERIMENT",
        help="Evaluated run directories (with eval/ from `trajflow eval`) and/or experiment directories "
             "(with experiment.json); experiments expand to their finished runs.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Report directory to write (replaced atomically; "
                                                          "an existing non-report directory is refused).")],
    no_figures: Annotated[bool, typer.Option("--no-figures", help="Tables and provenance only (fast).")] = False,
    examples: Annotated[int, typer.Option("--examples", min=0, metavar="N",
                                          help="Example samples per dataset in the prediction figure.")] = 4,
    quiet: Quiet = False,
) -> None:
    """Tables (Markdown + self-contained HTML), PNG figures and provenance from evaluated runs: mean ± std over
    folds and seeds per dataset and model, next to the paper's TrajFlow numbers."""
    from ..stages.report import report

    with user_errors(ctx):
        path = report(runs, out, quiet=quiet, figures=not no_figures, max_examples=examples)
    if not quiet:
        say(("wrote", "green"), f" report {path / 'report.html'} (Markdown: {path / 'report.md'})")
