"""An experiment's data stages: its ingest and its augmentations, each built only when what it depends on changed.

A config's ``[data]`` names the first stage (an ingest, or a dataset used as it is) and each ``[[augment]]`` step
one more, reading the dataset before it; the runs train on the last one's. A stage's identity is its kind, name
and options plus the content of what it reads: for an ingest the files of its raw input (relative paths, sizes,
SHA-256; only the files the adapter reads, see ``Ingest.inputs``), for an augmentation the ``data_sha256`` of the
dataset before it. After a build, the stage's record (``stage.json``, :mod:`trajflow_pipeline.schemas.stage_record`)
keeps the identity and the built dataset's ``data_sha256``. A stage is current when its dataset exists, its
record's identity is the one computed now and the dataset is still the one it built; otherwise it is built again
into the same path (replacing it atomically). So an unchanged config rebuilds nothing, and a changed augmentation
option rebuilds that step and the steps after it, not the ingest. The raw input's location is not part of the
identity: the same files elsewhere (``--set data.raw=PATH`` on another machine) are the same stage. Files whose
size and modification time are unchanged since the record was written are not hashed again.

A dataset at a stage's path without a record (made by hand, or a build interrupted before its record was written)
is built again; anything there that is not a trajflow dataset is left alone and refused, as ``trajflow ingest``
refuses it. The code of the ingests is not part of the identity: after an upgrade that changes what an ingest
writes, delete the dataset to have it built anew.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import TrajflowError, UsageError
from ..ingest.registry import get_ingest
from ..schemas import open_dataset
from ..schemas.stage_record import StageRecord, read_stage_record, write_stage_record
from ..util.claim import claim
from ..util.options import option_value
from ..util.progress import say
from .augment import AUGMENTATIONS
from .experiment_config import ExperimentConfig

#: raw bytes to hash above which the build says it is hashing (about a second at SHA-256's speed)
SAY_HASHING = 1_000_000_000
#: what a stage can be: built by this call, reused (current), stale or missing (to be built), or "given" (the
#: [data] path without an ingest: used as it is)
STATES = ("built", "reused", "stale", "missing", "given", "unknown")


@dataclass(frozen=True)
class DataStage:
    """One data stage of an experiment: an ingest, an augmentation, or the dataset given as it is."""

    #: "ingest", "augment" or "given"
    kind: str
    #: the ingest's registry name or the augmentation's kind ("" for a given dataset)
    name: str
    #: the dataset it writes (or, given, is)
    path: Path
    #: its options as the config gives them (an ingest's raw input aside)
    options: dict[str, Any]
    #: an ingest's raw input (None: generated data, or not an ingest)
    raw: Path | None = None
    #: an augmentation's source: the dataset of the stage before it
    source: Path | None = None

    @property
    def label(self) -> str:
        return f"{self.kind} {self.name}".strip()


@dataclass(frozen=True)
class StageState:
    """Where a stage stands: its state (:data:`STATES`) and why, with its record when it has one."""

    stage: DataStage
    state: str
    reason: str = ""
    record: StageRecord | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, for `trajflow status --json`."""
        return {"kind": self.stage.kind, "name": self.stage.name, "path": str(self.stage.path),
                "state": self.state, "reason": self.reason,
                "builds": self.record.builds if self.record else 0, "built": self.record.built if self.record else None}


def data_stages(config: ExperimentConfig) -> list[DataStage]:
    """The experiment's data stages in the order they are built."""
    options = dict(config.ingest_options)
    raw = options.pop("raw", None)
    first = (DataStage("ingest", config.ingest, config.source_path, options, None if raw is None else Path(raw))
             if config.ingest else DataStage("given", "", config.source_path, {}))
    stages = [first]
    for step in config.augment:
        stages.append(DataStage("augment", step.kind, step.path, step.options, source=stages[-1].path))
    return stages


def build_data(config: ExperimentConfig, *, quiet: bool = False) -> list[StageState]:
    """Build every data stage of the experiment that is not current (see the module docstring), in order; returns
    each stage's state ("built", "reused" or "given")."""
    states: list[StageState] = []
    upstream: str | None = None
    for stage in data_stages(config):
        if stage.kind == "given":
            if not (stage.path / "dataset.json").is_file():
                raise UsageError(f"{stage.path}: dataset not found, and the experiment config names no ingest to "
                                 "build it ([data] ingest)")
            upstream = open_dataset(stage.path).fingerprint()["data_sha256"]
            states.append(StageState(stage, "given", "used as it is ([data] names no ingest)"))
            continue
        with claim(stage.path.with_name(f".{stage.path.name}.stage.lock"), wait=True):  # one builder at a time
            state = _build(stage, upstream, quiet)
        states.append(state)
        assert state.record is not None
        upstream = state.record.output
    return states


def data_status(config: ExperimentConfig) -> list[StageState]:
    """Each data stage's state as it is now, building nothing: "reused" reads here as current. A stage after one
    that is stale or missing is stale too (it is built after it); one whose inputs cannot be read is "unknown"."""
    states: list[StageState] = []
    upstream: str | None = None
    for stage in data_stages(config):
        try:
            if stage.kind == "given":
                upstream = open_dataset(stage.path).fingerprint()["data_sha256"]
                states.append(StageState(stage, "given", "used as it is ([data] names no ingest)"))
                continue
            if states and states[-1].state == "unknown":
                states.append(StageState(stage, "unknown", "the stage before it could not be checked",
                                         read_stage_record(stage.path)))
                continue
            if states and states[-1].state not in ("reused", "given"):
                states.append(StageState(stage, "stale", "the stage before it is built again first",
                                         read_stage_record(stage.path)))
                continue
            identity, _ = _identity(stage, upstream, read_stage_record(stage.path))
            state, reason, record = _current(stage, identity)
            states.append(StageState(stage, "reused" if state == "current" else state, reason, record))
            upstream = record.output if record is not None else None
        except TrajflowError as error:
            states.append(StageState(stage, "unknown", str(error)))
            upstream = None
    return states


def _build(stage: DataStage, upstream: str | None, quiet: bool) -> StageState:
    """Build `stage` unless it is current; its state after."""
    before = read_stage_record(stage.path)
    identity, inputs = _identity(stage, upstream, before, quiet)
    state, reason, record = _current(stage, identity)
    if state == "current":
        if not quiet:
            say((f"data: {stage.label} -> {stage.path}: current, reused", "dim"))
        assert record is not None
        return StageState(stage, "reused", "", record)
    if before is None and stage.path.exists() and not (stage.path / "dataset.json").is_file() and (
            not stage.path.is_dir() or any(stage.path.iterdir())):
        raise UsageError(f"{stage.path}: holds something that is not a trajflow dataset, which the data stage "
                         f"{stage.label} will not replace; give the stage another path in the config")
    if not quiet:
        say((f"data: {stage.label} -> {stage.path}", "bold"), f" ({reason}): building")
    # Replace a dataset this stage built (its record says so) whatever it holds now; anything else only when it
    # is an earlier copy of the same dataset, as `trajflow ingest` would.
    _runner(stage)(overwrite=before is not None, quiet=quiet)
    built = StageRecord(kind=stage.kind, name=stage.name, identity=identity,
                        output=open_dataset(stage.path).fingerprint()["data_sha256"],
                        options=_canonical(_typed_options(stage)), inputs=inputs, upstream=upstream,
                        builds=(before.builds + 1) if before is not None else 1,
                        built=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"), version=__version__)
    write_stage_record(stage.path, built)
    return StageState(stage, "built", reason, built)


def _current(stage: DataStage, identity: str) -> tuple[str, str, StageRecord | None]:
    """("current" | "stale" | "missing", why, the record) of the stage whose identity now is `identity`."""
    if not (stage.path / "dataset.json").is_file():
        return "missing", "not built yet", None
    record = read_stage_record(stage.path)
    if record is None:
        return "stale", "no stage record: made outside an experiment, or its build was interrupted", None
    if record.identity != identity:
        return "stale", _what_changed(stage, record, identity), record
    if open_dataset(stage.path).fingerprint()["data_sha256"] != record.output:
        return "stale", "the dataset was replaced since this stage built it", record
    return "current", "", record


def _what_changed(stage: DataStage, record: StageRecord, identity: str) -> str:
    """In words, why the record's identity is not the one computed now."""
    options = _canonical(_typed_options(stage))
    if options != record.options:
        keys = sorted(k for k in {*options, *record.options} if options.get(k) != record.options.get(k))
        return "options changed: " + ", ".join(keys)
    if stage.kind == "augment":
        return "the dataset it augments changed"
    if stage.kind == "ingest" and stage.raw is not None:
        return "the raw input changed"
    return f"it was built by another kind of stage ({record.kind} {record.name})" if (
        record.kind, record.name) != (stage.kind, stage.name) else f"identity {record.identity[:12]} != {identity[:12]}"


def _identity(stage: DataStage, upstream: str | None, before: StageRecord | None,
              quiet: bool = True) -> tuple[str, list[dict[str, Any]]]:
    """The stage's identity (SHA-256, hex) and the fingerprints of the raw files it reads (ingests)."""
    inputs = _raw_fingerprints(stage, before, quiet) if stage.kind == "ingest" and stage.raw is not None else []
    payload = {"kind": stage.kind, "name": stage.name, "options": _canonical(_typed_options(stage)),
               "inputs": [[f["path"], f["size"], f["sha256"]] for f in inputs], "upstream": upstream}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest(), inputs


def _typed_options(stage: DataStage) -> dict[str, Any]:
    """The stage's options as its function takes them (a file an option names read: its content counts)."""
    if stage.kind == "ingest":
        return get_ingest(stage.name).config_options(stage.options, f"[data] of ingest {stage.name}")
    _, function = AUGMENTATIONS[stage.name]
    return {key: option_value(function, key, value) for key, value in stage.options.items()}


def _canonical(value: Any) -> Any:
    """`value` as plain JSON values (dataclasses as tables, tuples as lists, paths as strings), for hashing and
    for the record."""
    if is_dataclass(value) and not isinstance(value, type):
        return _canonical(asdict(value))
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def _raw_fingerprints(stage: DataStage, before: StageRecord | None, quiet: bool = True) -> list[dict[str, Any]]:
    """Relative path, size, modification time and SHA-256 of each raw file the ingest reads, sorted by path; a file
    of the same size and modification time as in the earlier record keeps its recorded hash (a line says so when
    more than :data:`SAY_HASHING` bytes are to be read)."""
    assert stage.raw is not None
    raw, adapter = stage.raw, get_ingest(stage.name)
    if not raw.exists():
        raise TrajflowError(f"{raw}: the raw input of {stage.label} does not exist")
    base = raw if raw.is_dir() else raw.parent
    if adapter.inputs is not None:
        files = adapter.inputs(raw, _typed_options(stage))
    else:
        files = [raw] if raw.is_file() else [p for p in raw.rglob("*") if p.is_file()]
    known = {entry["path"]: entry for entry in (before.inputs if before is not None else [])}
    files = sorted(files)
    stats = [path.stat() for path in files]
    names = [path.relative_to(base).as_posix() for path in files]
    hashes = [entry["sha256"] if (entry := known.get(name)) and (entry.get("size"), entry.get("mtime_ns")) == (
        stat.st_size, stat.st_mtime_ns) else None for name, stat in zip(names, stats)]
    to_read = sum(stat.st_size for stat, digest in zip(stats, hashes) if digest is None)
    if to_read > SAY_HASHING and not quiet:
        say((f"data: {stage.label}: hashing {hashes.count(None)} raw file(s), {to_read / 1e9:.1f} GB", "dim"))
    fingerprints = []
    for path, name, stat, digest in zip(files, names, stats, hashes):
        if digest is None:
            with path.open("rb") as handle:
                digest = hashlib.file_digest(handle, "sha256").hexdigest()
        fingerprints.append({"path": name, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "sha256": digest})
    return fingerprints


def _runner(stage: DataStage) -> Callable[..., Path]:
    """A call that builds the stage's dataset: ``(overwrite=..., quiet=...) -> path``."""
    if stage.kind == "ingest":
        adapter = get_ingest(stage.name)
        options = _typed_options(stage)
        return lambda **flags: adapter.run(stage.raw, stage.path, **flags, **options)
    _, function = AUGMENTATIONS[stage.name]
    return lambda **flags: function(stage.source, stage.path, **flags, **_typed_options(stage))
