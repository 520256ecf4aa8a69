"""`trajflow ingest eth-ucy`: the ETH/UCY pedestrian sequences as a unified Parquet dataset.

Reads the Social-GAN / Trajectron++ layout (``<location>/{train,val,test}/*.txt``) or a flat folder of the
eight full sequences (``all_data/``). The layout repeats every sequence several times; each is ingested once.

Protocol (the paper's strict one): every pedestrian at every frame t0 with 8 past and 12 future positions on
consecutive frames becomes a sample. Leave-one-location-out folds: eth, hotel, univ (students001 + 003), zara1,
zara2; crowds_zara03 and uni_examples only ever train. Inside a training sequence the standard split cuts at a
frame: windows entirely before it are `train`, entirely after it `val`; windows across it serve only as test.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from ..errors import DataError, TrajflowError
from ..schemas import PROTOCOL_FOLDS, DatasetMeta, DatasetWriter
from ..util import input_files
from ..util.progress import make_progress
from .base import Ingest
from .textfile import read_numeric_tables
from .windows import complete_windows, identical_input_groups

DATASET = "eth_ucy"
DT = 0.4
RAW_FRAME_STEP = 10
N_PAST, N_FUTURE = 8, 12

#: sequence name -> recording location; the five leave-one-out folds are named after their location
SEQUENCES: dict[str, str] = {
    "biwi_eth": "eth", "biwi_hotel": "hotel", "students001": "univ", "students003": "univ",
    "crowds_zara01": "zara1", "crowds_zara02": "zara2", "crowds_zara03": "zara3", "uni_examples": "uni_examples",
}
FOLDS = ("eth", "hotel", "univ", "zara1", "zara2")

#: First raw frame of each sequence's `*_val.txt` in the standard layout: the train/val cut used when only the
#: flat folder of full sequences is given. Ingesting the layout reads the cut from the files themselves, and the
#: tests check that both agree on the shared copy.
STANDARD_VAL_START_RAW_FRAME: dict[str, int] = {
    "biwi_eth": 10240, "biwi_hotel": 14400, "students001": 3550, "students003": 4320,
    "crowds_zara01": 7110, "crowds_zara02": 8420, "crowds_zara03": 6030, "uni_examples": 5940,
}


@dataclass
class SequenceSource:
    """Where one sequence's lines come from: the files whose concatenation is the full sequence."""

    name: str
    files: list[Path]
    val_start_raw_frame: int
    val_file: Path | None = None
    read_from: list[Path] = field(default_factory=list)


def _is_layout(raw: Path) -> bool:
    return any((raw / loc / split).is_dir() for loc in FOLDS for split in ("train", "val", "test"))


def _layout_sources(raw: Path) -> dict[str, SequenceSource]:
    """Locate each sequence once in the Trajectron++ layout, preferring the full test copy."""
    missing = [loc for loc in FOLDS if not (raw / loc).is_dir()]
    if missing:
        raise DataError(f"location folder(s) {', '.join(missing)} missing from the ETH/UCY layout "
                        f"(expected {', '.join(FOLDS)}, each with train/val/test)", path=raw)
    sources: dict[str, SequenceSource] = {}
    for name, location in SEQUENCES.items():
        test_copy = raw / location / "test" / f"{name}.txt"
        train_copies = sorted(raw.glob(f"*/train/{name}_train.txt"))
        val_copies = sorted(raw.glob(f"*/val/{name}_val.txt"))
        if test_copy.exists():
            files = [test_copy]
        elif train_copies and val_copies:
            train_copy = train_copies[0]
            files = [train_copy, train_copy.parent.parent / "val" / f"{name}_val.txt"]
        else:
            raise DataError(f"sequence '{name}' not found: expected {location}/test/{name}.txt or "
                            f"<location>/train/{name}_train.txt with its _val.txt", path=raw)
        if not val_copies:
            raise DataError(f"no <location>/val/{name}_val.txt: the train/val cut of '{name}' is unknown",
                            path=raw)
        sources[name] = SequenceSource(name=name, files=files, val_start_raw_frame=-1, val_file=val_copies[0])
    return sources


def _flat_sources(folder: Path) -> dict[str, SequenceSource]:
    """The eight full sequences as `<name>.txt` in one folder; the cut is the standard one."""
    missing = [f"{name}.txt" for name in SEQUENCES if not (folder / f"{name}.txt").is_file()]
    if missing:
        raise DataError(f"missing sequence file(s) {', '.join(missing)} (a flat ETH/UCY folder holds all eight)",
                        path=folder)
    return {name: SequenceSource(name=name, files=[folder / f"{name}.txt"],
                                 val_start_raw_frame=STANDARD_VAL_START_RAW_FRAME[name])
            for name in SEQUENCES}


def discover_sources(raw: Path) -> dict[str, SequenceSource]:
    """Recognise the layout of `raw` and find every sequence exactly once."""
    if not raw.exists():
        raise DataError("raw ETH/UCY folder not found", path=raw)
    if not raw.is_dir():
        raise DataError("expected a folder (the ETH/UCY layout or the flat folder of eight sequences)", path=raw)
    if _is_layout(raw):
        return _layout_sources(raw)
    if (raw / "all_data").is_dir():
        return _flat_sources(raw / "all_data")
    if not any(raw.iterdir()):
        raise DataError("folder is empty", path=raw)
    return _flat_sources(raw)


def _read_tracks(sources: dict[str, SequenceSource]) -> pl.DataFrame:
    """All lines of every sequence as tracks rows, with integer frames and pedestrian ids checked.

    Every file is parsed in one pass, sorted once into the contract's order (stable, so of two rows with the same
    key the earlier line comes first) and checked by one query; only when a check fails is the first offending
    line looked up to name its file and line.
    """
    files = [(name, path) for name, source in sources.items() for path in source.files]
    scene_names = sorted(sources)
    lines = (read_numeric_tables([path for _, path in files], ("frame", "ped", "x", "y"))
             .with_columns(__scene=pl.col("file").replace_strict(
                 range(len(files)), [scene_names.index(name) for name, _ in files], return_dtype=pl.Int64))
             .sort("__scene", "ped", "frame", maintain_order=True))
    same_key = pl.all_horizontal(pl.col(name) == pl.col(name).shift(1) for name in ("__scene", "ped", "frame"))
    checks = {
        "__fractional_frame": pl.col("frame") != pl.col("frame").round(),
        "__fractional_ped": pl.col("ped") != pl.col("ped").round(),
        "__off_step": pl.col("frame") % RAW_FRAME_STEP != 0,
        "__duplicate": same_key.fill_null(False),
    }
    problems = lines.with_columns(**checks).filter(pl.any_horizontal(*checks)).sort("file", "line").head(1)
    if problems.height:
        _raise_line_problem(problems.row(0, named=True), lines, [path for _, path in files])
    frame = (pl.col("frame") / RAW_FRAME_STEP).round().cast(pl.Int64)
    return lines.select(
        pl.col("__scene").replace_strict(range(len(scene_names)), scene_names, return_dtype=pl.String)
        .alias("scene_id"),
        pl.col("ped").cast(pl.Int64).alias("agent_id"),
        pl.lit("pedestrian").alias("agent_type"),
        frame.alias("frame"),
        (frame.cast(pl.Float64) * DT).alias("t"),
        "x", "y",
    )


def _raise_line_problem(problem: dict, lines: pl.DataFrame, paths: list[Path]) -> None:
    """Explain the first line that failed a check of :func:`_read_tracks` (checks in the order listed there)."""
    path, line = paths[problem["file"]], problem["line"]
    for column in ("frame", "ped"):
        if problem[column] != round(problem[column]):
            raise DataError(f"{column} must be a whole number, got {problem[column]}", path=path, line=line)
    if problem["__off_step"]:
        raise DataError(f"frame {problem['frame']:g} is not a multiple of the frame step {RAW_FRAME_STEP}",
                        path=path, line=line)
    first = (lines.filter((pl.col("__scene") == problem["__scene"]) & (pl.col("frame") == problem["frame"])
                          & (pl.col("ped") == problem["ped"])).sort("file", "line").row(0, named=True))
    raise DataError(f"duplicate row for frame {problem['frame']:g}, pedestrian {problem['ped']:g} "
                    f"(first at {paths[first['file']].name}:{first['line']})", path=path, line=line)


def _val_start_raw_frame(source: SequenceSource) -> int:
    if source.val_file is None:
        return source.val_start_raw_frame
    with open(input_files.regular_file(source.val_file), encoding="utf-8") as handle:
        for number, line in enumerate(handle, start=1):
            if line.strip():
                try:
                    return int(float(line.split()[0]))
                except ValueError:
                    raise DataError(f"frame is not a number: {line.split()[0]!r}", path=source.val_file,
                                    line=number) from None
    raise DataError("file is empty", path=source.val_file)


def _samples(tracks: pl.DataFrame, scenes: pl.DataFrame) -> pl.DataFrame:
    """Every complete 8 + 12 window, tagged with its fold (test location) and train/val segment."""
    windows = complete_windows(tracks, N_PAST, N_FUTURE).join(
        scenes.select("scene_id", "fold", "val_start_frame"), on="scene_id", how="left")
    segment = (pl.when(pl.col("t0_frame") + N_FUTURE < pl.col("val_start_frame")).then(pl.lit("train"))
               .when(pl.col("t0_frame") - (N_PAST - 1) >= pl.col("val_start_frame")).then(pl.lit("val"))
               .otherwise(pl.lit(None, dtype=pl.String)))
    samples = (windows.sort("scene_id", "t0_frame", "agent_id")
               .with_row_index("sample_id")
               .select(pl.col("sample_id").cast(pl.Int64), "scene_id", "agent_id", "t0_frame",
                       pl.lit(N_PAST, dtype=pl.Int64).alias("n_past"),
                       pl.lit(N_FUTURE, dtype=pl.Int64).alias("n_future"),
                       segment.alias("split"), "fold",
                       _change_count("scene_id", "t0_frame").alias("joint_id")))
    return samples.with_columns(group_id=identical_input_groups(samples, tracks))


def _change_count(*columns: str) -> pl.Expr:
    """0, 1, 2, ...: how many times `columns` changed value from the first row on (a dense id of rows sorted by
    them, without ranking)."""
    changed = pl.any_horizontal(pl.col(name) != pl.col(name).shift(1) for name in columns).fill_null(False)
    return changed.cum_sum().cast(pl.Int64)


def ingest_eth_ucy(raw: str | Path, out: str | Path, *, overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest ETH/UCY from `raw` into the dataset directory `out`; returns `out`.

    The dataset is written to a temporary directory and moved into place only when complete.
    """
    raw, out = Path(raw), Path(out)
    sources = discover_sources(raw)
    meta = DatasetMeta(dataset=DATASET, dt=DT, protocol=PROTOCOL_FOLDS)
    with make_progress(quiet) as progress:
        task = progress.add_task("reading ETH/UCY sequences", total=None)
        tracks = _read_tracks(sources)
        progress.update(task, total=1, completed=1)
    scenes = pl.DataFrame([_scene_row(name, source, raw) for name, source in sources.items()],
                          schema_overrides={"fold": pl.String, "val_start_frame": pl.Int64})
    samples = _samples(tracks, scenes)
    if samples.height == 0:
        raise TrajflowError(f"{raw}: no pedestrian has {N_PAST + N_FUTURE} consecutive frames; no samples")
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        writer.add_tracks(tracks)
        writer.finish(scenes, samples, lineage={"raw": str(raw.resolve()), "n_past": N_PAST,
                                                "n_future": N_FUTURE, "raw_frame_step": RAW_FRAME_STEP})
    return out


def _scene_row(name: str, source: SequenceSource, raw: Path) -> dict[str, object]:
    """The scenes-table row of one sequence: its location, fold, source files and train/val cut."""
    location = SEQUENCES[name]
    return {"dataset": DATASET, "scene_id": name, "location": location, "dt": DT,
            "source": ";".join(_relative(path, raw) for path in source.files),
            "fold": location if location in FOLDS else None,
            "val_start_frame": _val_start_raw_frame(source) // RAW_FRAME_STEP}


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


ADAPTER = Ingest(name="eth-ucy", dataset=DATASET, dt=DT, folds=FOLDS, raw="the raw ETH/UCY folder",
                 function=ingest_eth_ucy)
