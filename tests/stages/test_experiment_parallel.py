"""Several processes on one experiment directory: run claims, `--jobs` workers, runs left to their holder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import polars as pl
import pytest

from test_eval_stage import write_tiny_experiment
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.stages.experiment import plan_order, run_experiment
from trajflow_pipeline.util.claim import claim

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="run claims need POSIX file locks")


def test_a_claim_is_exclusive_until_released(tmp_path: Path) -> None:
    lock = tmp_path / "runs" / ".a.lock"
    with claim(lock) as first:
        assert first
        with claim(lock) as second:
            assert not second
    with claim(lock) as again:
        assert again


def test_a_claim_ends_with_its_process_however_it_ends(tmp_path: Path) -> None:
    lock = tmp_path / ".run.lock"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom trajflow_pipeline.util.claim import claim\n"
        f"with claim({str(lock)!r}) as mine:\n    print(mine, flush=True)\n    time.sleep(60)\n")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "True"
        with claim(lock) as mine:
            assert not mine
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    with claim(lock) as mine:
        assert mine


def test_a_run_claimed_elsewhere_is_left_to_its_holder(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["cv"], [0, 1, 2])
    out = tmp_path / "exp"
    with claim(out / "runs" / ".cv-all-s1.lock") as mine:
        assert mine
        run_experiment(config, out, quiet=True)
    index = json.loads((out / "experiment.json").read_text())
    assert index["runs"] == ["runs/cv-all-s0", "runs/cv-all-s2"]
    assert len(index["planned"]) == 3 and not (out / "runs" / "cv-all-s1").exists()
    assert set(pl.read_parquet(out / "metrics.parquet").get_column("seed")) == {0, 2}
    run_experiment(config, out, quiet=True)
    assert json.loads((out / "experiment.json").read_text())["runs"] == [f"runs/cv-all-s{s}" for s in range(3)]


def test_only_works_on_the_matching_runs_and_the_index_keeps_the_whole_plan(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["cv"], [0, 1, 2])
    out = run_experiment(config, tmp_path / "exp", quiet=True, only=["cv-all-s1"])
    index = json.loads((out / "experiment.json").read_text())
    assert index["runs"] == ["runs/cv-all-s1"] and len(index["planned"]) == 3
    assert sorted(p.name for p in (out / "runs").iterdir() if not p.name.startswith(".")) == ["cv-all-s1"]
    run_experiment(config, out, quiet=True, only=["cv-all-s[02]"], jobs=2)
    index = json.loads((out / "experiment.json").read_text())
    assert index["runs"] == index["planned"]
    assert set(pl.read_parquet(out / "metrics.parquet").get_column("seed")) == {0, 1, 2}


def test_jobs_beyond_the_selected_runs_do_not_take_their_share_of_the_threads(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae", "cv"], [0, 1])
    out = run_experiment(config, tmp_path / "exp", quiet=True, jobs=2, only="trajflow-no-ae-all-s1")
    info = json.loads((out / "runs" / "trajflow-no-ae-all-s1" / "run.json").read_text())
    assert info["status"] == "finished" and info["cpu_threads"] == _torch_threads()
    assert json.loads((out / "experiment.json").read_text())["runs"] == ["runs/trajflow-no-ae-all-s1"]


def test_an_only_pattern_that_matches_no_run_is_refused_before_any_work(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["cv"], [0, 1])
    result = CliRunner().invoke(app, ["experiment", str(config), "-o", str(tmp_path / "exp"), "--quiet",
                                      "--only", "cv-all-s*", "--only", "flomo-*"])
    assert result.exit_code == 2, result.output
    assert "--only 'flomo-*' matches no run" in result.output and "cv-all-s0, cv-all-s1" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "exp" / "runs").exists()


def test_jobs_share_the_runs_and_train_each_once(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae", "cv"], [0, 1])
    out = run_experiment(config, tmp_path / "exp", quiet=True, jobs=2)
    index = json.loads((out / "experiment.json").read_text())
    assert index["runs"] == index["planned"] and len(index["runs"]) == 4
    for seed in (0, 1):
        run = out / "runs" / f"trajflow-no-ae-all-s{seed}"
        log = pl.read_parquet(run / "train_log.parquet")
        assert log.select("stage", "epoch").is_unique().all(), "a run was trained by two workers"
        info = json.loads((run / "run.json").read_text())
        assert info["status"] == "finished" and info["cpu_threads"] == max(1, _torch_threads() // 2)
    metrics = pl.read_parquet(out / "metrics.parquet")
    assert set(metrics.get_column("model")) == {"trajflow-no-ae", "cv"}
    started = time.perf_counter()
    run_experiment(config, out, quiet=True, jobs=2)  # everything done: the workers only skip
    assert time.perf_counter() - started < 60


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie waiting for its reaper counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_worker_ends_with_the_experiment_process_even_when_that_is_killed(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text(
        "import multiprocessing, time\n"
        "from trajflow_pipeline.util.scheduler import exit_with_parent as _exit_with_parent\n"
        "def worker():\n    _exit_with_parent()\n    time.sleep(120)\n"
        "if __name__ == '__main__':\n"
        "    child = multiprocessing.get_context('spawn').Process(target=worker)\n"
        "    child.start()\n    print(child.pid, flush=True)\n    time.sleep(120)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    time.sleep(1.0)  # the worker is up (were the parent gone sooner, the watch would fire at once)
    assert _alive(child)
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 20
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(child), "an orphaned worker would keep its runs claimed"


def test_the_closed_form_baseline_is_worked_on_first(tmp_path: Path) -> None:
    """cv takes minutes where a trained model takes hours: its rows come first, for reports of unfinished work."""
    assert plan_order(["trajflow", "flomo", "cv"], ["eth", "hotel"], [0]) == [
        ("cv", "eth", 0), ("cv", "hotel", 0), ("trajflow", "eth", 0), ("trajflow", "hotel", 0),
        ("flomo", "eth", 0), ("flomo", "hotel", 0)]
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae", "cv"], [0])
    out = tmp_path / "exp"
    with claim(out / "runs" / ".trajflow-no-ae-all-s0.lock") as mine:  # the trained run is busy elsewhere
        assert mine
        run_experiment(config, out, quiet=True)
    index = json.loads((out / "experiment.json").read_text())
    assert index["planned"] == ["runs/cv-all-s0", "runs/trajflow-no-ae-all-s0"]
    assert index["runs"] == ["runs/cv-all-s0"]
    assert index["plan"] == [{"run": "runs/cv-all-s0", "model": "cv", "fold": None, "seed": 0},
                             {"run": "runs/trajflow-no-ae-all-s0", "model": "trajflow-no-ae", "fold": None, "seed": 0}]
