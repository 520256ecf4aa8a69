"""Bad rounD input: one clear line naming the file (and line), nothing written; recordings without any
gap-acceptance situation only warn."""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pytest
import typer
from test_round_synth import EGO_ACCEPT, EGO_REJECT, gap_scenario, write_gap_recordings, write_recording
from typer.testing import CliRunner

from trajflow_pipeline.cli.ingest_cmd import ingest_round_command
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.round import ingest_round
from trajflow_pipeline.ingest.round_geometry import RoundaboutGeometry, load_geometry_file


@pytest.fixture
def raw(tmp_path: Path) -> Path:
    return write_gap_recordings(tmp_path / "raw", 1)


def fails(raw: Path, out: Path, *fragments: str) -> None:
    with pytest.raises(DataError) as caught:
        ingest_round(raw, out, quiet=True)
    message = str(caught.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    assert not out.exists()


def edit_lines(path: Path, edit) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")


def line_of(path: Path, track: int, nth: int) -> int:
    """1-based line number of the nth row (0-based) of `track` in a tracks CSV."""
    lines = path.read_text().splitlines()
    rows = [i for i, line in enumerate(lines[1:], start=2) if line.split(",")[1] == str(track)]
    return rows[nth]


@pytest.mark.parametrize("kind", ["tracksMeta.csv", "recordingMeta.csv", "tracks.csv", "background.png"])
def test_missing_file_is_named(raw: Path, tmp_path: Path, kind: str) -> None:
    (raw / f"00_{kind}").unlink()
    fails(raw, tmp_path / "out", f"00_{kind}: file is missing")


@pytest.mark.parametrize(("file", "column"), [("tracks", "xCenter"), ("tracksMeta", "class"),
                                               ("recordingMeta", "orthoPxToMeter"), ("tracks", "frame")])
def test_missing_or_renamed_column(raw: Path, tmp_path: Path, file: str, column: str) -> None:
    path = raw / f"00_{file}.csv"
    edit_lines(path, lambda lines: [lines[0].replace(column, column + "_renamed"), *lines[1:]])
    fails(raw, tmp_path / "out", f"00_{file}.csv: missing column(s) {column}; found ", f"{column}_renamed")


def test_track_with_a_gap_in_its_frames(raw: Path, tmp_path: Path) -> None:
    path = raw / "00_tracks.csv"
    gone = line_of(path, 3, 10)
    text = path.read_text().splitlines()
    frame = int(text[gone - 1].split(",")[2])
    edit_lines(path, lambda lines: lines[:gone - 1] + lines[gone:])
    fails(raw, tmp_path / "out", f"00_tracks.csv:{gone}: track 3 jumps from frame {frame - 1} to frame {frame + 1}",
          "must be contiguous")


def test_duplicated_row(raw: Path, tmp_path: Path) -> None:
    path = raw / "00_tracks.csv"
    again = line_of(path, 2, 5)
    edit_lines(path, lambda lines: lines[:again] + [lines[again - 1]] + lines[again:])
    fails(raw, tmp_path / "out", f"00_tracks.csv:{again + 1}: track 2 has two rows for frame")


def test_cells_that_are_not_numbers(raw: Path, tmp_path: Path) -> None:
    path = raw / "00_tracks.csv"
    bad = line_of(path, 1, 7)
    edit_lines(path, lambda lines: [*lines[:bad - 1], ",".join(v if i != 4 else "abc" for i, v in
                                                               enumerate(lines[bad - 1].split(","))), *lines[bad:]])
    fails(raw, tmp_path / "out", f"00_tracks.csv:{bad}: column 'xCenter' holds 'abc', not a number")
    write_gap_recordings(raw, 1)
    edit_lines(path, lambda lines: [*lines[:bad - 1], ",".join(v if i != 5 else "" for i, v in
                                                               enumerate(lines[bad - 1].split(","))), *lines[bad:]])
    fails(raw, tmp_path / "out", f"00_tracks.csv:{bad}: column 'yCenter' is empty")
    write_gap_recordings(raw, 1)
    edit_lines(path, lambda lines: [*lines[:bad - 1], ",".join(v if i != 5 else "1e300" for i, v in
                                                               enumerate(lines[bad - 1].split(","))), *lines[bad:]])
    fails(raw, tmp_path / "out", f"00_tracks.csv:{bad}: column 'yCenter' is beyond the largest magnitude accepted")
    write_gap_recordings(raw, 1)
    edit_lines(raw / "00_tracksMeta.csv", lambda lines: [lines[0], lines[1].replace(",1,", ",1.5,", 1), *lines[2:]])
    fails(raw, tmp_path / "out", "00_tracksMeta.csv:2: column 'trackId' holds '1.5', not a whole number")


def test_tracks_and_their_meta_must_agree(raw: Path, tmp_path: Path) -> None:
    meta = raw / "00_tracksMeta.csv"
    edit_lines(meta, lambda lines: [line for line in lines if line.split(",")[1] != "5"])
    fails(raw, tmp_path / "out", "00_tracks.csv:", "track 5 is not listed in 00_tracksMeta.csv")
    write_gap_recordings(raw, 1)
    table = pl.read_csv(meta).with_columns(pl.when(pl.col("trackId") == 4).then(pl.col("finalFrame") + 3)
                                           .otherwise(pl.col("finalFrame")).alias("finalFrame"))
    table.write_csv(meta)
    fails(raw, tmp_path / "out", "00_tracksMeta.csv:5: track 4 spans frames", "in 00_tracks.csv")
    write_gap_recordings(raw, 1)
    pl.read_csv(meta).with_columns(numFrames=pl.col("numFrames") + 1).write_csv(meta)
    fails(raw, tmp_path / "out", "00_tracksMeta.csv:2: track 1 spans frames")


def test_background_that_does_not_open(raw: Path, tmp_path: Path) -> None:
    (raw / "00_background.png").write_bytes(b"\x89PNG broken")
    fails(raw, tmp_path / "out", "00_background.png: cannot open the background image")


def test_unusable_recording_meta(raw: Path, tmp_path: Path) -> None:
    meta = raw / "00_recordingMeta.csv"
    pl.read_csv(meta).with_columns(frameRate=pl.lit(24)).write_csv(meta)
    fails(raw, tmp_path / "out", "00_recordingMeta.csv:2: frameRate 24 Hz cannot be resampled to 5 Hz")
    meta.write_text("")
    fails(raw, tmp_path / "out", "00_recordingMeta.csv: file is empty")


def test_unpadded_recording_prefix(tmp_path: Path) -> None:
    raw = write_gap_recordings(tmp_path / "raw", 1)
    for path in raw.iterdir():
        path.rename(raw / path.name.replace("00_", "7_"))
    out = ingest_round(raw / "7_tracks.csv", tmp_path / "out", quiet=True)
    assert open_dataset(out).scenes().get_column("source")[0].startswith("7_recordingMeta.csv")


def test_wrong_paths(tmp_path: Path) -> None:
    fails(tmp_path / "nowhere", tmp_path / "out", "raw rounD path not found")
    (tmp_path / "empty").mkdir()
    fails(tmp_path / "empty", tmp_path / "out", "no levelX recordings")
    (tmp_path / "notes.txt").write_text("x")
    fails(tmp_path / "notes.txt", tmp_path / "out", "not a levelX recording file")
    with pytest.raises(UsageError, match="'x1' is not a recording number"):
        ingest_round(write_gap_recordings(tmp_path / "raw", 1), tmp_path / "out", recordings=["x1"], quiet=True)


def test_recording_without_gap_acceptance_only_warns(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    raw = write_gap_recordings(tmp_path / "raw", 1)
    write_recording(raw, 1, [t for t in gap_scenario() if t.track_id not in (EGO_ACCEPT, EGO_REJECT)])
    out = ingest_round(raw, tmp_path / "out", quiet=True)
    ds = open_dataset(out)
    assert ds.scenes().get_column("scene_id").to_list() == ["rec00", "rec01"]
    assert set(ds.samples().get_column("scene_id")) == {"rec00"}
    warnings = json.loads((out / "dataset.json").read_text())["lineage"]["warnings"]
    assert len(warnings) == 1 and "01_tracks.csv: no gap-acceptance situation" in warnings[0]
    assert "warning:" in capsys.readouterr().err


def test_recording_with_too_little_traffic_only_warns(tmp_path: Path) -> None:
    raw = tmp_path / "raw"
    write_recording(raw, 3, [t for t in gap_scenario() if t.cls == "pedestrian"])
    out = ingest_round(raw, tmp_path / "out", quiet=True)
    ds = open_dataset(out)
    assert ds.samples().height == 0 and ds.scenes().row(0, named=True)["geometry_source"] is None
    warnings = json.loads((out / "dataset.json").read_text())["lineage"]["warnings"]
    assert "cannot infer the roundabout geometry" in warnings[0] and "no samples" in warnings[1]


def test_geometry_values_are_checked(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="inner_radius < outer_radius"):
        RoundaboutGeometry(centre_x=0, centre_y=0, inner_radius=5, outer_radius=4)
    spec = tmp_path / "g.json"
    spec.write_text('{"centre": [1, 2], "inner_radius": 3, "outer_radius": 6, "radius": 4}')
    with pytest.raises(UsageError, match="unknown key"):
        load_geometry_file(spec)
    spec.write_text("{")
    with pytest.raises(UsageError, match="g.json:1: not valid JSON"):
        load_geometry_file(spec)
    spec.write_text('{"centre": [1, 2], "inner_radius": 3, "outer_radius": 6}')
    assert load_geometry_file(spec) == RoundaboutGeometry(1.0, 2.0, 3.0, 6.0)


def test_cli_error_is_one_line_and_keeps_the_previous_dataset(raw: Path, tmp_path: Path) -> None:
    app = typer.Typer()
    app.command()(ingest_round_command)
    runner = CliRunner()
    out = tmp_path / "out"
    assert runner.invoke(app, [str(raw), "-o", str(out), "-q"]).exit_code == 0
    before = (out / "samples.parquet").read_bytes()
    edit_lines(raw / "00_tracks.csv", lambda lines: [lines[0].replace("yCenter", "y"), *lines[1:]])
    result = runner.invoke(app, [str(raw), "-o", str(out), "-q", "--overwrite"])
    assert result.exit_code == 1
    text = result.output.strip()
    assert text.startswith("error: ") and "00_tracks.csv: missing column(s) yCenter" in text
    assert "Traceback" not in text
    assert (out / "samples.parquet").read_bytes() == before
