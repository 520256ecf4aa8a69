"""Reading and writing dataset directories: Parquet files with contract metadata, written atomically.

Layout of a dataset directory::

    DATA/dataset.json              manifest: schema version, dataset name, dt, protocol, counts, lineage
    DATA/scenes.parquet
    DATA/samples.parquet
    DATA/tracks/part-00000.parquet sorted by (scene_id, agent_id, frame); a scene never spans two shards
    DATA/maps/...                  optional raster maps referenced by scenes.map_path
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterator
from contextlib import AbstractContextManager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from .. import __version__
from ..errors import DataError, TrajflowError
from ..util import input_files
from ..util.atomic import atomic_directory, atomic_write_text, recover
from .tables import (META_DATASET, META_DT, META_PROTOCOL, META_SCHEMA_VERSION, META_TABLE, META_VERSION,
                     PROTOCOLS, SAMPLES, SCENES, SCHEMA_VERSION, TRACKS, TableSpec, conform)
from .validate import (shard_scenes, validate_columns, validate_references, validate_shard_scenes,
                       validate_table)

MANIFEST = "dataset.json"
TRACKS_DIR = "tracks"
DEFAULT_SHARD_ROWS = 1_000_000
# Manifest entries that say where inputs lay, not what they held: raw folders in lineages, and the path and
# whole-manifest hash of a source dataset's fingerprint (which holds its own raw folder).
LOCATION_KEYS = frozenset({"raw", "path", "manifest_sha256"})


@dataclass(frozen=True)
class DatasetMeta:
    """What every file of a dataset says about the dataset it belongs to."""

    dataset: str
    dt: float
    protocol: str
    schema_version: int = SCHEMA_VERSION
    version: str = __version__

    def parquet_metadata(self, table: str) -> dict[bytes, bytes]:
        """Key-value metadata stored in the footer of each Parquet file."""
        values = {META_SCHEMA_VERSION: str(self.schema_version), META_DATASET: self.dataset,
                  META_DT: repr(float(self.dt)), META_VERSION: self.version, META_PROTOCOL: self.protocol,
                  META_TABLE: table}
        return {key.encode(): value.encode() for key, value in values.items()}


def write_table(frame: pl.DataFrame, spec: TableSpec, path: Path, meta: DatasetMeta,
                display_path: Path | None = None) -> None:
    """Validate `frame` against `spec` and write it to `path` with the dataset's metadata.

    Errors name `display_path` (the file's final location) when the file is written to a temporary place.
    """
    frame = conform(frame, spec)
    validate_table(frame, spec, display_path or path)
    table = frame.to_arrow()
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta.parquet_metadata(spec.name)})
    pq.write_table(table, path, compression="zstd")


class DatasetWriter(AbstractContextManager["DatasetWriter"]):
    """Writes a dataset into a temporary directory that replaces `out` only when :meth:`finish` succeeded.

    Tracks are added scene group by scene group (streaming), buffered and flushed as shards of about
    `shard_rows` rows; the scenes and samples tables and the manifest are written by :meth:`finish`.
    """

    def __init__(self, out: str | Path, meta: DatasetMeta, *, overwrite: bool = False,
                 shard_rows: int = DEFAULT_SHARD_ROWS) -> None:
        if meta.protocol not in PROTOCOLS:
            raise ValueError(f"unknown protocol {meta.protocol!r}")
        self.out = Path(out)
        self.meta = meta
        self.shard_rows = shard_rows
        check_output_path(self.out, meta.dataset, overwrite=overwrite)
        self._atomic = atomic_directory(self.out)
        self._buffer: list[pl.DataFrame] = []
        self._buffered_rows = 0
        self._shards = 0
        self.tracks_rows = 0
        self._finished = False
        self.root = Path()

    def __enter__(self) -> "DatasetWriter":
        self.root = self._atomic.__enter__()
        (self.root / TRACKS_DIR).mkdir()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool | None:
        if exc_type is None and not self._finished:
            exc_type, exc = RuntimeError, RuntimeError("DatasetWriter closed without finish()")
        return self._atomic.__exit__(exc_type, exc, tb)

    def add_tracks(self, tracks: pl.DataFrame) -> None:
        """Queue the tracks of one or more whole scenes (sorted by scene, agent, frame) for writing."""
        if tracks.height == 0:
            return
        self._buffer.append(tracks)
        self._buffered_rows += tracks.height
        if self._buffered_rows >= self.shard_rows:
            self._flush()

    def _flush(self) -> None:
        if not self._buffer:
            return
        shard = pl.concat(self._buffer, how="diagonal_relaxed")
        name = f"{TRACKS_DIR}/part-{self._shards:05d}.parquet"
        write_table(shard, TRACKS, self.root / name, self.meta, self.out / name)
        self._shards += 1
        self.tracks_rows += shard.height
        self._buffer, self._buffered_rows = [], 0

    def finish(self, scenes: pl.DataFrame, samples: pl.DataFrame, lineage: dict[str, Any] | None = None) -> None:
        """Write the remaining tracks, the scenes and samples tables and the manifest."""
        self._flush()
        validate_references(samples, scenes, self.out / "samples.parquet")
        write_table(scenes, SCENES, self.root / "scenes.parquet", self.meta, self.out / "scenes.parquet")
        write_table(samples, SAMPLES, self.root / "samples.parquet", self.meta, self.out / "samples.parquet")
        manifest = {**asdict(self.meta), "counts": {"scenes": scenes.height, "samples": samples.height,
                                                     "tracks": self.tracks_rows, "track_shards": self._shards},
                    "lineage": lineage or {}}
        atomic_write_text(self.root / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        self._finished = True


def check_output_path(out: Path, dataset: str, *, overwrite: bool) -> None:
    """Refuse to replace anything but an earlier copy of the same dataset (unless `overwrite`)."""
    if not out.exists() or overwrite:
        return
    if not out.is_dir():
        raise TrajflowError(f"{out}: output path exists and is not a directory (pass --overwrite to replace it)")
    if not any(out.iterdir()):
        return
    manifest = out / MANIFEST
    if not manifest.exists():
        raise TrajflowError(f"{out}: output directory is not empty and holds no trajflow dataset; "
                            "choose another path or pass --overwrite")
    try:
        existing = json.loads(input_files.read_text(manifest)).get("dataset")
    except (TrajflowError, OSError, json.JSONDecodeError, AttributeError):  # unreadable, or not a JSON object
        existing = None
    if existing != dataset:
        raise TrajflowError(f"{out}: output path already holds dataset '{existing}', not '{dataset}'; "
                            "choose another path or pass --overwrite")


def _read_parquet(path: Path, spec: TableSpec) -> tuple[pl.DataFrame, dict[str, str]]:
    """Read one Parquet file of the dataset, turning unreadable files into a DataError naming them."""
    if not path.exists():
        raise DataError(f"{spec.name} table is missing", path=path)
    try:
        table = pq.read_table(input_files.regular_file(path))
    except (pa.ArrowException, OSError) as error:
        raise DataError(f"cannot read Parquet file ({error})", path=path) from None
    metadata = {k.decode(errors="replace"): v.decode(errors="replace")
                for k, v in (table.schema.metadata or {}).items() if k.startswith(b"trajflow.")}
    frame = pl.from_arrow(table)
    assert isinstance(frame, pl.DataFrame)
    return frame, metadata


@dataclass
class Dataset:
    """An opened dataset directory: its manifest, with validated access to its tables."""

    path: Path
    meta: DatasetMeta
    counts: dict[str, int] = field(default_factory=dict)
    lineage: dict[str, Any] = field(default_factory=dict)

    @property
    def track_shards(self) -> list[Path]:
        return sorted((self.path / TRACKS_DIR).glob("part-*.parquet"))

    def _check_metadata(self, path: Path, metadata: dict[str, str], table: str) -> None:
        version = metadata.get(META_SCHEMA_VERSION)
        if version is None:
            raise DataError("not a trajflow table (no trajflow.schema_version metadata)", path=path)
        if not version.isdigit() or int(version) != SCHEMA_VERSION:
            raise DataError(f"schema version {version}, this trajflow reads version {SCHEMA_VERSION}", path=path)
        if metadata.get(META_DATASET) != self.meta.dataset:
            raise DataError(f"belongs to dataset '{metadata.get(META_DATASET)}', not '{self.meta.dataset}'",
                            path=path)
        if metadata.get(META_TABLE) not in (None, table):
            raise DataError(f"holds table '{metadata.get(META_TABLE)}', expected '{table}'", path=path)

    def _table(self, spec: TableSpec, path: Path) -> pl.DataFrame:
        frame, metadata = _read_parquet(path, spec)
        self._check_metadata(path, metadata, spec.name)
        validate_table(frame, spec, path)
        return frame

    def scenes(self) -> pl.DataFrame:
        """The validated scenes table."""
        return self._table(SCENES, self.path / "scenes.parquet")

    def samples(self) -> pl.DataFrame:
        """The validated samples table."""
        return self._table(SAMPLES, self.path / "samples.parquet")

    def iter_track_shards(self) -> Iterator[tuple[Path, pl.DataFrame]]:
        """Each tracks shard, fully validated, one at a time (memory bounded by the shard size and a row per
        scene): its own contents (:func:`validate_table`), and against the others and the scenes table (every row's
        scene exists, no scene continues from an earlier shard), so that every reader of the tracks, whatever
        part of them it keeps, sees the same checked table."""
        shards = self.track_shards
        if not shards:
            raise DataError("tracks table is missing (no tracks/part-*.parquet)", path=self.path / TRACKS_DIR)
        scene_ids = self.scenes().select("scene_id")
        earlier = shard_scenes(pl.DataFrame(schema={"scene_id": pl.String()}), "")
        for shard in shards:
            frame = self._table(TRACKS, shard)
            validate_references(frame, scene_ids, shard, table=TRACKS.name)
            validate_shard_scenes(frame, earlier, shard)
            earlier = pl.concat([earlier, shard_scenes(frame, shard)], rechunk=False)
            yield shard, frame

    def tracks(self) -> pl.DataFrame:
        """All tracks, validated shard by shard (use :meth:`scan_tracks` for larger-than-memory data)."""
        return pl.concat([frame for _, frame in self.iter_track_shards()], how="diagonal_relaxed")

    def scan_tracks(self) -> pl.LazyFrame:
        """A lazy polars scan over all shards, after checking each shard's schema and metadata."""
        shards = self.track_shards
        if not shards:
            raise DataError("tracks table is missing (no tracks/part-*.parquet)", path=self.path / TRACKS_DIR)
        for shard in shards:
            try:
                schema = pq.read_schema(input_files.regular_file(shard))
            except (pa.ArrowException, OSError) as error:
                raise DataError(f"cannot read Parquet file ({error})", path=shard) from None
            metadata = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()
                        if k.startswith(b"trajflow.")}
            self._check_metadata(shard, metadata, TRACKS.name)
            validate_columns(pl.Schema(pl.from_arrow(schema.empty_table()).schema), TRACKS, shard)
        return input_files.scan_parquet(shards)

    def map_file(self, relative: str, scene: str | None = None) -> Path:
        """The raster file a scenes row's `map_path` names, checked to lie inside the dataset directory once links
        are followed (the table checks refuse absolute and '..' paths; a link could still lead out) and to be a
        regular file."""
        path = self.path / relative
        of_scene = f" of scene '{scene}'" if scene is not None else ""
        if not path.exists():
            raise DataError(f"map raster{of_scene} is missing", path=path)
        if not path.resolve().is_relative_to(self.path.resolve()):
            raise DataError(f"map raster{of_scene} leads outside the dataset directory (to {path.resolve()})",
                            path=path)
        return input_files.regular_file(path)

    def fingerprint(self) -> dict[str, str]:
        """Identifies the data a run was trained on: path, manifest metadata, a hash of the manifest and one of
        the manifest less the places its inputs lay (``data_sha256``: the same for a copy ingested elsewhere)."""
        manifest = input_files.read_bytes(self.path / MANIFEST)
        placeless = json.dumps(_without_locations(json.loads(manifest)), sort_keys=True).encode()
        return {"path": str(self.path.resolve()), "dataset": self.meta.dataset, "dt": repr(self.meta.dt),
                "protocol": self.meta.protocol, "schema_version": str(self.meta.schema_version),
                "written_by": self.meta.version, "manifest_sha256": hashlib.sha256(manifest).hexdigest(),
                "data_sha256": hashlib.sha256(placeless).hexdigest()}


def _without_locations(value: Any) -> Any:
    """A manifest less every :data:`LOCATION_KEYS` entry, at any depth (lineages nest source fingerprints)."""
    if isinstance(value, dict):
        return {key: _without_locations(item) for key, item in value.items() if key not in LOCATION_KEYS}
    if isinstance(value, list):
        return [_without_locations(item) for item in value]
    return value


def data_mismatch(trained: dict[str, str], given: dict[str, str]) -> str | None:
    """How the data `given` (a fingerprint) differs from the data a run recorded as `trained`, or None.

    Compares the dataset name and ``data_sha256``, so the same raw files ingested in another folder match;
    fingerprints recorded before ``data_sha256`` existed compare the whole manifest's hash.
    """
    digest = "data_sha256" if "data_sha256" in trained and "data_sha256" in given else "manifest_sha256"
    for key in ("dataset", digest):
        if key in trained and trained[key] != given.get(key):
            return f"{key}: run has {trained[key]!r}, data has {given.get(key)!r}"
    return None


def open_dataset(path: str | Path) -> Dataset:
    """Open a dataset directory written by trajflow, checking its manifest."""
    path = Path(path)
    if not path.is_dir():
        recover(path)  # an interrupted replacement may have left the previous version aside
    if not path.is_dir():
        raise DataError("dataset directory not found", path=path)
    manifest_path = path / MANIFEST
    if not manifest_path.exists():
        raise DataError(f"not a trajflow dataset ({MANIFEST} is missing)", path=path)
    try:
        manifest = json.loads(input_files.read_text(manifest_path))
        meta = DatasetMeta(dataset=str(manifest["dataset"]), dt=float(manifest["dt"]),
                           protocol=str(manifest["protocol"]), schema_version=int(manifest["schema_version"]),
                           version=str(manifest["version"]))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise DataError(f"unreadable manifest ({error})", path=manifest_path) from None
    if meta.schema_version != SCHEMA_VERSION:
        raise DataError(f"schema version {meta.schema_version}, this trajflow reads version {SCHEMA_VERSION}",
                        path=manifest_path)
    if not (math.isfinite(meta.dt) and meta.dt > 0):
        raise DataError(f"dt must be a positive number of seconds, not {meta.dt}", path=manifest_path)
    if meta.protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {meta.protocol!r} (one of {', '.join(PROTOCOLS)})", path=manifest_path)
    return Dataset(path=path, meta=meta, counts=manifest.get("counts", {}), lineage=manifest.get("lineage", {}))
