"""The levelX family through one reader: every member's fixture (its exact columns) ingests, the scripted scenarios
give the known pairs, all-agents gives the windows the tracks allow, and bad input is one line naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import typer
from levelx_fixture import (LC_FOLLOWER, LC_TARGET, LONE_CHANGER, ONCOMING_AFTER, ONCOMING_FIRST, TURNER,
                            highd_expected_pairs, windows_per_agent, write_members)
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.ingest.registry import get_ingest
from trajflow_pipeline.schemas import open_dataset


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("levelx")
    return {member: write_members(root / member, member, 2) for member in ("highd", "ind", "exid", "unid")}


def ingest(member: str, raw: Path, out: Path, **options: object) -> Path:
    return get_ingest(member).run(raw, out, quiet=True, **options)


def pairs(out: Path) -> pl.DataFrame:
    samples = open_dataset(out).samples()
    return samples.filter(pl.col("role") == "target").select("scene_id", "agent_id", "partner_id", *(
        c for c in ("gap", "from_lane", "to_lane") if c in samples.columns))


def test_highd_lane_changes_into_a_gap(raw: dict[str, Path], tmp_path: Path) -> None:
    out = ingest("highd", raw["highd"], tmp_path / "out")
    found = pairs(out)
    assert found.height == 4 and set(found.get_column("scene_id")) == {"rec01", "rec02"}
    assert set(zip(found.get_column("agent_id"), found.get_column("partner_id"))) == highd_expected_pairs()
    assert LONE_CHANGER not in found.get_column("agent_id").to_list()  # its new lane was empty
    lower = found.filter(pl.col("agent_id") == LC_TARGET)
    assert lower.get_column("from_lane").to_list() == [6, 6] and lower.get_column("to_lane").to_list() == [7, 7]
    ds = open_dataset(out)
    tracks = ds.tracks().filter((pl.col("scene_id") == "rec01") & (pl.col("agent_id") == LC_FOLLOWER))
    # y up (the image's y flipped), box centres, heading of a vehicle driving +x is 0
    assert tracks.get_column("y").max() < 0 and np.allclose(tracks.get_column("heading").to_numpy(), 0.0)
    assert ds.scenes().get_column("map_m_per_px").to_list() == pytest.approx([0.40424, 0.40424])
    samples = ds.samples()
    assert samples.group_by("joint_id").agg(pl.col("fold").n_unique()).get_column("fold").max() == 1


def test_ind_gap_acceptance_at_the_intersection(raw: dict[str, Path], tmp_path: Path) -> None:
    found = pairs(ingest("ind", raw["ind"], tmp_path / "out"))
    per_scene = found.filter(pl.col("scene_id") == "rec00").sort("partner_id")
    assert per_scene.rows() == [("rec00", TURNER, ONCOMING_FIRST, "rejected"), ("rec00", TURNER, ONCOMING_AFTER,
                                                                                  "accepted")]
    assert found.height == 4


@pytest.mark.parametrize("member", ["exid", "unid", "ind", "highd"])
def test_all_agents_are_every_complete_window(raw: dict[str, Path], tmp_path: Path, member: str) -> None:
    out = ingest(member, raw[member], tmp_path / "out", problems="all-agents")
    ds = open_dataset(out)
    tracks = ds.tracks()
    classes = json.loads((out / "dataset.json").read_text())["lineage"]["classes"]
    rows = tracks.filter(pl.col("agent_class").is_in(classes)).group_by("scene_id", "agent_id").len()
    expected = sum(windows_per_agent(n) for n in rows.get_column("len").to_list())
    samples = ds.samples()
    assert samples.height == expected > 0
    assert samples.group_by("scene_id", "agent_id").agg(pl.col("fold").n_unique()).get_column("fold").max() == 1
    if member == "exid":
        assert "pedestrian" not in classes


def test_classes_option(raw: dict[str, Path], tmp_path: Path) -> None:
    out = ingest("unid", raw["unid"], tmp_path / "out", classes="pedestrian")
    agents = open_dataset(out).samples().get_column("agent_id").unique().to_list()
    assert agents == [6]
    with pytest.raises(UsageError, match="--classes: lorry is not a levelX class"):
        ingest("unid", raw["unid"], tmp_path / "x", classes="lorry")
    with pytest.raises(UsageError, match="--problems: 'lane-change' is not a problem"):
        ingest("ind", raw["ind"], tmp_path / "x", problems="lane-change")
    with pytest.raises(UsageError, match="--classes and --stride"):
        ingest("highd", raw["highd"], tmp_path / "x", stride=2)


def test_round_alias_and_levelx_round_write_the_same_bytes(tmp_path: Path) -> None:
    from test_round_synth import write_gap_recordings

    source = write_gap_recordings(tmp_path / "raw", 2)
    runner = CliRunner()
    for args, out in ((["ingest", "round"], "a"), (["ingest", "levelx", "round"], "b")):
        assert runner.invoke(app, [*args, str(source), "-o", str(tmp_path / out), "-q"]).exit_code == 0
    for path in sorted((tmp_path / "a").rglob("*")):
        if path.is_file():
            assert path.read_bytes() == (tmp_path / "b" / path.relative_to(tmp_path / "a")).read_bytes(), path


# ------------------------------------------------------------------------------------------------- bad input


def fails(member: str, raw: Path, out: Path, *fragments: str) -> None:
    with pytest.raises(DataError) as caught:
        ingest(member, raw, out)
    message = str(caught.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    assert not out.exists()


def fresh(tmp_path: Path, member: str) -> Path:
    return write_members(tmp_path / "raw", member, 1)


def edit(path: Path, change) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(change(lines)) + "\n")


def test_missing_files_and_recordings(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "highd")
    (raw / "01_highway.png").unlink()
    fails("highd", raw, tmp_path / "out", "01_highway.png: file is missing")
    raw = fresh(tmp_path, "ind")
    with pytest.raises(DataError, match="recording\\(s\\) 07 not found; found 00"):
        get_ingest("ind").run(raw, tmp_path / "out", recordings=["7"], quiet=True)


def test_wrong_columns_for_the_member(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "ind")
    for path in raw.iterdir():
        if path.name.endswith("background.png"):
            path.rename(raw / "00_highway.png")
    fails("highd", raw, tmp_path / "out", "00_recordingMeta.csv: missing column(s) id, upperLaneMarkings")
    raw = fresh(tmp_path / "h", "highd")
    (raw / "01_highway.png").rename(raw / "01_background.png")
    fails("round", raw, tmp_path / "out", "01_recordingMeta.csv: missing column(s) recordingId")


def test_mismatched_ids_between_the_csvs(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "unid")
    edit(raw / "00_tracksMeta.csv", lambda lines: [lines[0], "5" + lines[1][1:], *lines[2:]])
    fails("unid", raw, tmp_path / "out", "00_tracksMeta.csv:2: recordingId 5 differs from the recording's (0")
    raw = fresh(tmp_path / "h", "highd")
    edit(raw / "01_tracksMeta.csv", lambda lines: [line for line in lines if not line.startswith("3,")])
    fails("highd", raw, tmp_path / "out", "01_tracks.csv:", "track 3 is not listed in 01_tracksMeta.csv")


def test_frames_going_back_and_nan_coordinates(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "highd")
    path = raw / "01_tracks.csv"
    edit(path, lambda lines: [lines[0], lines[2], lines[1], *lines[3:]])
    fails("highd", raw, path.parent / "out", "01_tracks.csv:3: track 1 goes back to frame")
    raw = fresh(tmp_path / "n", "exid")
    path = raw / "00_tracks.csv"
    edit(path, lambda lines: [lines[0], lines[1], ",".join(v if i != 4 else "NaN"
                                                           for i, v in enumerate(lines[2].split(","))), *lines[3:]])
    fails("exid", raw, tmp_path / "out", "00_tracks.csv:3: column 'xCenter' is")


def test_unreadable_image_and_bad_markings(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "highd")
    (raw / "01_highway.png").write_bytes(b"\x89PNG broken")
    fails("highd", raw, tmp_path / "out", "01_highway.png: cannot open the background image")
    raw = fresh(tmp_path / "m", "highd")
    meta = raw / "01_recordingMeta.csv"
    pl.read_csv(meta).with_columns(upperLaneMarkings=pl.lit("8.5;x")).write_csv(meta)
    fails("highd", raw, tmp_path / "out", "01_recordingMeta.csv:2: column 'upperLaneMarkings' holds '8.5;x'")


def test_cli_levelx_error_is_one_line_exit_1(tmp_path: Path) -> None:
    raw = fresh(tmp_path, "ind")
    (raw / "00_background.png").write_bytes(b"broken")
    result = CliRunner().invoke(app, ["ingest", "levelx", "ind", str(raw), "-o", str(tmp_path / "out"), "-q"])
    assert result.exit_code == 1 and result.output.strip().startswith("error: ") and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()
