"""What every ingest adapter shares: the :class:`Ingest` description the registry hands out, the one channel for
non-fatal problems (:func:`warn`) and the line the CLI prints after a dataset is written (:func:`wrote_line`)."""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.text import Text

from ..errors import UsageError
from ..util.progress import say, styled


#: the lists of the collect_warnings() blocks now running, innermost last
_COLLECTORS: list[list[str]] = []


def warn(message: str) -> None:
    """Report a non-fatal problem of an ingest (the dataset is written all the same): one ``warning: ...`` line on
    stderr, even under --quiet, and the message kept by every :func:`collect_warnings` block running."""
    for messages in _COLLECTORS:
        messages.append(message)
    say(("warning:", "bold yellow"), f" {message}")


@contextlib.contextmanager
def collect_warnings() -> Iterator[list[str]]:
    """The messages :func:`warn` reports while the block runs, in order: for an adapter that records its
    warnings in the lineage, and for programs calling an ingest."""
    messages: list[str] = []
    _COLLECTORS.append(messages)
    try:
        yield messages
    finally:
        _COLLECTORS.remove(messages)


def wrote_line(out: Path, summary: dict[str, Any]) -> Text:
    """The line after an ingest (or augmentation): where the dataset is and how much it holds."""
    return styled(("wrote", "green"), f" {out}: {summary['scenes']} scenes, {summary['track_rows']} track rows, "
                  f"{summary['samples']} samples, {summary['groups']} groups")


@dataclass(frozen=True)
class Ingest:
    """One dataset's adapter: its registry name, what it writes, and how to run it.

    `function` is the module's ``ingest_*`` function: ``(raw, out, *, <options>, overwrite, quiet) -> out``, or
    ``(out, *, ...)`` for a dataset that is generated (`raw` is None then).
    """

    #: the name the CLI (``trajflow ingest NAME``) and experiment configs (``[data] ingest``) use
    name: str
    #: the dataset name written into dataset.json (None: an option chooses it)
    dataset: str | None
    #: seconds between frames (None: an option gives it)
    dt: float | None
    #: the fold names, where the dataset fixes them (None: no folds, or as many as an option says)
    folds: tuple[str, ...] | None
    #: what the raw input is, for messages (None: the data is generated, there is no raw input)
    raw: str | None
    function: Callable[..., Path]
    #: the line printed after the dataset is written
    summary: Callable[[Path, dict[str, Any]], Text] = wrote_line

    @property
    def options(self) -> dict[str, Any]:
        """The keyword options of `function` (besides overwrite and quiet) with their defaults."""
        parameters = inspect.signature(self.function).parameters.values()
        return {p.name: p.default for p in parameters
                if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in ("overwrite", "quiet")}

    def run(self, raw: str | Path | None, out: str | Path, *, overwrite: bool = False, quiet: bool = False,
            **options: Any) -> Path:
        """Ingest `raw` (None for generated data) into the dataset directory `out`; returns `out`."""
        if (raw is None) != (self.raw is None):
            needs = f"needs {self.raw}" if self.raw is not None else "generates its data and reads no raw input"
            raise UsageError(f"ingest {self.name} {needs}")
        unknown = sorted(set(options) - set(self.options))
        if unknown:
            raise UsageError(f"ingest {self.name}: unknown option(s) {', '.join(unknown)}; allowed: "
                             f"{', '.join(self.options) or 'none'}")
        args = (out,) if raw is None else (raw, out)
        return self.function(*args, overwrite=overwrite, quiet=quiet, **options)
