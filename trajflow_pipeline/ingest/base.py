"""What every ingest adapter shares: the :class:`Ingest` description the registry hands out, the one channel for
non-fatal problems (:func:`warn`) and the line the CLI prints after a dataset is written (:func:`wrote_line`)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.text import Text

from ..errors import UsageError
from ..util.options import REQUIRED, keyword_options, option_value
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
    #: option -> how a plain config value (TOML: string, number, list, table) becomes the argument `function`
    #: takes, for options whose type is not plain (the CSV column mapping, rounD's geometry)
    converters: Mapping[str, Callable[[Any], Any]] = field(default_factory=dict)
    #: the files of the raw input the ingest reads, given the raw path and the options (None: every file under
    #: it); what an experiment's data stage hashes to tell whether the raw input changed
    inputs: Callable[[Path, dict[str, Any]], list[Path]] | None = None
    #: whether its samples come in groups of several futures of one input (None: that depends on the data), which
    #: `augment forking` needs
    multi_future: bool | None = False

    @property
    def options(self) -> dict[str, Any]:
        """The keyword options of `function` (besides overwrite and quiet) with their defaults."""
        return keyword_options(self.function)

    def config_options(self, values: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Options given as plain config values (an experiment's [data] table) as `function` takes them: unknown
        names refused, converters applied, numbers and strings made of their default's type (samples = 3000.0 ->
        3000). Every problem is a UsageError starting with `where` (the config file) and naming the key."""
        unknown = sorted(set(values) - set(self.options))
        if unknown:
            raise UsageError(f"{where}: unknown key(s) {', '.join(unknown)} in [data]: ingest {self.name} takes "
                             f"{', '.join(self.options) or 'no options'}")
        missing = [key for key, default in self.options.items() if default is REQUIRED and key not in values]
        if missing:
            raise UsageError(f"{where}: ingest {self.name} needs [data] {', '.join(missing)}")
        converted = {}
        for key, value in values.items():
            try:
                converted[key] = (self.converters[key](value) if key in self.converters
                                  else option_value(self.function, key, value))
            except UsageError as error:
                raise UsageError(f"{where}: [data] {key} {error}") from None
        return converted

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
