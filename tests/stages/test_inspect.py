"""`trajflow inspect` validates the rows of every tracks shard: bad rows end as one line naming file and rows."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import polars as pl
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter

META = DatasetMeta(dataset="toy", dt=0.4, protocol=PROTOCOL_FOLDS)
SCENES, AGENTS, FRAMES = 3, 2, 6


def write_dataset(out: Path) -> Path:
    """Three scenes of two agents over six frames, one scene per shard, one sample per agent (frames 1..5)."""
    tracks = (pl.DataFrame({"scene_id": [f"s{s}" for s in range(SCENES)]})
              .join(pl.DataFrame({"agent_id": list(range(AGENTS))}), how="cross")
              .join(pl.DataFrame({"frame": list(range(FRAMES))}), how="cross")
              .with_columns(agent_type=pl.lit("pedestrian"), t=pl.col("frame") * 0.4, x=pl.col("frame") * 1.0,
                            y=pl.col("agent_id") * 1.0)
              .sort("scene_id", "agent_id", "frame"))
    scenes = pl.DataFrame({"dataset": "toy", "scene_id": [f"s{s}" for s in range(SCENES)], "location": "here",
                           "dt": 0.4, "source": "generated", "fold": [str(s) for s in range(SCENES)]})
    samples = (tracks.select("scene_id", "agent_id").unique(maintain_order=True)
               .with_columns(sample_id=pl.int_range(pl.len(), dtype=pl.Int64), t0_frame=pl.lit(2, pl.Int64),
                             n_past=pl.lit(2, pl.Int64), n_future=pl.lit(3, pl.Int64), group_id=pl.lit(0, pl.Int64),
                             split=pl.lit("train"), fold=pl.col("scene_id").str.slice(1)))
    with DatasetWriter(out, META, shard_rows=AGENTS * FRAMES) as writer:
        for _, part in tracks.group_by("scene_id", maintain_order=True):
            writer.add_tracks(part)
        writer.finish(scenes, samples)
    return out


def rewrite(path: Path, edit: Callable[[pl.DataFrame], pl.DataFrame]) -> None:
    """Replace the rows of one Parquet file of a dataset, keeping its trajflow metadata (a hand-edited file)."""
    table = pq.read_table(path)
    frame = edit(pl.from_arrow(table))
    pq.write_table(frame.to_arrow().replace_schema_metadata(table.schema.metadata), path)


def set_cell(column: str, row: int, value: object) -> Callable[[pl.DataFrame], pl.DataFrame]:
    """An edit that puts `value` into `column` at `row` (0-based)."""
    return lambda frame: frame.with_columns(
        pl.when(pl.int_range(pl.len()) == row).then(pl.lit(value, frame.schema[column])).otherwise(pl.col(column))
        .alias(column))


def inspect(data: Path, *options: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["inspect", str(data), *options])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, result.output


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    return write_dataset(tmp_path / "toy")


def shard(data: Path, number: int) -> Path:
    return data / "tracks" / f"part-{number:05d}.parquet"


def test_clean_dataset_inspects_fine_and_says_it_checked(dataset: Path) -> None:
    assert len(list((dataset / "tracks").iterdir())) == SCENES
    code, output = inspect(dataset, "--json")
    assert code == 0, output
    summary = json.loads(output)
    assert summary["tracks_checked"] is True and summary["track_rows"] == SCENES * AGENTS * FRAMES
    code, output = inspect(dataset, "--no-check-tracks", "--json")
    assert code == 0 and json.loads(output)["tracks_checked"] is False
    code, output = inspect(dataset)
    assert code == 0 and "tracks_checked" in output


@pytest.mark.parametrize(("edit", "message"), [
    (set_cell("x", 3, float("nan")), "tracks table: NaN or infinite values in column 'x' (rows 3; 0-based)"),
    (set_cell("y", 7, float("inf")), "tracks table: NaN or infinite values in column 'y' (rows 7; 0-based)"),
    (set_cell("frame", 4, 3), "tracks table: duplicated key (scene_id, agent_id, frame) (rows 3, 4; 0-based)"),
    (lambda frame: pl.concat([frame.slice(0, 2), frame.slice(3, 1), frame.slice(2, 1), frame.slice(4)]),
     "tracks table: rows are not sorted by (scene_id, agent_id, frame) (rows 3; 0-based)"),
    (set_cell("scene_id", 11, "s1~gone"), "tracks table: scene_id not present in the scenes table (rows 11; 0-based)"),
    (lambda frame: frame.with_columns(scene_id=pl.lit("s0")),
     "tracks table: scene 's0' also has rows in part-00000.parquet; a scene must not span two shards "
     "(rows 0, 1, 2, 3, 4 and 7 more; 0-based)"),
])
def test_bad_rows_name_the_shard_and_the_rows(dataset: Path, edit: Callable[[pl.DataFrame], pl.DataFrame],
                                              message: str) -> None:
    rewrite(shard(dataset, 1), edit)
    code, output = inspect(dataset)
    assert code == 1, output
    assert output.strip() == f"error: {shard(dataset, 1)}: {message}"
    assert "Traceback" not in output
    code, output = inspect(dataset, "--no-check-tracks")
    assert code == 0, output


def test_sample_whose_window_lost_a_frame(dataset: Path) -> None:
    # scene s2, agent 1 loses frame 4: sample row 5 (frames 1..5) is no longer complete
    rewrite(shard(dataset, 2), lambda frame: frame.filter(~((pl.col("agent_id") == 1) & (pl.col("frame") == 4))))
    code, output = inspect(dataset)
    assert code == 1, output
    assert output.strip() == (f"error: {dataset / 'samples.parquet'}: samples table: target window not complete in "
                              "the tracks (first: agent 1 of scene 's2' lacks a frame of 1..5) (rows 5; 0-based)")


def test_scene_without_tracks_leaves_its_samples_without_windows(dataset: Path) -> None:
    shard(dataset, 0).unlink()
    code, output = inspect(dataset)
    assert code == 1 and "samples table: target window not complete" in output and "(rows 0, 1; 0-based)" in output


def test_samples_of_unknown_scenes_fail_even_without_the_track_scan(dataset: Path) -> None:
    rewrite(dataset / "samples.parquet", set_cell("scene_id", 2, "nowhere"))
    code, output = inspect(dataset, "--no-check-tracks")
    assert code == 1
    assert output.strip() == (f"error: {dataset / 'samples.parquet'}: samples table: scene_id not present in the "
                              "scenes table (rows 2; 0-based)")


def test_a_shard_copied_under_a_second_name_is_refused_by_every_reader(dataset: Path) -> None:
    """The tracks checks are those of every read: what inspect refuses, training and evaluation refuse too."""
    from trajflow_pipeline.data.loader import load_problems
    from trajflow_pipeline.errors import DataError

    copy = shard(dataset, 9)
    copy.write_bytes(shard(dataset, 0).read_bytes())
    message = (f"{copy}: tracks table: scene 's0' also has rows in part-00000.parquet; a scene must not span two "
               "shards (rows 0, 1, 2, 3, 4 and 7 more; 0-based)")
    code, output = inspect(dataset)
    assert code == 1 and output.strip() == f"error: {message}"
    for split in ("train", "test"):
        with pytest.raises(DataError) as raised:
            load_problems(dataset, fold="1", split=split)
        assert str(raised.value) == message
