"""Bad Forking Paths input: one clear message naming the file (and the record), nothing written.

Run through the stage function and through the CLI function wrapped in a small Typer app.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from test_forking_fixture import Moment, default_moments, write_release
from typer.testing import CliRunner

from trajflow_pipeline.cli.ingest_cmd import ingest_forking_paths_command
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.forking_paths import ingest_forking_paths

runner = CliRunner()
cli = typer.Typer()
cli.command("forking-paths")(ingest_forking_paths_command)
cli.command("unused")(lambda: None)  # two commands, so Typer keeps the sub-command name


def small_release(root: Path):
    return write_release(root, default_moments()[:2], other_camera=False)


def target_file(release) -> Path:
    moment = release.moments[0]
    dest, annotator, _ = moment.futures[1]
    return release.file(moment, dest, annotator)


def edit_records(path: Path, edit) -> None:
    records = json.loads(path.read_text())
    edit(records)
    path.write_text(json.dumps(records))


def assert_cli_error(result, code: int, *fragments: str) -> None:
    assert result.exit_code == code, result.output
    text = result.output.replace("\n", "")
    assert "error: " in text and "Traceback" not in text
    for fragment in fragments:
        assert fragment in text, (fragment, text)


def test_unparseable_json_names_file_and_line(tmp_path: Path) -> None:
    release = small_release(tmp_path / "raw")
    path = target_file(release)
    path.write_text('[{"class_name": "Person",\n "is_x_agent": 1 "bbox": [1, 2, 3, 4]}]\n')
    with pytest.raises(DataError, match=rf"{path.name}:2: unparseable JSON: Expecting ',' delimiter \(column 18\)"):
        ingest_forking_paths(release.root, tmp_path / "out", folds=2, quiet=True)
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--folds", "2"])
    assert_cli_error(result, 1, path.name, "unparseable JSON")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("edit", "fragment"), [
    (lambda r: r[5].update(bbox=[10.0, 20.0, -3.0, 40.0]), "record 5 (0-based): bbox has negative size (w=-3, h=40)"),
    (lambda r: r[11].update(frame_id=1), "record 11 (0-based): frame_id 1 follows a larger frame_id (frame ids go "
                                         "backwards)"),
    (lambda r: r[2].pop("track_id"), "record 2 (0-based): missing or null field 'track_id'"),
    (lambda r: r[4].update(class_name="Bicycle"), "record 4 (0-based): class_name 'Bicycle' is not one of Person, "
                                                  "Vehicle"),
    (lambda r: r[3].update(bbox=[1.0, 2.0, 3.0]), "record 3 (0-based): bbox must be [x, y, w, h], got 3 values"),
    (lambda r: r[3].update(frame_id="seven"), "record 3 (0-based): frame_id must be a number, got 'seven'"),
    (lambda r: r[7].update(is_x_agent=2), "record 7 (0-based): is_x_agent must be 0 or 1, got 2"),
    (lambda r: r.insert(4, dict(r[3])), "record 4 (0-based): second box of Person 3 at frame_id 1 (first at record 3)"),
    (lambda r: [rec.update(is_x_agent=0) for rec in r], "no record has is_x_agent = 1"),
    (lambda r: r[1].update(is_x_agent=1), "several agents are marked is_x_agent = 1 (Person 3, Person 252)"),
])
def test_bad_records_are_located(tmp_path: Path, edit, fragment: str) -> None:
    release = small_release(tmp_path / "raw")
    path = target_file(release)
    edit_records(path, edit)
    with pytest.raises(DataError) as error:
        ingest_forking_paths(release.root, tmp_path / "out", folds=2, quiet=True)
    assert path.name in str(error.value) and fragment in str(error.value), str(error.value)
    assert not (tmp_path / "out").exists()


def test_not_a_list_and_empty_list(tmp_path: Path) -> None:
    release = small_release(tmp_path / "raw")
    path = target_file(release)
    path.write_text('{"class_name": "Person"}')
    with pytest.raises(DataError, match="expected a JSON list of bounding-box records, found a JSON dict"):
        ingest_forking_paths(release.root, tmp_path / "out", folds=2, quiet=True)
    path.write_text("[]")
    with pytest.raises(DataError, match=f"{path.name}: holds no bounding-box records"):
        ingest_forking_paths(release.root, tmp_path / "out", folds=2, quiet=True)


def test_file_names_folders_and_cameras(tmp_path: Path) -> None:
    release = small_release(tmp_path / "raw")
    stray = release.bbox / "zara01_1_252_cam4.json"
    stray.write_text("[]")
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--folds", "2"])
    assert_cli_error(result, 1, "zara01_1_252_cam4.json: file name does not follow <scene>_<moment>_<xagentID>_"
                                "<destIdx>_<annotatorID>_<cam>.json")
    stray.unlink()
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--camera", "cam3"])
    assert_cli_error(result, 1, "no cam3 files among 5 annotation files (cameras present: cam4)")
    result = runner.invoke(cli, ["forking-paths", str(tmp_path / "nowhere"), "-o", str(tmp_path / "out")])
    assert_cli_error(result, 1, "Forking Paths folder not found")
    (tmp_path / "empty").mkdir()
    result = runner.invoke(cli, ["forking-paths", str(tmp_path / "empty"), "-o", str(tmp_path / "out")])
    assert_cli_error(result, 1, "no bounding-box annotations")
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--fps", "zara=x"])
    assert_cli_error(result, 2, "--fps: expected a number or scene=number pairs")
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--scale", "-1"])
    assert_cli_error(result, 2, "scale (metres per pixel) for scene 'zara01' must be a positive number")
    with pytest.raises(UsageError, match="only 2 moment"):
        ingest_forking_paths(release.root, tmp_path / "out", quiet=True)


def test_wrong_x_agent_in_name(tmp_path: Path) -> None:
    release = small_release(tmp_path / "raw")
    path = target_file(release)
    path.rename(path.with_name(path.name.replace("_252_", "_253_")))
    with pytest.raises(DataError, match="the x-agent is Person 252, but the file name says person 253"):
        ingest_forking_paths(release.root, tmp_path / "out", folds=2, quiet=True)


def test_single_future_group_and_short_future(tmp_path: Path) -> None:
    moments = [Moment("hotel", 1, 5, ((0, "27", 20.0),), fork=0),
               Moment("hotel", 2, 6, ((0, "27", 20.0), (1, "28", -40.0)), fork=90),
               Moment("hotel", 3, 8, ((0, "27", 20.0), (1, "28", -40.0)), fork=95, extra_frames=-20)]
    release = write_release(tmp_path / "raw", moments, other_camera=False)
    result = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "out"), "--folds", "2"])
    assert result.exit_code == 0, result.output
    assert "skipped 2 annotated future(s)" in result.output
    quiet = runner.invoke(cli, ["forking-paths", str(release.root), "-o", str(tmp_path / "quiet"), "--folds", "2",
                                "--quiet"])
    assert quiet.exit_code == 0 and "warning: skipped 2 annotated future(s)" in quiet.output   # even under --quiet
    ds = open_dataset(tmp_path / "out")
    samples = ds.samples()
    assert samples.get_column("moment").to_list() == ["hotel_1_5", "hotel_2_6", "hotel_2_6"]
    assert ds.lineage["single_future_groups"] == 1
    skipped = ds.lineage["skipped"]
    assert [Path(s["file"]).name for s in skipped] == ["hotel_3_8_0_27_cam4.json", "hotel_3_8_1_28_cam4.json"]
    assert "8 of 8 past and 9 of 12 future steps" in skipped[0]["reason"]
