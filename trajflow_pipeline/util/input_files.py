"""Reading input files: exactly the path given (``[``, ``]``, ``*`` and ``?`` are characters), and only a file.

polars expands glob patterns in every path it is given by default, so a valid file ``run[1].csv`` reads as "no
files", a folder named ``data[2]`` loses its shards and ``data*.csv`` merges its siblings; and any reader opened on
a FIFO or a device named like an input (``dataset.json`` a pipe, ``tracks.csv`` -> /dev/zero) blocks or never
ends. Every read of an input file by trajflow goes through these functions: nothing globs, and anything but a
regular file (or a link to one) is refused with a DataError naming it.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import polars as pl

from ..errors import DataError

PathLike = str | Path


def regular_file(path: PathLike) -> Path:
    """`path`, checked to be a regular file (or a link to one) before anything opens it."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise DataError("file not found", path=path) from None
    except OSError as error:
        raise DataError(f"cannot open ({error.strerror})", path=path) from None
    if not stat.S_ISREG(mode):
        kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "not a regular file")
        raise DataError(f"is {kind}, not a file that can be read", path=path)
    return path


def read_bytes(path: PathLike) -> bytes:
    """The bytes of the regular file `path`."""
    return regular_file(path).read_bytes()


def read_text(path: PathLike) -> str:
    """The UTF-8 text of the regular file `path`; undecodable bytes are a DataError naming the byte offset."""
    data = read_bytes(path)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data.count(b"\n", 0, error.start) + 1
        raise DataError(f"not valid UTF-8 text (byte {error.start})", path=path, line=line) from None


def _files(paths: PathLike | Sequence[PathLike]) -> PathLike | list[PathLike]:
    if isinstance(paths, (str, Path)):
        return regular_file(paths)
    return [regular_file(path) for path in paths]


def read_parquet(path: PathLike, **options: Any) -> pl.DataFrame:
    """``pl.read_parquet`` of exactly `path`."""
    return pl.read_parquet(regular_file(path), glob=False, **options)


def scan_parquet(paths: PathLike | Sequence[PathLike], **options: Any) -> pl.LazyFrame:
    """``pl.scan_parquet`` of exactly the given file(s)."""
    return pl.scan_parquet(_files(paths), glob=False, **options)


def read_csv(path: PathLike, **options: Any) -> pl.DataFrame:
    """``pl.read_csv`` of exactly `path`."""
    return pl.read_csv(regular_file(path), glob=False, **options)


def scan_csv(path: PathLike, **options: Any) -> pl.LazyFrame:
    """``pl.scan_csv`` of exactly `path`."""
    return pl.scan_csv(regular_file(path), glob=False, **options)
