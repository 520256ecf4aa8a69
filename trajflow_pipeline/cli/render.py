"""What the commands print as their output (stdout): the tables of inspect, eval and status, in one place."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from ..util.progress import duration_text, say, stdout

if TYPE_CHECKING:  # only for annotations: the CLI imports no stage before a command runs
    from ..stages.status import ExperimentStatus, RunStatus, StageProgress

#: how each state is shown
_STATE_STYLE = {"done": "green", "training": "bold cyan", "evaluating": "bold cyan", "continuing": "bold cyan",
                "interrupted": "yellow", "training or interrupted": "yellow", "trained": "yellow",
                "budget raised": "yellow", "temperature changed": "yellow", "planned": "dim", "unreadable": "bold red",
                "data changed": "yellow"}
#: how each data stage state (stages/data_stages.py) is shown
_DATA_STYLE = {"reused": "green", "given": "green", "built": "green", "stale": "yellow", "missing": "yellow",
               "unknown": "bold red"}


def report_written(out: Path, quiet: bool, line: Callable[[Path, dict[str, Any]], Text] | None = None) -> None:
    """After an ingest or augmentation: `line` (default: ``ingest.base.wrote_line``) for the dataset at `out`,
    from its inspect summary; nothing under --quiet."""
    if quiet:
        return
    from ..ingest.base import wrote_line
    from ..stages.inspect import summarize

    say((line or wrote_line)(out, summarize(out)))


def print_dataset_summary(summary: dict) -> None:
    """inspect's tables: the overview, samples by fold and split, agent types."""
    overview = Table(title=f"{summary['dataset']}  ({summary['path']})", show_header=False)
    for key in ("schema_version", "written_by", "protocol", "dt", "scenes", "agents", "track_rows",
                "track_shards", "samples", "groups", "has_map", "tracks_checked"):
        overview.add_row(key, str(summary[key]))
    overview.add_row("horizons (past/future)",
                     ", ".join(f"{h['n_past']}/{h['n_future']} ({h['len']})" for h in summary["horizons"]))
    stdout.print(overview)
    splits = Table(title="samples by fold and split")
    for column in ("fold", "split", "samples", "groups"):
        splits.add_column(column, justify="right" if column in ("samples", "groups") else "left")
    for row in summary["samples_by_fold_and_split"]:
        splits.add_row(str(row["fold"] or "-"), str(row["split"] or "-"), str(row["samples"]), str(row["groups"]))
    stdout.print(splits)
    types = Table(title="agent types")
    for column in ("agent_type", "agents", "rows"):
        types.add_column(column)
    for row in summary["agent_types"]:
        types.add_row(row["agent_type"], str(row["agents"]), str(row["rows"]))
    stdout.print(types)


def print_metric_means(title: str, means: dict[str, float]) -> None:
    """eval's table of the aggregate metrics."""
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for name, value in means.items():
        table.add_row(name, f"{value:.4f}")
    stdout.print(table)


def print_status(status: ExperimentStatus, out: Console) -> None:
    """The status as rich tables (the data stages, the runs) and a summary line."""
    if status.data:
        stages = Table(title="data stages")
        for column in ("stage", "dataset", "state", "builds", "why"):
            stages.add_column(column, justify="right" if column == "builds" else "left")
        for stage in status.data:
            state = "current" if stage.state == "reused" else stage.state
            stages.add_row(stage.stage.label, str(stage.stage.path),
                           Text(state, style=_DATA_STYLE.get(stage.state, "")),
                           str(stage.record.builds) if stage.record else "", stage.reason)
        out.print(stages)
    table = Table(title=f"{status.kind} {status.name}  ({status.path})")
    table.add_column("run", no_wrap=True)
    table.add_column("state")
    for column in ("stage: epoch", "best (patience)", "s/epoch", "stage left", "trained", "minADE/FDE"):
        table.add_column(column, justify="right")
    for run in status.runs:
        metrics = [run.metrics.get("min_ade"), run.metrics.get("min_fde")]
        table.add_row(run.name, Text(run.state, style=_STATE_STYLE.get(run.state, "")), *_progress_cells(run),
                      duration_text(run.train_seconds) if run.train_seconds else "",
                      "/".join(f"{v:.3f}" for v in metrics if v is not None))
    out.print(table)
    states = Counter(run.state for run in status.runs)
    trained = sum(run.train_seconds for run in status.runs)
    evaluated = sum(run.eval_seconds or 0.0 for run in status.runs)
    summary = ", ".join(f"{count} {state}" for state, count in states.most_common())
    runs = f"{len(status.runs)} run{'' if len(status.runs) == 1 else 's'}"
    say(f"{runs}: {summary}. Time so far, summed over runs: training {duration_text(trained)}, "
        f"evaluation {duration_text(evaluated)}.", out=out)
    for run in status.runs:
        if run.problem:
            say((f"{run.name}:", "red"), f" {run.problem}", out=out)
    if status.note:
        say(("note:", "yellow"), f" {status.note}", out=out)


def _progress_cells(run: RunStatus) -> list[str]:
    """stage and epoch of its maximum, best epoch (and the patience left while training), seconds per epoch,
    and the time the stage may still take (while its training goes on)."""
    progress: StageProgress | None = run.progress
    if run.fits_saved is not None:  # an evaluation in progress: its saved fits say how far it is
        return [f"eval: {run.fits_saved[0]:,}/{run.fits_saved[1]:,} fits saved", "", "", ""]
    if progress is None:
        return [""] * 4
    epoch = f"{progress.stage}: {progress.epoch}" + (f"/{progress.max_epochs}" if progress.max_epochs else "")
    training = run.state in ("training", "interrupted", "training or interrupted", "budget raised",
                             "temperature changed", "continuing")
    best = progress.kept_epoch if not training and progress.kept_epoch is not None else progress.best_epoch
    best_text = "" if best is None else str(best)
    if training and progress.patience_left is not None:
        best_text += f" ({progress.patience_left}/{progress.patience})"
    left = progress.epochs_left
    remaining = ""
    if training and left is not None and progress.seconds_per_epoch is not None:
        fewest, most = (n * progress.seconds_per_epoch for n in left)
        remaining = duration_text(most) if fewest == most else f"{duration_text(fewest)}-{duration_text(most)}"
    elif training and left is not None and left != (0, 0):
        remaining = f"{left[0]}-{left[1]} epochs" if left[0] != left[1] else f"{left[1]} epochs"
    return [epoch, best_text, "" if progress.seconds_per_epoch is None else f"{progress.seconds_per_epoch:.1f}",
            remaining]
