"""Bad nuScenes input through the command: one line naming the path, a non-zero exit, no traceback, no output."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

pytest.importorskip("nuscenes", reason="nuscenes-devkit is not installed (pip install -e '.[nuscenes]')")

from nuscenes_fixture import Release, write_release  # noqa: E402

from trajflow_pipeline.cli.ingest_cmd import ingest_nuscenes_command  # noqa: E402

runner = CliRunner()
app = typer.Typer()
app.command()(ingest_nuscenes_command)


def run(root: Path, out: Path, *extra: str, quiet: bool = True):
    return runner.invoke(app, [str(root), "-o", str(out), *extra, *(["--quiet"] if quiet else [])])


def assert_one_line_error(result, *fragments: str, code: int = 1) -> None:
    """Exit `code`, no traceback, and (after any warning) one `error: ...` message holding every fragment."""
    assert result.exit_code == code, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    text = result.output.strip()
    assert "Traceback" not in text
    error = text[text.index("error: "):] if "error: " in text else text
    assert error.startswith("error: ") and text[:text.index(error)].count("error: ") == 0, text
    flat = error.replace("\n", "")
    for fragment in fragments:
        assert fragment in flat, (fragment, text)


@pytest.fixture()
def release(tmp_path: Path) -> Release:
    return write_release(tmp_path / "nuscenes")


def test_the_command_ingests_and_reports(release: Release, tmp_path: Path) -> None:
    result = run(release.root, tmp_path / "data", quiet=False)
    assert result.exit_code == 0, result.output
    assert "warning: " in result.output and "map expansion not found" in result.output
    assert "dropped 1 prediction-challenge entry" in result.output
    assert "2 scenes" in result.output and "7 samples (test 2, train 5)" in result.output
    assert (tmp_path / "data" / "dataset.json").exists()
    quiet = run(release.root, tmp_path / "data", "--version", "v1.0-mini")
    assert quiet.exit_code == 0 and "wrote" not in quiet.output


def test_missing_dataroot_and_version_folder(release: Release, tmp_path: Path) -> None:
    assert_one_line_error(run(tmp_path / "nowhere", tmp_path / "data"), "nowhere: nuScenes dataroot not found")
    result = run(release.root, tmp_path / "data", "--version", "v1.0-trainval")
    assert_one_line_error(result, f"{release.root / 'v1.0-trainval'}: version folder 'v1.0-trainval' not found",
                          "found v1.0-mini")
    (release.root / "v1.0-mini").rename(release.root / "tables")
    assert_one_line_error(run(release.root, tmp_path / "data"), "version folder 'v1.0-mini' not found")
    assert not (tmp_path / "data").exists()


def test_unsupported_version_is_a_usage_error(release: Release, tmp_path: Path) -> None:
    assert_one_line_error(run(release.root, tmp_path / "data", "--version", "v1.0-test"),
                          "--version 'v1.0-test' is not supported", "v1.0-mini, v1.0-trainval", code=2)


@pytest.mark.parametrize("table", ["sample_annotation", "map"])
def test_missing_table(release: Release, tmp_path: Path, table: str) -> None:
    (release.table_root / f"{table}.json").unlink()
    assert_one_line_error(run(release.root, tmp_path / "data"),
                          f"{release.table_root / table}.json: table '{table}' is missing")
    assert not (tmp_path / "data").exists()


def test_table_that_is_not_json(release: Release, tmp_path: Path) -> None:
    (release.table_root / "ego_pose.json").write_text('[{"token": "x",')
    assert_one_line_error(run(release.root, tmp_path / "data"),
                          f"{release.table_root / 'ego_pose.json'}: table is not valid JSON")


def test_inconsistent_tables(release: Release, tmp_path: Path) -> None:
    path = release.table_root / "sample_annotation.json"
    rows = json.loads(path.read_text())
    rows[0]["instance_token"] = "0" * 32
    path.write_text(json.dumps(rows))
    assert_one_line_error(run(release.root, tmp_path / "data"), "tables are inconsistent", "0" * 32)


def test_missing_semantic_map_png(release: Release, tmp_path: Path) -> None:
    png = next((release.root / "maps").glob("*.png"))
    png.unlink()
    assert_one_line_error(run(release.root, tmp_path / "data"),
                          f"{png}: semantic map named by v1.0-mini/map.json does not exist")


def test_missing_prediction_scenes_offers_all_agents(release: Release, tmp_path: Path) -> None:
    path = release.root / "maps" / "prediction" / "prediction_scenes.json"
    path.unlink()
    assert_one_line_error(run(release.root, tmp_path / "data"), f"{path}: prediction_scenes.json not found",
                          "cannot be defined", "--all-agents")
    assert run(release.root, tmp_path / "data", "--all-agents").exit_code == 0


def test_broken_prediction_scenes(release: Release, tmp_path: Path) -> None:
    path = release.root / "maps" / "prediction" / "prediction_scenes.json"
    path.write_text("{not json")
    assert_one_line_error(run(release.root, tmp_path / "data"), f"{path}: not valid JSON")
    path.write_text(json.dumps({"scene-0061": ["no-underscore"]}))
    assert_one_line_error(run(release.root, tmp_path / "data"), f"{path}: entry 'no-underscore' is not")
    path.write_text(json.dumps({"scene-0103": [f"{'a' * 32}_{release.sample_tokens['scene-0103'][3]}"]}))
    assert_one_line_error(run(release.root, tmp_path / "data"), str(path), "names a sample or instance that is "
                          "not in v1.0-mini")
    # an instance that exists but is not annotated in that sample
    entry = f"{release.instance_token('scene-0061', 1)}_{release.sample_tokens['scene-0061'][0]}"
    path.write_text(json.dumps({"scene-0061": [entry]}))
    assert_one_line_error(run(release.root, tmp_path / "data"), str(path), "not annotated in that sample")


@pytest.mark.parametrize(("content", "fragment"), [
    ("{broken", "map expansion is not valid JSON"),
    (json.dumps({"version": "1.2", "canvas_edge": [1, 1]}), "map expansion does not load: outdated map version"),
    (json.dumps({"version": "1.3", "canvas_edge": [1, 1], "polygon": []}), "map expansion does not load"),
])
def test_map_expansion_that_does_not_load(release: Release, tmp_path: Path, content: str, fragment: str) -> None:
    path = release.root / "maps" / "expansion" / "boston-seaport.json"
    path.parent.mkdir(parents=True)
    path.write_text(content)
    assert_one_line_error(run(release.root, tmp_path / "data"), f"{path}: {fragment}")
    assert not (tmp_path / "data").exists()


def test_output_is_not_replaced_by_a_failed_run(release: Release, tmp_path: Path) -> None:
    assert run(release.root, tmp_path / "data").exit_code == 0
    before = (tmp_path / "data" / "samples.parquet").read_bytes()
    (release.table_root / "scene.json").write_text("[")
    assert_one_line_error(run(release.root, tmp_path / "data"), "scene.json: table is not valid JSON")
    assert (tmp_path / "data" / "samples.parquet").read_bytes() == before
