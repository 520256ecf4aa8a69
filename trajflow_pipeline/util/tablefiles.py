"""polars' file readers with paths taken as paths: ``[``, ``]``, ``*`` and ``?`` in a name are characters.

polars expands glob patterns in every path it is given by default, so a valid file ``run[1].csv`` reads as "no
files", a folder named ``data[2]`` loses its shards and ``data*.csv`` merges its siblings. Every read of a file
by trajflow goes through these functions; nothing globs.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import polars as pl

PathLike = str | Path


def read_parquet(path: PathLike, **options: Any) -> pl.DataFrame:
    """``pl.read_parquet`` of exactly `path`."""
    return pl.read_parquet(path, glob=False, **options)


def scan_parquet(paths: PathLike | Sequence[PathLike], **options: Any) -> pl.LazyFrame:
    """``pl.scan_parquet`` of exactly the given file(s)."""
    return pl.scan_parquet(paths, glob=False, **options)


def read_csv(path: PathLike, **options: Any) -> pl.DataFrame:
    """``pl.read_csv`` of exactly `path`."""
    return pl.read_csv(path, glob=False, **options)


def scan_csv(path: PathLike, **options: Any) -> pl.LazyFrame:
    """``pl.scan_csv`` of exactly `path`."""
    return pl.scan_csv(path, glob=False, **options)
