"""`trajflow inspect`: what a dataset directory holds, for people (rich tables) and scripts (JSON).

Opening a dataset checks the manifest, the scenes and samples tables and the tracks shards' schema and metadata;
`check_tracks` also validates the contents of every tracks shard, streaming them one at a time, so that bad rows
show up here rather than halfway through a training run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import polars as pl

from ..schemas import PROTOCOL_FOLDS, Dataset, open_dataset
from ..schemas.validate import TracksContentCheck, validate_references


def check_tracks(ds: Dataset, samples: pl.DataFrame) -> None:
    """Validate the contents of every tracks shard, one shard in memory at a time.

    What every read of the tracks checks (training and evaluation included): per shard nulls, NaN or infinite
    values, agent types, duplicated (scene_id, agent_id, frame) keys and sort order; rows of scenes missing from
    the scenes table, scenes spanning two shards. Here also: samples whose window is not complete in the tracks.
    Raises a DataError naming the file and the offending rows.
    """
    check = TracksContentCheck(samples, ds.path / "samples.parquet")
    for _, tracks in ds.iter_track_shards():
        check.add_shard(tracks)
        del tracks  # let it go before the next shard is read: one shard in memory, not two
    check.finish()


def summarize(path: str | Path, *, check_tracks_contents: bool = False) -> dict[str, Any]:
    """Counts and metadata of a dataset: scenes, agents, rows, samples per fold / split, agent types.

    `check_tracks_contents` also reads every tracks shard in full to validate it (:func:`check_tracks`); off by
    default because writers already validate each shard, and the scan costs a full read of the tracks.
    """
    ds = open_dataset(path)
    scenes, samples = ds.scenes(), ds.samples()
    validate_references(samples, scenes, ds.path / "samples.parquet")
    if check_tracks_contents:
        check_tracks(ds, samples)
    tracks = ds.scan_tracks()
    agents = tracks.select(pl.struct("scene_id", "agent_id").n_unique()).collect().item()
    types = (tracks.group_by("agent_type").agg(pl.struct("scene_id", "agent_id").n_unique().alias("agents"),
                                               pl.len().alias("rows"))
             .sort("agent_type").collect())
    by_split = (samples.group_by("fold", "split").agg(pl.len().alias("samples"), pl.col("group_id").n_unique()
                                                      .alias("groups"))
                .sort("fold", "split", nulls_last=True))
    by_location = (samples.join(scenes.select("scene_id", "location"), on="scene_id")
                   .group_by("location").agg(pl.len().alias("samples")).sort("location"))
    return {
        "path": str(ds.path), "dataset": ds.meta.dataset, "schema_version": ds.meta.schema_version,
        "written_by": ds.meta.version, "protocol": ds.meta.protocol,
        "dt": sorted(scenes.get_column("dt").unique().to_list()),
        "scenes": scenes.height, "agents": agents, "track_rows": sum(types.get_column("rows").to_list()),
        "track_shards": len(ds.track_shards), "samples": samples.height,
        "groups": samples.get_column("group_id").n_unique(),
        "horizons": samples.group_by("n_past", "n_future").len().sort("n_past", "n_future").rows(named=True),
        "folds": (samples.get_column("fold").drop_nulls().unique().sort().to_list()
                  if ds.meta.protocol == PROTOCOL_FOLDS else []),
        "samples_by_fold_and_split": by_split.rows(named=True),
        "samples_by_location": by_location.rows(named=True),
        "agent_types": types.rows(named=True),
        "has_map": "map_path" in scenes.columns and scenes.get_column("map_path").null_count() < scenes.height,
        "tracks_checked": check_tracks_contents,
        "lineage": ds.lineage,
    }
