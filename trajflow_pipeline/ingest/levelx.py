"""The files of a levelX recording (rounD and its family highD, inD, exiD, uniD: XX_recordingMeta.csv,
XX_tracksMeta.csv, XX_tracks.csv and the recording's image, XX_background.png or highD's XX_highway.png): each
member's :class:`Layout` (the columns levelX documents for it), finding the recordings, and reading each CSV with its
types checked, every problem a DataError naming the file and the line an editor shows. The member layouts and what
the ingests make of them: docs/datasets/levelx.md."""

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
    "recordingId": pl.Int64(), "trackId": pl.Int64(), "initialFrame": pl.Int64(), "finalFrame": pl.Int64(),
    "numFrames": pl.Int64(), "class": pl.String()}
TRACKS_COLUMNS: dict[str, pl.DataType] = {
    "recordingId": pl.Int64(), "trackId": pl.Int64(), "frame": pl.Int64(), "xCenter": pl.Float64(),
    "yCenter": pl.Float64(), "heading": pl.Float64(), "width": pl.Float64(), "length": pl.Float64(),
    "xVelocity": pl.Float64(),
    "yVelocity": pl.Float64()}
#: highD (the oldest member): `id` for the track and the recording, a bounding box (x, y its upper-left corner,
#: width along x, height along y) in metres with y pointing down the image, lanes and neighbours per row
HIGHD_RECORDING_META_COLUMNS: dict[str, pl.DataType] = {
    "id": pl.Int64(), "locationId": pl.Int64(), "frameRate": pl.Float64(), "upperLaneMarkings": pl.String(),
    "lowerLaneMarkings": pl.String()}
HIGHD_TRACKS_META_COLUMNS: dict[str, pl.DataType] = {
    "id": pl.Int64(), "initialFrame": pl.Int64(), "finalFrame": pl.Int64(), "numFrames": pl.Int64(),
    "class": pl.String(), "drivingDirection": pl.Int64()}
HIGHD_TRACKS_COLUMNS: dict[str, pl.DataType] = {
    "id": pl.Int64(), "frame": pl.Int64(), "x": pl.Float64(), "y": pl.Float64(), "width": pl.Float64(),
    "height": pl.Float64(), "xVelocity": pl.Float64(), "yVelocity": pl.Float64(), "precedingId": pl.Int64(),
    "followingId": pl.Int64(), "laneId": pl.Int64()}
#: metres per pixel of highD's full-resolution aerial image (the highD tools scale its XX_highway.png by 4 more)
HIGHD_ORTHO_PX_TO_METER = 0.10106


@dataclass(frozen=True)
class Layout:
    """One levelX member's files: the columns read from each CSV (typed), the image's file name and scale."""

    #: registry / dataset name ("round", "highd", ...) and the name people write ("rounD", "highD", ...)
    name: str
    title: str
    recording_meta: dict[str, pl.DataType]
    tracks_meta: dict[str, pl.DataType]
    tracks: dict[str, pl.DataType]
    #: the file kind of the image ("background.png"; highD: "highway.png")
    image: str = "background.png"
    #: the column naming the track (and, in the recording meta, the recording)
    id_column: str = "trackId"
    recording_id_column: str = "recordingId"
    #: the levelX tools show the image downscaled by this factor: metres per pixel = orthoPxToMeter * factor
    scale_down: int = 10
    #: metres per raw pixel where the recording meta has no orthoPxToMeter (highD)
    ortho_px_to_meter: float | None = None

    @property
    def file_kinds(self) -> tuple[str, ...]:
        return ("recordingMeta.csv", "tracksMeta.csv", "tracks.csv", self.image)

    @property
    def file_pattern(self) -> re.Pattern[str]:
        return re.compile(r"^(\d+)_(recordingMeta\.csv|tracksMeta\.csv|tracks\.csv|" + re.escape(self.image) + r")$")


def _drone_layout(name: str, title: str, scale_down: int) -> Layout:
    """inD, rounD, exiD and uniD share the drone layout (xCenter / yCenter, heading, trackId, orthoPxToMeter)."""
    return Layout(name, title, RECORDING_META_COLUMNS, TRACKS_META_COLUMNS, TRACKS_COLUMNS, scale_down=scale_down)


#: the members and their image scale-down factors (those of the levelX tools and of lxd-io)
LAYOUTS: dict[str, Layout] = {
    "round": _drone_layout("round", "rounD", 10),
    "ind": _drone_layout("ind", "inD", 12),
    "exid": _drone_layout("exid", "exiD", 6),
    "unid": _drone_layout("unid", "uniD", 2),
    "highd": Layout("highd", "highD", HIGHD_RECORDING_META_COLUMNS, HIGHD_TRACKS_META_COLUMNS, HIGHD_TRACKS_COLUMNS,
                    image="highway.png", id_column="id", recording_id_column="id", scale_down=4,
                    ortho_px_to_meter=HIGHD_ORTHO_PX_TO_METER),
}
ROUND = LAYOUTS["round"]
FILE_KINDS = ROUND.file_kinds


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
    #: highD: the y positions (metres, y up as the ingest stores them) of the upper and lower lane markings
    lane_markings: tuple[tuple[float, ...], tuple[float, ...]] | None = None


# --------------------------------------------------------------------------------------------- discovering input


def discover_recordings(raw: Path, recordings: Sequence[int | str] | None = None,
                        layout: Layout = ROUND) -> list[Recording]:
    """The recordings to read: all of a folder (or its data/ sub-folder), a selection, or one file's recording.

    Every selected recording must have its four files (those of `layout`); the list is sorted by recording number.
    """
    if not raw.exists():
        raise DataError(f"raw {layout.title} path not found", path=raw)
    if raw.is_file():
        match = layout.file_pattern.match(raw.name)
        if match is None:
            raise DataError("not a levelX recording file (expected XX_tracks.csv, XX_tracksMeta.csv, "
                            f"XX_recordingMeta.csv or XX_{layout.image})", path=raw)
        folder, found = raw.parent, _prefixes_in(raw.parent, layout)
        wanted = {int(match.group(1))} if recordings is None else None
    else:
        folder = raw
        found = _prefixes_in(folder, layout)
        if not found and (raw / "data").is_dir():
            folder, found = raw / "data", _prefixes_in(raw / "data", layout)
        wanted = None
    if not found:
        raise DataError("no levelX recordings (XX_tracks.csv, XX_tracksMeta.csv, XX_recordingMeta.csv, "
                        f"XX_{layout.image}) in this folder", path=raw)
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
        for kind in layout.file_kinds:
            if not recording.path(kind).is_file():
                raise DataError(f"file is missing (every levelX recording needs XX_{', XX_'.join(layout.file_kinds)})",
                                path=recording.path(kind))
    return selected


def _prefixes_in(folder: Path, layout: Layout) -> dict[int, str]:
    """Recording number -> file prefix of the levelX files in a folder ("07" for 07_tracks.csv)."""
    matches = (layout.file_pattern.match(p.name) for p in sorted(folder.iterdir()))
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


def read_recording_meta(recording: Recording, layout: Layout = ROUND) -> RecordingMeta:
    """Recording id, locationId, frameRate and metres per raw image pixel of a recording (its meta file has one
    row); highD's lane markings too."""
    path = recording.path("recordingMeta.csv")
    meta = read_csv_columns(path, layout.recording_meta)
    if meta.height != 1:
        raise DataError(f"expected exactly one data row, found {meta.height}", path=path)
    row = meta.row(0, named=True)
    ortho = layout.ortho_px_to_meter if layout.ortho_px_to_meter is not None else row["orthoPxToMeter"]
    if row["frameRate"] <= 0 or ortho <= 0:
        what = "frameRate and orthoPxToMeter" if layout.ortho_px_to_meter is None else "frameRate"
        raise DataError(f"{what} must be positive", path=path, line=2)
    markings = None
    if "upperLaneMarkings" in layout.recording_meta:
        markings = (_markings(row["upperLaneMarkings"], "upperLaneMarkings", path),
                    _markings(row["lowerLaneMarkings"], "lowerLaneMarkings", path))
    return RecordingMeta(int(row[layout.recording_id_column]), int(row["locationId"]), float(row["frameRate"]),
                         float(ortho), markings)


def _markings(text: str, column: str, path: Path) -> tuple[float, ...]:
    """highD lane markings "8.51;12.59;16.43" (y down the image) -> y positions with y up, in the order given."""
    try:
        values = tuple(-float(part) for part in text.strip().split(";") if part.strip())
    except ValueError:
        raise DataError(f"column '{column}' holds {text!r}, not numbers separated by ';'", path=path,
                        line=2) from None
    if len(values) < 2 or not all(math.isfinite(v) and abs(v) <= MAX_MAGNITUDE for v in values):
        raise DataError(f"column '{column}' holds {text!r}: expected two or more finite y positions", path=path,
                        line=2)
    return values


def check_recording_id(table: pl.DataFrame, path: Path, meta: RecordingMeta, layout: Layout) -> None:
    """Every row of a tracks or tracks meta file names the recording its recording meta file describes (the drone
    layouts repeat recordingId on every row; highD's files have no such column)."""
    if "recordingId" not in table.columns:
        return
    other = table.filter(pl.col("recordingId") != meta.recording_id)
    if other.height:
        first = other.row(0, named=True)
        raise DataError(f"recordingId {first['recordingId']} differs from the recording's "
                        f"({meta.recording_id} in its recordingMeta.csv)", path=path, line=first["__row"] + 2)


def read_tracks_meta(recording: Recording, layout: Layout = ROUND, meta: RecordingMeta | None = None) -> pl.DataFrame:
    """trackId, class (lower case) and frame span of each track (highD: and its drivingDirection, 1 or 2); track ids
    must be unique. highD's `id` is renamed trackId."""
    path = recording.path("tracksMeta.csv")
    table = read_csv_columns(path, layout.tracks_meta).rename({layout.id_column: "trackId"})
    if meta is not None:
        check_recording_id(table, path, meta, layout)
    repeated = table.filter(pl.col("trackId").is_duplicated())
    if repeated.height:
        first = repeated.row(0, named=True)
        raise DataError(f"{layout.id_column} {first['trackId']} appears more than once", path=path,
                        line=first["__row"] + 2)
    if "drivingDirection" in table.columns:
        wrong = table.filter(~pl.col("drivingDirection").is_in([1, 2]))
        if wrong.height:
            first = wrong.row(0, named=True)
            raise DataError(f"drivingDirection {first['drivingDirection']} of track {first['trackId']} is neither 1 "
                            "(upper lanes) nor 2 (lower lanes)", path=path, line=first["__row"] + 2)
    return table.with_columns(pl.col("class").str.strip_chars().str.to_lowercase())


def read_raw_tracks(recording: Recording, tracks_meta: pl.DataFrame, layout: Layout = ROUND,
                    meta: RecordingMeta | None = None) -> pl.DataFrame:
    """All rows of XX_tracks.csv, checked: sorted by (trackId, frame), unique, contiguous, consistent with the
    tracks meta file (every track listed there, with the same frame span). Rows of one track whose frames go
    backwards are an error; tracks may follow each other in any order. highD's `id` is renamed trackId."""
    path = recording.path("tracks.csv")
    tracks = read_csv_columns(path, layout.tracks).rename({layout.id_column: "trackId"})
    if meta is not None:
        check_recording_id(tracks, path, meta, layout)
    going_back = (pl.col("trackId") == pl.col("trackId").shift(1)) & (pl.col("frame") < pl.col("frame").shift(1))
    back = tracks.filter(going_back)
    if back.height:
        first = back.row(0, named=True)
        raise DataError(f"track {first['trackId']} goes back to frame {first['frame']}; the rows of a track must be "
                        "in frame order", path=path, line=first["__row"] + 2)
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
