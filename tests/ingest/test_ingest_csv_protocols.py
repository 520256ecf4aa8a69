"""`ingest csv --protocol folds|fixed|train-is-test --split-by ...`: every protocol of the contract, made of time
cuts, whole scenes or whole groups; a protocol that leaves no test or training samples is refused at ingest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from test_ingest_bad_input import assert_one_line_error
from test_ingest_csv import walkers
from trajflow_pipeline.cli.app import app
from trajflow_pipeline.data import list_folds, select_samples
from trajflow_pipeline.schemas import open_dataset

runner = CliRunner()
PAST, FUTURE = 10, 14


def multi_future_csv(path: Path, scenes: int = 60, pasts: int = 1, seed: int = 0) -> Path:
    """The issue's data, scaled down: scenes of 24 frames at dt 0.25, one agent each, a 10-step past shared by
    every scene (or one of `pasts` pasts), then one of two future modes scaled by N(1, 0.15)."""
    rng = np.random.default_rng(seed)
    rows = []
    for scene in range(scenes):
        past = np.stack([np.linspace(-2.7, 0.0, PAST), np.full(PAST, float(scene % pasts))], axis=1)
        steps = np.arange(1, FUTURE + 1)
        bend = (1 if scene % 2 else -1) * rng.normal(1.0, 0.15) * 0.05 * steps ** 1.5
        future = np.stack([steps * 0.3, past[-1, 1] + bend], axis=1)
        for frame, (x, y) in enumerate(np.concatenate([past, future])):
            rows.append({"scene_id": f"s{scene:03d}", "agent_id": 0, "frame": frame, "x": x, "y": y})
    pl.DataFrame(rows).write_csv(path)
    return path


def ingest(path: Path, out: Path, *options: str):
    return runner.invoke(app, ["ingest", "csv", str(path), "-o", str(out), "--dt", "0.25", "--past", str(PAST),
                               "--future", str(FUTURE), "-q", *options])


def scenes_of(ds, fold: str | None, split: str) -> set[str]:
    return set(select_samples(ds, fold, split).get_column("scene_id"))


def test_short_scenes_fold_by_whole_scenes_by_default(tmp_path: Path) -> None:
    """The issue: 24-frame scenes cross every time block; the default now deals whole scenes into 5 folds, each
    with test and training scenes that never overlap, and the dataset inspects cleanly."""
    result = ingest(multi_future_csv(tmp_path / "mf.csv"), tmp_path / "ds")
    assert result.exit_code == 0, result.output
    ds = open_dataset(tmp_path / "ds")
    assert ds.meta.protocol == "folds" and ds.lineage["split_by"] == "scene"
    assert list_folds(ds) == ["0", "1", "2", "3", "4"]
    for fold in list_folds(ds):
        test, train, val = (scenes_of(ds, fold, split) for split in ("test", "train", "val"))
        assert len(test) == 12 and train and not test & (train | val) and not train & val
    scene_folds = dict(ds.scenes().select("scene_id", "fold").iter_rows())
    assert all(scene_folds[row["scene_id"]] == row["fold"] for row in ds.samples().iter_rows(named=True))
    inspected = runner.invoke(app, ["inspect", str(tmp_path / "ds"), "--json"])
    assert inspected.exit_code == 0, inspected.output
    # the same seed gives the same folds; another seed others
    assert ingest(tmp_path / "mf.csv", tmp_path / "again").exit_code == 0
    assert open_dataset(tmp_path / "again").samples().equals(ds.samples())
    assert ingest(tmp_path / "mf.csv", tmp_path / "seed1", "--seed", "1").exit_code == 0
    assert not open_dataset(tmp_path / "seed1").samples().get_column("fold").equals(ds.samples().get_column("fold"))


def test_train_is_test_with_a_seeded_validation_fraction_trains(tmp_path: Path) -> None:
    """Every sample tests; a seeded tenth of the scenes validates; `train` needs no --fold and runs."""
    result = ingest(multi_future_csv(tmp_path / "mf.csv"), tmp_path / "ds", "--protocol", "train-is-test",
                    "--val-fraction", "0.1")
    assert result.exit_code == 0, result.output
    ds = open_dataset(tmp_path / "ds")
    assert ds.meta.protocol == "train-is-test" and list_folds(ds) == []
    samples = ds.samples()
    assert samples.get_column("fold").null_count() == samples.height
    assert select_samples(ds, None, "test").height == 60
    assert len(scenes_of(ds, None, "val")) == 6 and len(scenes_of(ds, None, "train")) == 54
    assert samples.get_column("group_id").n_unique() == 1  # one shared past: JSD over all samples
    trained = runner.invoke(app, ["--threads", "1", "train", str(tmp_path / "ds"), "-o", str(tmp_path / "run"),
                                  "--set", "train.ae_max_epochs=1", "--set", "train.flow_max_epochs=1", "-q"])
    assert trained.exit_code == 0, trained.output
    assert json.loads((tmp_path / "run" / "run.json").read_text())["fold"] is None


def test_group_folds_keep_identical_inputs_together(tmp_path: Path) -> None:
    path = multi_future_csv(tmp_path / "mf.csv", scenes=60, pasts=6)
    assert ingest(path, tmp_path / "ds", "--split-by", "group", "--folds", "3").exit_code == 0
    samples = open_dataset(tmp_path / "ds").samples()
    assert samples.get_column("group_id").n_unique() == 6
    assert samples.group_by("group_id").agg(pl.col("fold").n_unique()).get_column("fold").max() == 1
    assert samples.get_column("fold").n_unique() == 3
    result = ingest(multi_future_csv(tmp_path / "one.csv"), tmp_path / "one", "--split-by", "group")
    assert_one_line_error(result, "one.csv: --protocol folds --split-by group: only 1 group(s) for 5 folds")
    assert result.exit_code == 2 and not (tmp_path / "one").exists()


def test_fixed_holdout_by_scenes_or_by_the_end_of_each_timeline(tmp_path: Path) -> None:
    assert ingest(multi_future_csv(tmp_path / "mf.csv"), tmp_path / "ds", "--protocol", "fixed",
                  "--test-fraction", "0.25").exit_code == 0
    ds = open_dataset(tmp_path / "ds")
    test, train, val = (scenes_of(ds, None, split) for split in ("test", "train", "val"))
    assert (len(test), len(val), len(train)) == (15, 12, 33) and not test & train
    long = tmp_path / "long.csv"
    walkers(frames=100).write_csv(long)
    result = runner.invoke(app, ["ingest", "csv", str(long), "-o", str(tmp_path / "time"), "--dt", "0.5", "-q",
                                 "--columns", "scene=sid,agent=who,time=time,x=px,y=py", "--past", "4",
                                 "--future", "6", "--protocol", "fixed", "--test-fraction", "0.2"])
    assert result.exit_code == 0, result.output
    ds = open_dataset(tmp_path / "time")
    assert ds.lineage["split_by"] == "time"
    start = pl.col("t0_frame") - 3
    end = pl.col("t0_frame") + 6
    assert select_samples(ds, None, "test").select((start >= 80).all()).item()
    assert select_samples(ds, None, "val").select(((start >= 60) & (end < 80)).all()).item()
    assert select_samples(ds, None, "train").select((end < 60).all()).item()


@pytest.mark.parametrize(("options", "fragments"), [
    (["--split-by", "time"], ["mf.csv: --protocol folds --split-by time: fold 0 has no test samples",
                              "windows of 24 frames that cross a cut", "use --split-by scene or group"]),
    (["--folds", "61"], ["only 60 scene(s) for 61 folds; use fewer --folds"]),
    (["--protocol", "train-is-test", "--split-by", "time"],
     ["--protocol train-is-test --split-by time: no training samples"]),
    (["--protocol", "fixed"], ["--protocol fixed needs --split-col COLUMN or --test-fraction F"]),
    (["--protocol", "folds", "--split-col", "frame"], ["--split-col gives the fixed protocol, not folds"]),
    (["--test-fraction", "0.2"], ["--test-fraction holds out a test set of the fixed protocol, not of folds"]),
    (["--protocol", "fixed", "--test-fraction", "0.9"], ["--test-fraction must be above 0 and"]),
    (["--val-fraction", "1"], ["--val-fraction must be at least 0 and below 1"]),
    (["--split-by", "agent"], ["--split-by must be one of auto, time, scene, group"]),
    (["--protocol", "kfold"], ["--protocol must be one of folds, fixed, train-is-test"]),
])
def test_protocols_that_cannot_work_are_refused_at_ingest(tmp_path: Path, options: list[str],
                                                          fragments: list[str]) -> None:
    result = ingest(multi_future_csv(tmp_path / "mf.csv"), tmp_path / "ds", *options)
    assert_one_line_error(result, *fragments)
    assert result.exit_code == 2 and not (tmp_path / "ds").exists()


def test_a_split_column_without_test_rows_is_refused(tmp_path: Path) -> None:
    frame = pl.read_csv(multi_future_csv(tmp_path / "mf.csv")).with_columns(part=pl.lit("train"))
    frame.write_csv(tmp_path / "s.csv")
    result = ingest(tmp_path / "s.csv", tmp_path / "ds", "--split-col", "part")
    assert_one_line_error(result, "s.csv: --protocol fixed --split-col part: no test samples")
