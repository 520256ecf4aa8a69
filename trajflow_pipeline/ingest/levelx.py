"""The files of a levelX recording (rounD and its family: XX_recordingMeta.csv, XX_tracksMeta.csv, XX_tracks.csv,
XX_background.png): finding the recordings, and reading each CSV with its types checked, every problem a DataError
naming the file and the line an editor shows."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import polars as pl

from ..errors import DataError, UsageError
from ..util import input_files
from .textfile import MAX_MAGNITUDE, csv_record_line, in_range, range_problem

RECORDING_META_COLUMNS: dict[str, pl.DataType] = {
    "recordingId": pl.Int64(), "locationId": pl.Int64(), "frameRate": pl.Float64(), "orthoPxToMeter": pl.Float64()}
TRACKS_META_COLUMNS: dict[str, pl.DataType] = {
    "trackId": pl.Int64(), "initialFrame": pl.Int64(), "finalFrame": pl.Int64(), "numFrames": pl.Int64(),
    "class": pl.String()}
TRACKS_COLUMNS: dict[str, pl.DataType] = {
    "trackId": pl.Int64(), "frame": pl.Int64(), "xCenter": pl.Float64(), "yCenter": pl.Float64(),
    "heading": pl.Float64(), "width": pl.Float64(), "length": pl.Float64(), "xVelocity": pl.Float64(),
    "yVelocity": pl.Float64()}
FILE_KINDS = ("recordingMeta.csv", "tracksMeta.csv", "tracks.csv", "background.png")
_FILE_PATTERN = re.compile(r"^(\d+)_(recordingMeta\.csv|tracksMeta\.csv|tracks\.csv|background\.png)$")


@dataclass(frozen=True)
class Recording:
    """One levelX recording: its number, the folder holding its four files and their prefix ("07" in 07_*)."""

    number: int
    folder: Path
    prefix: str = ""

    def path(self, kind: str) -> Path:
        return self.folder / f"{self.prefix or f'{self.number:02d}'}_{kind}"

    @property
    def scene_id(self) -> str:
        return f"rec{self.number:02d}"


@dataclass(frozen=True)
class RecordingMeta:
    """What the ingest needs from XX_recordingMeta.csv."""

    recording_id: int
    location_id: int
    frame_rate: float
    ortho_px_to_meter: float


# --------------------------------------------------------------------------------------------- discovering input


def discover_recordings(raw: Path, recordings: Sequence[int | str] | None = None) -> list[Recording]:
    """The recordings to read: all of a folder (or its data/ sub-folder), a selection, or one file's recording.

    Every selected recording must have its four files; the list is sorted by recording number.
    """
    if not raw.exists():
        raise DataError("raw rounD path not found", path=raw)
    if raw.is_file():
        match = _FILE_PATTERN.match(raw.name)
        if match is None:
            raise DataError("not a levelX recording file (expected XX_tracks.csv, XX_tracksMeta.csv, "
                            "XX_recordingMeta.csv or XX_background.png)", path=raw)
        folder, found = raw.parent, _prefixes_in(raw.parent)
        wanted = {int(match.group(1))} if recordings is None else None
    else:
        folder = raw
        found = _prefixes_in(folder)
        if not found and (raw / "data").is_dir():
            folder, found = raw / "data", _prefixes_in(raw / "data")
        wanted = None
    if not found:
        raise DataError("no levelX recordings (XX_tracks.csv, XX_tracksMeta.csv, XX_recordingMeta.csv, "
                        "XX_background.png) in this folder", path=raw)
    if recordings is not None:
        wanted = {_recording_number(value) for value in recordings}
        unknown = sorted(wanted - set(found))
        if unknown:
            raise DataError(f"recording(s) {', '.join(f'{n:02d}' for n in unknown)} not found; found "
                            f"{', '.join(f'{n:02d}' for n in sorted(found))}", path=folder)
    selected = sorted((Recording(number, folder, found[number]) for number in (wanted if wanted is not None
                                                                                  else found)),
                      key=lambda recording: recording.scene_id)
    for recording in selected:
        for kind in FILE_KINDS:
            if not recording.path(kind).is_file():
                raise DataError(f"file is missing (every levelX recording needs XX_{', XX_'.join(FILE_KINDS)})",
                                path=recording.path(kind))
    return selected


def _prefixes_in(folder: Path) -> dict[int, str]:
    """Recording number -> file prefix of the levelX files in a folder ("07" for 07_tracks.csv)."""
    matches = (_FILE_PATTERN.match(p.name) for p in sorted(folder.iterdir()))
    return {int(m.group(1)): m.group(1) for m in matches if m}


def _recording_number(value: int | str) -> int:
    try:
        number = int(str(value).strip())
    except ValueError:
        raise UsageError(f"--recording: {value!r} is not a recording number (e.g. 00 or 7)") from None
    if number < 0:
        raise UsageError(f"--recording: {value!r} is not a recording number")
    return number


# ------------------------------------------------------------------------------------------------- reading CSVs


def _header(path: Path) -> list[str]:
    try:
        return input_files.read_csv(path, n_rows=0).columns
    except pl.exceptions.NoDataError:
        raise DataError("file is empty", path=path) from None
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"cannot read CSV ({str(error).splitlines()[0]})", path=path) from None


def read_csv_columns(path: Path, columns: dict[str, pl.DataType]) -> pl.DataFrame:
    """The named columns of a CSV file with their types, plus `__row` (0-based data row).

    A missing (or renamed) column, a cell that does not parse, an empty cell or a number that is not finite or
    beyond :data:`textfile.MAX_MAGNITUDE` raise a DataError naming the file and, for cells, the line an editor
    shows (:func:`textfile.csv_record_line`).
    """
    header = _header(path)
    missing = [name for name in columns if name not in header]
    if missing:
        raise DataError(f"missing column(s) {', '.join(missing)}; found {', '.join(header)}", path=path)
    try:
        frame = input_files.read_csv(path, columns=list(columns), schema_overrides=columns)
    except (pl.exceptions.PolarsError, OSError):
        raise _locate_bad_cell(path, columns) from None
    frame = frame.select(list(columns)).with_row_index("__row")
    bad = [pl.col(name).is_null() | (~in_range(pl.col(name)) if dtype == pl.Float64 else pl.lit(False))
           for name, dtype in columns.items()]
    flags = frame.select(pl.any_horizontal(bad).alias("bad")).to_series()
    if flags.any():
        row = frame.row(int(flags.arg_true()[0]), named=True)
        name = next(n for n, d in columns.items() if row[n] is None
                    or (d == pl.Float64 and not (math.isfinite(row[n]) and abs(row[n]) <= MAX_MAGNITUDE)))
        problem = "is empty" if row[name] is None else f"is {range_problem(row[name])}"
        raise DataError(f"column '{name}' {problem}", path=path, **_line(path, int(row["__row"])))
    return frame


def _line(path: Path, row: int) -> dict[str, int]:
    """Where data row `row` (0-based) of a CSV file starts, as an editor counts lines."""
    line = csv_record_line(path, row)
    return {"line": line} if line is not None else {}


def _locate_bad_cell(path: Path, columns: dict[str, pl.DataType]) -> DataError:
    """Find the first cell that does not parse as its column's type (the slow path, only after a failure)."""
    try:
        text = input_files.read_csv(path, columns=list(columns), infer_schema=False)
    except (pl.exceptions.PolarsError, OSError) as error:
        return DataError(f"cannot parse CSV ({str(error).splitlines()[0]})", path=path)
    for name, dtype in columns.items():
        if dtype == pl.String:
            continue
        raw = text.get_column(name).str.strip_chars()
        parsed = raw.cast(pl.Float64, strict=False)
        bad = parsed.is_null() & raw.is_not_null()
        if dtype == pl.Int64:
            bad = bad | (parsed.is_not_null() & (parsed != parsed.round()))
        if bad.any():
            row = int(bad.arg_true()[0])
            kind = "a whole number" if dtype == pl.Int64 else "a number"
            return DataError(f"column '{name}' holds {raw[row]!r}, not {kind}", path=path, **_line(path, row))
    return DataError("cannot parse CSV", path=path)


def read_recording_meta(recording: Recording) -> RecordingMeta:
    """recordingId, locationId, frameRate and orthoPxToMeter of a recording (its meta file has one row)."""
    path = recording.path("recordingMeta.csv")
    meta = read_csv_columns(path, RECORDING_META_COLUMNS)
    if meta.height != 1:
        raise DataError(f"expected exactly one data row, found {meta.height}", path=path)
    row = meta.row(0, named=True)
    if row["frameRate"] <= 0 or row["orthoPxToMeter"] <= 0:
        raise DataError("frameRate and orthoPxToMeter must be positive", path=path, line=2)
    return RecordingMeta(int(row["recordingId"]), int(row["locationId"]), float(row["frameRate"]),
                         float(row["orthoPxToMeter"]))


def read_tracks_meta(recording: Recording) -> pl.DataFrame:
    """trackId, class and frame span of each track; track ids must be unique."""
    path = recording.path("tracksMeta.csv")
    meta = read_csv_columns(path, TRACKS_META_COLUMNS)
    repeated = meta.filter(pl.col("trackId").is_duplicated())
    if repeated.height:
        first = repeated.row(0, named=True)
        raise DataError(f"trackId {first['trackId']} appears more than once", path=path, line=first["__row"] + 2)
    return meta.with_columns(pl.col("class").str.strip_chars().str.to_lowercase())


def read_raw_tracks(recording: Recording, tracks_meta: pl.DataFrame) -> pl.DataFrame:
    """All rows of XX_tracks.csv, checked: sorted by (trackId, frame), unique, contiguous, consistent with the
    tracks meta file (every track listed there, with the same frame span)."""
    path = recording.path("tracks.csv")
    tracks = read_csv_columns(path, TRACKS_COLUMNS)
    in_order = (pl.col("trackId") > pl.col("trackId").shift(1)) | (
        (pl.col("trackId") == pl.col("trackId").shift(1)) & (pl.col("frame") >= pl.col("frame").shift(1)))
    if not tracks.select(in_order.fill_null(True).all()).item():
        tracks = tracks.sort("trackId", "frame")   # levelX files come sorted; sorting copies every column
    same_track = pl.col("trackId") == pl.col("trackId").shift(1)
    step = pl.col("frame") - pl.col("frame").shift(1)
    problems = tracks.with_columns(previous=pl.col("frame").shift(1)).filter(same_track & (step != 1))
    if problems.height:
        first = problems.row(0, named=True)
        if first["frame"] == first["previous"]:
            raise DataError(f"track {first['trackId']} has two rows for frame {first['frame']}", path=path,
                            line=first["__row"] + 2)
        raise DataError(f"track {first['trackId']} jumps from frame {first['previous']} to frame {first['frame']}; "
                        "the frames of a track must be contiguous", path=path, line=first["__row"] + 2)
    spans = tracks.group_by("trackId").agg(pl.col("frame").min().alias("first"), pl.col("frame").max().alias("last"),
                                           pl.col("__row").min().alias("row"))
    unlisted = spans.join(tracks_meta, on="trackId", how="anti").sort("row")
    if unlisted.height:
        first = unlisted.row(0, named=True)
        raise DataError(f"track {first['trackId']} is not listed in {recording.path('tracksMeta.csv').name}",
                        path=path, line=first["row"] + 2)
    compared = tracks_meta.join(spans, on="trackId", how="left").sort("__row")
    wrong = compared.filter(pl.col("first").is_null() | (pl.col("first") != pl.col("initialFrame"))
                            | (pl.col("last") != pl.col("finalFrame"))
                            | (pl.col("numFrames") != pl.col("finalFrame") - pl.col("initialFrame") + 1))
    if wrong.height:
        first = wrong.row(0, named=True)
        seen = "no rows" if first["first"] is None else f"frames {first['first']}..{first['last']}"
        raise DataError(f"track {first['trackId']} spans frames {first['initialFrame']}..{first['finalFrame']} "
                        f"({first['numFrames']} frames) here but has {seen} in {path.name}",
                        path=recording.path("tracksMeta.csv"), line=first["__row"] + 2)
    return tracks
