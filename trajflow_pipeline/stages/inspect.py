"""`trajflow inspect`: what a dataset directory holds, for people (rich tables) and scripts (JSON)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import polars as pl

from ..schemas import PROTOCOL_FOLDS, open_dataset


def summarize(path: str | Path) -> dict[str, Any]:
    """Counts and metadata of a dataset: scenes, agents, rows, samples per fold / split, agent types."""
    ds = open_dataset(path)
    scenes, samples = ds.scenes(), ds.samples()
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
        "lineage": ds.lineage,
    }
