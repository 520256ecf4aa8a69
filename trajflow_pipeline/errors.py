"""User-facing errors: every problem a user can cause ends as one clear line, never a bare traceback."""

from __future__ import annotations

from pathlib import Path


class TrajflowError(Exception):
    """An error caused by input or usage; the CLI prints its message on one line and exits non-zero."""

    exit_code = 1


class DataError(TrajflowError):
    """Bad input data, located as precisely as possible: the file and, where it applies, the line or row."""

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None,
                 row: int | None = None) -> None:
        self.path = None if path is None else str(path)
        self.line = line
        self.row = row
        where = ""
        if self.path is not None:
            where = self.path
            if line is not None:
                where += f":{line}"
            elif row is not None:
                where += f" (row {row})"
            where += ": "
        super().__init__(f"{where}{message}")


class UsageError(TrajflowError):
    """A bad option or combination of options (unknown fold, unknown config key, ...)."""

    exit_code = 2
