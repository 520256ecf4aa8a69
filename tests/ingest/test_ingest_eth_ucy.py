"""ETH/UCY ingest on the real shared copy, checked against counts computed independently from the raw files."""

from __future__ import annotations

import shutil
from collections import defaultdict
from pathlib import Path

import polars as pl
import pytest

from trajflow_pipeline.data import list_folds, load_problems, select_samples
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import data_mismatch, open_dataset
from trajflow_pipeline.ingest.eth_ucy import (FOLDS, SEQUENCES, STANDARD_VAL_START_RAW_FRAME,
                                              discover_sources, ingest_eth_ucy)

WINDOW = 20  # 8 past + 12 future


def raw_windows(path: Path) -> set[tuple[int, int]]:
    """(pedestrian, t0 raw frame) of every complete 20-frame window, by plain Python set lookups."""
    frames: dict[int, set[int]] = defaultdict(set)
    for line in path.read_text().splitlines():
        if line.strip():
            frame, ped, _, _ = (float(v) for v in line.split())
            frames[int(ped)].add(int(frame))
    return {(ped, f + 70) for ped, fs in frames.items() for f in fs
            if all(f + 10 * k in fs for k in range(WINDOW))}


def ingested_windows(samples: pl.DataFrame, scenes: list[str] | None = None) -> set[tuple[str, int, int]]:
    if scenes is not None:
        samples = samples.filter(pl.col("scene_id").is_in(scenes))
    return {(s, a, 10 * t) for s, a, t in samples.select("scene_id", "agent_id", "t0_frame").iter_rows()}


def test_tracks_hold_one_row_per_raw_line(eth_ucy_raw: Path, eth_ucy_dataset: Path) -> None:
    ds = open_dataset(eth_ucy_dataset)
    raw_lines = sum(1 for f in (eth_ucy_raw / "all_data").glob("*.txt") for line in f.read_text().splitlines()
                    if line.strip())
    assert raw_lines == 74_428
    assert ds.tracks().height == 74_428
    assert ds.counts["tracks"] == 74_428
    assert ds.meta.dt == 0.4
    scenes = ds.scenes()
    assert sorted(scenes.get_column("scene_id")) == sorted(SEQUENCES)
    assert set(ds.tracks().get_column("agent_type").unique()) == {"pedestrian"}


def test_sample_counts_per_location_match_an_independent_count(eth_ucy_raw: Path, eth_ucy_dataset: Path) -> None:
    ds = open_dataset(eth_ucy_dataset)
    samples = ds.samples()
    expected = {name: raw_windows(eth_ucy_raw / "all_data" / f"{name}.txt") for name in SEQUENCES}
    for name, windows in expected.items():
        got = ingested_windows(samples, [name])
        assert got == {(name, ped, t0) for ped, t0 in windows}, name
    per_location = samples.join(ds.scenes().select("scene_id", "location"), on="scene_id").group_by(
        "location").len()
    counts = dict(per_location.iter_rows())
    for location in FOLDS:
        assert counts[location] == sum(len(w) for n, w in expected.items() if SEQUENCES[n] == location)
    assert (samples.get_column("n_past") == 8).all() and (samples.get_column("n_future") == 12).all()


@pytest.mark.parametrize("fold", FOLDS)
def test_folds_reproduce_the_standard_split(eth_ucy_raw: Path, eth_ucy_dataset: Path, fold: str) -> None:
    """train / val / test of a fold are exactly the windows found in that fold's standard split files."""
    ds = open_dataset(eth_ucy_dataset)
    for split in ("train", "val", "test"):
        expected = set()
        for path in (eth_ucy_raw / fold / split).glob("*.txt"):
            name = path.stem.removesuffix(f"_{split}")
            expected |= {(name, ped, t0) for ped, t0 in raw_windows(path)}
        got = ingested_windows(select_samples(ds, fold, split))
        assert got == expected, (fold, split, len(got), len(expected))


def test_no_training_sample_comes_from_the_test_location(eth_ucy_dataset: Path) -> None:
    ds = open_dataset(eth_ucy_dataset)
    location = dict(ds.scenes().select("scene_id", "location").iter_rows())
    for fold in list_folds(ds):
        for split in ("train", "val"):
            scenes = set(select_samples(ds, fold, split).get_column("scene_id"))
            assert fold not in {location[s] for s in scenes}
        assert {location[s] for s in select_samples(ds, fold, "test").get_column("scene_id")} == {fold}
    train_only = ds.samples().filter(pl.col("scene_id").is_in(["crowds_zara03", "uni_examples"]))
    assert train_only.get_column("fold").null_count() == train_only.height


def test_standard_cut_table_matches_the_layout(eth_ucy_raw: Path) -> None:
    sources = discover_sources(eth_ucy_raw)
    for name, source in sources.items():
        first_val = min(int(float(line.split()[0])) for line in source.val_file.read_text().splitlines() if line)
        assert first_val == STANDARD_VAL_START_RAW_FRAME[name]


def test_flat_folder_gives_the_same_dataset(eth_ucy_raw: Path, eth_ucy_dataset: Path, tmp_path: Path) -> None:
    flat = ingest_eth_ucy(eth_ucy_raw / "all_data", tmp_path / "flat", quiet=True)
    a, b = open_dataset(eth_ucy_dataset), open_dataset(flat)
    assert a.tracks().equals(b.tracks())
    assert a.samples().equals(b.samples())
    assert a.scenes().drop("source").equals(b.scenes().drop("source"))
    # The same data from another folder: another manifest (its lineage names the folder), the same data hash,
    # so a run trained on one copy evaluates and resumes on the other; fingerprints from before the data hash
    # compare whole manifests.
    trained, given = a.fingerprint(), b.fingerprint()
    assert trained["manifest_sha256"] != given["manifest_sha256"]
    assert trained["data_sha256"] == given["data_sha256"]
    assert data_mismatch(trained, given) is None
    legacy = {key: value for key, value in trained.items() if key != "data_sha256"}
    assert data_mismatch(legacy, given) == (f"manifest_sha256: run has {trained['manifest_sha256']!r}, "
                                            f"data has {given['manifest_sha256']!r}")
    assert data_mismatch(legacy, trained) is None
    assert data_mismatch({**trained, "dataset": "rounD"}, given) == "dataset: run has 'rounD', data has 'eth_ucy'"


def test_problems_hold_the_raw_positions(eth_ucy_raw: Path, eth_ucy_dataset: Path) -> None:
    problems = load_problems(eth_ucy_dataset, "eth", "test")
    raw = pl.read_csv(eth_ucy_raw / "eth" / "test" / "biwi_eth.txt", separator="\t", has_header=False,
                      new_columns=["frame", "ped", "x", "y"])
    i = len(problems) // 2
    agent, t0 = int(problems.agent_id[i]), int(problems.t0_frame[i]) * 10
    track = raw.filter((pl.col("ped") == agent) & (pl.col("frame") >= t0 - 70) & (pl.col("frame") <= t0 + 120))
    positions = track.sort("frame").select("x", "y").to_numpy()
    batch = problems.batch
    assert positions[:8] == pytest.approx(batch.past[i].numpy(), abs=1e-5)
    assert positions[8:] == pytest.approx(batch.future[i].numpy(), abs=1e-5)
    present = raw.filter((pl.col("frame") == t0) & (pl.col("ped") != agent)).height
    assert int(batch.neighbours_mask[i].sum()) == present


def test_unknown_fold_is_a_usage_error(eth_ucy_dataset: Path) -> None:
    with pytest.raises(UsageError, match="fold 'mars' does not exist.*eth, hotel, univ, zara1, zara2"):
        load_problems(eth_ucy_dataset, "mars", "test")
    with pytest.raises(UsageError, match="choose --fold"):
        load_problems(eth_ucy_dataset, None, "train")


def test_missing_location_folder_is_reported(eth_ucy_raw: Path, tmp_path: Path) -> None:
    layout = tmp_path / "layout"
    for location in ("eth", "hotel", "univ", "zara1"):
        shutil.copytree(eth_ucy_raw / location, layout / location)
    with pytest.raises(DataError, match=r"location folder\(s\) zara2 missing"):
        ingest_eth_ucy(layout, tmp_path / "out", quiet=True)
    assert not (tmp_path / "out").exists()
