"""What the commands print as their output (stdout): the tables of inspect, eval and status, in one place, each
printed whole by :func:`show` (never a cell cut short, whether to a terminal of any width or to a file)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich import box
from rich.cells import cell_len
from rich.console import Console
from rich.measure import Measurement
from rich.segment import Segments
from rich.table import Column, Table
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
    show(overview, stdout)
    splits = Table(title="samples by fold and split")
    for column in ("fold", "split", "samples", "groups"):
        splits.add_column(column, justify="right" if column in ("samples", "groups") else "left")
    for row in summary["samples_by_fold_and_split"]:
        splits.add_row(str(row["fold"] or "-"), str(row["split"] or "-"), str(row["samples"]), str(row["groups"]))
    show(splits, stdout)
    types = Table(title="agent types")
    for column in ("agent_type", "agents", "rows"):
        types.add_column(column)
    for row in summary["agent_types"]:
        types.add_row(row["agent_type"], str(row["agents"]), str(row["rows"]))
    show(types, stdout)


def print_metric_means(title: str, means: dict[str, float]) -> None:
    """eval's table of the aggregate metrics."""
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for name, value in means.items():
        table.add_row(name, f"{value:.4f}")
    show(table, stdout)


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
        show(stages, out)
    left_out = show(lambda leave_out: _runs_table(status, leave_out), out, optional=_STATUS_OPTIONAL)
    if left_out:
        say(f"({' and '.join(left_out)} left out at this terminal's width; `--json` has every field)", out=out)
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


#: the status columns a narrow terminal leaves out first (the time a stage may still take already uses s/epoch)
_STATUS_OPTIONAL = ("s/epoch", "trained")


def _runs_table(status: ExperimentStatus, leave_out: tuple[str, ...] = ()) -> Table:
    """The runs of `status`, a row each, without the columns named in `leave_out`; no vertical rules, so that
    it fits a terminal of 80 columns more often (two spaces between columns, none at the edges)."""
    table = Table(title=f"{status.kind} {status.name}  ({status.path})", box=box.SIMPLE_HEAD, show_edge=False,
                  padding=(0, 1, 0, 0), pad_edge=False)
    headers = ("run", "state", "stage: epoch", "best (patience)", "s/epoch", "stage left", "trained", "minADE/FDE")
    kept = [header not in leave_out for header in headers]
    for header, keep in zip(headers, kept):
        if keep:
            table.add_column(header, justify="left" if header in ("run", "state") else "right",
                             no_wrap=header == "run")
    for run in status.runs:
        metrics = [run.metrics.get("min_ade"), run.metrics.get("min_fde")]
        cells = [run.name, Text(run.state, style=_STATE_STYLE.get(run.state, "")), *_progress_cells(run),
                 duration_text(run.train_seconds) if run.train_seconds else "",
                 "/".join(f"{v:.3f}" for v in metrics if v is not None)]
        table.add_row(*(cell for cell, keep in zip(cells, kept) if keep))
    return table


def show(table: Table | Callable[[tuple[str, ...]], Table], out: Console,
         optional: tuple[str, ...] = ()) -> list[str]:
    """Print a table whole: no cell is ever cut short with an ellipsis. Written to a file or a pipe (no
    terminal to fit, and rich would assume 80 columns) it keeps its natural width. In a terminal narrower than
    that, headers wrap at their spaces first; if that is not enough and `table` is given as a function of the
    headers to leave out, it is built again without the `optional` columns, one by one, until it fits; then
    cells wrap at their spaces, and what still does not fit folds onto more lines. Returns the headers left
    out."""
    build = table if callable(table) else (lambda leave_out: table)
    left_out: list[str] = []
    shown = build(())
    if not out.is_terminal:  # rendered at its own width (print's width= can only narrow) and printed uncropped
        width = max(out.width, _natural_width(shown, out))
        out.print(Segments(out.render(shown, out.options.update_width(width))), crop=False, soft_wrap=True)
        return left_out
    for header in optional:
        if _narrow(shown, out, (_widest_cell,)):
            break
        left_out.append(header)
        shown = build(tuple(left_out))
    _narrow(shown, out, (_widest_cell, _longest_word))
    out.print(shown)
    return left_out


def _natural_width(table: Table, out: Console) -> int:
    """The width `table` takes when nothing has to wrap."""
    return Measurement.get(out, out.options.update_width(10_000), table).maximum


def _narrow(table: Table, out: Console, floors: tuple[Callable[[Column], int], ...]) -> bool:
    """Narrow the wrappable columns of `table` until it fits `out`, each in turn down to each floor: first
    `_widest_cell` (headers wrap at their spaces: a line once), then `_longest_word` (cells wrap: a line every
    row), the columns with the most room first (rich alone narrows all columns evenly once two are equally
    wide, splitting numbers); what still does not fit folds, never cut. Whether it fits."""
    for column in table.columns:
        column.overflow = "fold"
    wrappable = [column for column in table.columns if not column.no_wrap]
    for floor in floors:
        for column in sorted(wrappable, key=lambda column: floor(column) - _width_now(column)):
            excess = _natural_width(table, out) - out.width
            if excess <= 0:
                return True
            column.max_width = max(floor(column), _width_now(column) - excess)
    return _natural_width(table, out) <= out.width


def _width_now(column: Column) -> int:
    """The width a column may take now: its limit if one was set, else its widest line, header included."""
    if column.max_width is not None:
        return column.max_width
    return _widest_line([str(column.header), *_cell_texts(column)])


def _widest_cell(column: Column) -> int:
    """The widest cell of a column, or its header's longest word if wider: its width with the header wrapped."""
    return max(_widest_line(_cell_texts(column)), _longest_word_of([str(column.header)]))


def _longest_word(column: Column) -> int:
    """The longest word among a column's header and cells: as narrow as it can get without splitting one."""
    return _longest_word_of([str(column.header), *_cell_texts(column)])


def _cell_texts(column: Column) -> list[str]:
    """A column's cells as plain text."""
    return [str(cell) for cell in column.cells]


def _widest_line(texts: list[str]) -> int:
    """The widest line of `texts`, in terminal cells (0 for none)."""
    return max((cell_len(line) for text in texts for line in text.splitlines()), default=0)


def _longest_word_of(texts: list[str]) -> int:
    """The longest word of `texts`, in terminal cells (at least 1)."""
    return max((cell_len(word) for text in texts for word in text.split()), default=1)


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
