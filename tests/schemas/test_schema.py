"""The Parquet dataset contract: round trip, metadata, lazy sharded scans and every validation error."""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pyarrow.parquet as pq
import pytest

from trajflow_pipeline.errors import DataError, TrajflowError
from trajflow_pipeline.schemas import (PROTOCOL_FOLDS, SAMPLES, SCENES, TRACKS, DatasetMeta, DatasetWriter,
                                       open_dataset)
from trajflow_pipeline.schemas.validate import validate_table

META = DatasetMeta(dataset="toy", dt=0.4, protocol=PROTOCOL_FOLDS)


def toy_tables(n_scenes: int = 3, n_agents: int = 2, n_frames: int = 5) -> tuple[pl.DataFrame, ...]:
    """Scenes, tracks and samples of a tiny valid dataset."""
    tracks = pl.DataFrame({
        "scene_id": [f"s{s}" for s in range(n_scenes) for _ in range(n_agents) for _ in range(n_frames)],
        "agent_id": [a for _ in range(n_scenes) for a in range(n_agents) for _ in range(n_frames)],
        "agent_type": "pedestrian",
        "frame": [f for _ in range(n_scenes) for _ in range(n_agents) for f in range(n_frames)],
    }).with_columns(t=pl.col("frame") * 0.4, x=pl.col("frame") * 1.0, y=pl.col("agent_id") * 1.0)
    scenes = pl.DataFrame({"dataset": "toy", "scene_id": [f"s{s}" for s in range(n_scenes)], "location": "here",
                           "dt": 0.4, "source": "generated", "fold": [str(s) for s in range(n_scenes)]})
    samples = pl.DataFrame({"sample_id": list(range(n_scenes)), "scene_id": [f"s{s}" for s in range(n_scenes)],
                            "agent_id": 0, "t0_frame": 1, "n_past": 2, "n_future": 3, "group_id": 0,
                            "split": "train", "fold": [str(s) for s in range(n_scenes)]})
    return tuple(frame.with_columns(pl.col(pl.Int32).cast(pl.Int64)) for frame in (scenes, tracks, samples))


def write_toy(out: Path, shard_rows: int = 1_000_000) -> Path:
    scenes, tracks, samples = toy_tables()
    with DatasetWriter(out, META, shard_rows=shard_rows) as writer:
        for _, part in tracks.group_by("scene_id", maintain_order=True):
            writer.add_tracks(part)
        writer.finish(scenes, samples, lineage={"made_by": "test"})
    return out


def test_round_trip_keeps_tables_and_metadata(tmp_path: Path) -> None:
    out = write_toy(tmp_path / "toy")
    scenes, tracks, samples = toy_tables()
    ds = open_dataset(out)
    assert ds.meta == META
    assert ds.counts == {"scenes": 3, "samples": 3, "tracks": 30, "track_shards": 1}
    assert ds.lineage == {"made_by": "test"}
    assert ds.tracks().equals(tracks.select(TRACKS.required.keys()))
    assert ds.samples().select(samples.columns).equals(samples.select(ds.samples().select(samples.columns).columns))
    assert ds.scenes().get_column("scene_id").to_list() == ["s0", "s1", "s2"]
    metadata = pq.read_schema(out / "samples.parquet").metadata
    assert metadata[b"trajflow.schema_version"] == b"1"
    assert metadata[b"trajflow.dataset"] == b"toy"
    assert float(metadata[b"trajflow.dt"]) == 0.4
    assert metadata[b"trajflow.version"].decode() == META.version
    assert ds.fingerprint()["dataset"] == "toy"


def test_tracks_are_sharded_and_scanned_lazily(tmp_path: Path) -> None:
    out = write_toy(tmp_path / "toy", shard_rows=10)
    ds = open_dataset(out)
    assert len(ds.track_shards) == 3
    lazy = ds.scan_tracks()
    assert isinstance(lazy, pl.LazyFrame)
    assert lazy.filter(pl.col("scene_id") == "s1").select(pl.len()).collect().item() == 10
    assert pl.scan_parquet(out / "tracks" / "*.parquet").select(pl.len()).collect().item() == 30


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda t: t.drop("x"), "missing column(s) x"),
    (lambda t: t.with_columns(pl.col("frame").cast(pl.Float64)), "column 'frame' has dtype Float64"),
    (lambda t: t.with_columns(x=pl.when(pl.col("frame") == 3).then(float("nan")).otherwise(pl.col("x"))),
     "NaN or infinite values in column 'x' (rows 3, 8, 13"),
    (lambda t: t.with_columns(y=pl.when(pl.int_range(pl.len()) == 7).then(float("inf")).otherwise(pl.col("y"))),
     "NaN or infinite values in column 'y' (rows 7;"),
    (lambda t: pl.concat([t.head(3), t.slice(2, 1), t.slice(3)]), "duplicated key (scene_id, agent_id, frame)"),
    (lambda t: pl.concat([t.head(2), t.slice(3, 1), t.slice(2, 1), t.slice(4)]),
     "not sorted by (scene_id, agent_id, frame) (rows 3;"),
    (lambda t: t.with_columns(agent_type=pl.lit("robot")), "agent_type ['robot'] not one of"),
    (lambda t: t.with_columns(x=pl.when(pl.col("frame") == 0).then(None).otherwise(pl.col("x"))),
     "null values in column 'x'"),
])
def test_tracks_validation_names_file_and_rows(mutate, message: str) -> None:
    _, tracks, _ = toy_tables()
    with pytest.raises(DataError) as caught:
        validate_table(mutate(tracks), TRACKS, "tracks/part-00000.parquet")
    assert str(caught.value).startswith("tracks/part-00000.parquet: tracks table: ")
    assert message in str(caught.value)


def test_scenes_and_samples_validation() -> None:
    scenes, _, samples = toy_tables()
    with pytest.raises(DataError, match="scenes table: duplicated key"):
        validate_table(pl.concat([scenes, scenes.head(1)]), SCENES, "scenes.parquet")
    with pytest.raises(DataError, match="n_past and n_future must be at least 1"):
        validate_table(samples.with_columns(n_future=pl.lit(0, dtype=pl.Int64)), SAMPLES, "samples.parquet")
    with pytest.raises(DataError, match="missing column"):
        validate_table(samples.drop("group_id"), SAMPLES, "samples.parquet")
    with pytest.raises(DataError, match=r"samples.parquet: samples table: split \['testing'\] not one of train, val, "
                                        r"test \(or null\) \(rows 1; 0-based\)"):
        validate_table(samples.with_columns(split=pl.Series(["train", "testing", None])), SAMPLES, "samples.parquet")
    for dt in (0.0, -0.4):
        with pytest.raises(DataError, match="scenes table: dt must be positive"):
            validate_table(scenes.with_columns(dt=pl.lit(dt)), SCENES, "scenes.parquet")
    with pytest.raises(DataError, match="NaN or infinite values in column 'dt'"):
        validate_table(scenes.with_columns(dt=pl.lit(float("nan"))), SCENES, "scenes.parquet")


def test_writer_refuses_invalid_tables_and_leaves_nothing(tmp_path: Path) -> None:
    scenes, tracks, samples = toy_tables()
    with pytest.raises(DataError, match="scene_id not present in the scenes table"):
        with DatasetWriter(tmp_path / "bad", META) as writer:
            writer.add_tracks(tracks)
            writer.finish(scenes.head(1), samples)
    assert not (tmp_path / "bad").exists()
    assert not list(tmp_path.iterdir())


def test_failed_rewrite_keeps_the_old_dataset(tmp_path: Path) -> None:
    out = write_toy(tmp_path / "toy")
    before = (out / "dataset.json").read_text()
    scenes, tracks, samples = toy_tables()
    with pytest.raises(RuntimeError, match="boom"):
        with DatasetWriter(out, META) as writer:
            writer.add_tracks(tracks)
            raise RuntimeError("boom")
    assert (out / "dataset.json").read_text() == before
    assert open_dataset(out).tracks().height == 30
    assert [p.name for p in tmp_path.iterdir()] == ["toy"]


def test_reading_reports_missing_tables_and_truncated_files(tmp_path: Path) -> None:
    out = write_toy(tmp_path / "toy")
    (out / "samples.parquet").unlink()
    with pytest.raises(DataError, match=r"samples\.parquet: samples table is missing"):
        open_dataset(out).samples()
    shard = out / "tracks" / "part-00000.parquet"
    shard.write_bytes(shard.read_bytes()[:200])
    with pytest.raises(DataError, match=r"part-00000\.parquet: cannot read Parquet file"):
        open_dataset(out).tracks()
    with pytest.raises(DataError, match=r"part-00000\.parquet: cannot read Parquet file"):
        open_dataset(out).scan_tracks()
    for shard in (out / "tracks").iterdir():
        shard.unlink()
    with pytest.raises(DataError, match="tracks table is missing"):
        open_dataset(out).tracks()


def test_reading_checks_metadata(tmp_path: Path) -> None:
    out = write_toy(tmp_path / "toy")
    table = pq.read_table(out / "scenes.parquet")
    pq.write_table(table.replace_schema_metadata({b"trajflow.schema_version": b"99"}), out / "scenes.parquet")
    with pytest.raises(DataError, match="scenes.parquet: schema version 99"):
        open_dataset(out).scenes()
    pq.write_table(table.replace_schema_metadata({}), out / "scenes.parquet")
    with pytest.raises(DataError, match="not a trajflow table"):
        open_dataset(out).scenes()
    manifest = json.loads((out / "dataset.json").read_text())
    (out / "dataset.json").write_text(json.dumps({**manifest, "schema_version": 2}))
    with pytest.raises(DataError, match="schema version 2"):
        open_dataset(out)
    with pytest.raises(DataError, match="not a trajflow dataset"):
        open_dataset(tmp_path)


@pytest.mark.parametrize(("edit", "message"), [
    ({"dt": float("nan")}, "dt must be a positive number of seconds, not nan"),
    ({"dt": 0}, "dt must be a positive number of seconds, not 0.0"),
    ({"dt": -0.4}, "dt must be a positive number of seconds, not -0.4"),
    ({"protocol": "leave-one-out"}, "unknown protocol 'leave-one-out'"),
])
def test_manifests_every_command_refuses(tmp_path: Path, edit: dict, message: str) -> None:
    """open_dataset is how every command reads a dataset: a manifest it refuses is refused everywhere."""
    out = write_toy(tmp_path / "toy")
    manifest = json.loads((out / "dataset.json").read_text())
    (out / "dataset.json").write_text(json.dumps({**manifest, **edit}))
    with pytest.raises(DataError, match=f"dataset.json: {message}"):
        open_dataset(out)


def test_output_path_guard(tmp_path: Path) -> None:
    write_toy(tmp_path / "toy")
    other = DatasetMeta(dataset="other", dt=0.4, protocol=PROTOCOL_FOLDS)
    with pytest.raises(TrajflowError, match="already holds dataset 'toy', not 'other'"):
        DatasetWriter(tmp_path / "toy", other)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "thesis.tex").write_text("precious")
    with pytest.raises(TrajflowError, match="holds no trajflow dataset"):
        DatasetWriter(tmp_path / "notes", META)
    assert (tmp_path / "notes" / "thesis.tex").read_text() == "precious"
