"""Experiments and evaluations on Ray (`--ray`): a local Ray instance of 2 CPUs, started once for this module.

The same metrics as the local path, a killed run task retried to the weights of an uninterrupted run, a run's
data or usage error reported once and never retried, and the pool's failure semantics on their own.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import polars as pl
import pytest

ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")

import torch  # noqa: E402
from polars.testing import assert_frame_equal  # noqa: E402
from safetensors.torch import load_file  # noqa: E402
from test_eval_stage import write_tiny_experiment  # noqa: E402

from trajflow_pipeline.errors import DataError, TrajflowError  # noqa: E402
from trajflow_pipeline.stages.evaluate import EvalOptions, evaluate  # noqa: E402
from trajflow_pipeline.stages.experiment import run_experiment  # noqa: E402
from trajflow_pipeline.stages.experiment_config import load_experiment  # noqa: E402
from trajflow_pipeline.util.scheduler import RayPool  # noqa: E402

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="run claims need POSIX file locks")

TESTS = Path(__file__).resolve().parents[1]
REPO = TESTS.parent
#: the folders of tests/ (conftest.py puts them on this process's path; Ray's workers get them through PYTHONPATH)
TEST_FOLDERS = [str(path) for path in sorted(TESTS.iterdir()) if path.is_dir() and not path.name.startswith(("_", "."))]


@pytest.fixture(scope="module", autouse=True)
def ray_instance() -> Iterator[None]:
    """One local Ray instance for the module; its workers can import this module's task functions."""
    path = os.pathsep.join(p for p in (*TEST_FOLDERS, os.environ.get("PYTHONPATH", "")) if p)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})
    yield
    ray.shutdown()


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Torch on one thread in this process, as a Ray task of one CPU has it (so that trained weights compare)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _fail_with_data_error(log: str) -> None:
    with open(log, "a") as handle:
        handle.write("attempt\n")
    raise DataError("rows.csv: line 3: x is not a number")


def _die_once(marker: str) -> int:
    if not os.path.exists(marker):
        Path(marker).write_text("died")
        os.kill(os.getpid(), signal.SIGKILL)
    return 42


def test_the_ray_pool_retries_a_killed_worker_and_never_a_raised_error(tmp_path: Path) -> None:
    with RayPool("auto", retries=2) as pool:
        dies = pool.submit(_die_once, str(tmp_path / "died"))
        fails = pool.submit(_fail_with_data_error, str(tmp_path / "attempts"))
        # generous bounds against a hang, not speed checks: on a loaded 2-core machine a worker's restart took minutes
        assert dies.result(timeout=900) == 42
        error = fails.exception(timeout=900)
    assert (tmp_path / "died").exists()
    assert isinstance(error, DataError) and str(error) == "rows.csv: line 3: x is not a number"
    assert (tmp_path / "attempts").read_text() == "attempt\n", "a raised error must not be retried"


def test_an_experiment_on_ray_ends_with_the_metrics_of_the_local_path(tmp_path: Path, one_thread: None) -> None:
    config = write_tiny_experiment(tmp_path, ["cv", "trajflow-no-ae"], [0])
    local = run_experiment(config, tmp_path / "local", quiet=True)
    on_ray = run_experiment(config, tmp_path / "ray", quiet=True, ray="auto")
    index_local, index_ray = (json.loads((out / "experiment.json").read_text()) for out in (local, on_ray))
    assert index_ray["runs"] == index_local["runs"] == index_ray["planned"]
    assert_frame_equal(pl.read_parquet(on_ray / "metrics.parquet"), pl.read_parquet(local / "metrics.parquet"))
    started = time.perf_counter()
    run_experiment(config, on_ray, quiet=True, ray="auto")  # all done: nothing is submitted
    assert time.perf_counter() - started < 30
    # `trajflow eval RUN --ray`: the ROME fits as Ray tasks, the same table as the local evaluation
    run = local / "runs" / "trajflow-no-ae-all-s0"
    before = pl.read_parquet(run / "eval" / "metrics.parquet")
    evaluate(run, options=load_options(config), quiet=True, ray="auto")
    assert json.loads((run / "eval" / "eval.json").read_text())["ray"] == "auto"
    assert_frame_equal(pl.read_parquet(run / "eval" / "metrics.parquet"), before)


def load_options(config: Path) -> EvalOptions:
    """The evaluation options of an experiment config."""
    return load_experiment(config).eval_options


def _run_task_pids() -> list[int]:
    """Pids of the Ray workers running a run of an experiment (Ray titles a busy worker `ray::<function>`)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(b"ray::_run_task"):
                pids.append(int(proc.name))
        except OSError:
            continue
    return pids


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the Ray worker's process in /proc")
def test_a_run_task_killed_mid_training_is_retried_and_ends_with_the_weights_of_an_uninterrupted_run(
        tmp_path: Path, one_thread: None) -> None:
    config = write_tiny_experiment(tmp_path, ["trajflow-no-ae"], [0])
    lines = config.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("set = "))
    longer = [*json.loads(lines[at].removeprefix("set = ")), "train.flow_max_epochs=40", "train.flow_min_epochs=40"]
    lines[at] = f"set = {json.dumps(longer)}"
    config.write_text("\n".join(lines) + "\n")
    uninterrupted = run_experiment(config, tmp_path / "local", quiet=True)
    out = tmp_path / "ray"
    result: list[BaseException | Path] = []
    driver = threading.Thread(target=lambda: result.append(_capture(run_experiment, config, out, quiet=True,
                                                                    ray="auto")))
    driver.start()
    state = out / "runs" / "trajflow-no-ae-all-s0" / "checkpoints" / "state.pt"
    killed = None
    deadline = time.monotonic() + 300
    while killed is None and driver.is_alive() and time.monotonic() < deadline:
        pids = _run_task_pids()
        if state.exists() and pids:
            log = pl.read_parquet(out / "runs" / "trajflow-no-ae-all-s0" / "train_log.parquet")
            os.kill(pids[0], signal.SIGKILL)
            killed = log.height
        time.sleep(0.02)
    driver.join(timeout=600)
    reference = uninterrupted / "runs" / "trajflow-no-ae-all-s0"
    epochs = pl.read_parquet(reference / "train_log.parquet").height
    assert killed is not None and killed < epochs, "the run was not killed mid-training"
    assert result and isinstance(result[0], Path), result
    run = out / "runs" / "trajflow-no-ae-all-s0"
    assert json.loads((run / "run.json").read_text())["status"] == "finished"
    log = pl.read_parquet(run / "train_log.parquet")
    assert log.select("stage", "epoch").is_unique().all() and log.height == epochs
    for weights in sorted((reference / "final").glob("*.safetensors")):
        mine, theirs = load_file(run / "final" / weights.name), load_file(weights)
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    assert_frame_equal(pl.read_parquet(out / "metrics.parquet"), pl.read_parquet(uninterrupted / "metrics.parquet"))


def _capture(function, *args, **kwargs):  # noqa: ANN001, ANN202 - the result or the exception of a call
    try:
        return function(*args, **kwargs)
    except BaseException as error:  # noqa: BLE001 - handed to the test thread
        return error


def test_a_run_with_a_bad_config_fails_once_with_its_one_line_error(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["cv"], [0, 1])
    # valid on its own, refused only when a run is evaluated: --steps below the horizon --extended-horizon scores
    config.write_text(config.read_text().replace("[eval]", "[eval]\nextended_horizon = true\nsteps = 1"))
    started = time.perf_counter()
    with pytest.raises(TrajflowError) as caught:
        run_experiment(config, tmp_path / "exp", quiet=True, ray="auto")
    message = str(caught.value)
    assert message.startswith("2 of 2 run(s) failed: cv-all-s0: --steps 1 is shorter than"), message
    assert "\n" not in message and "Traceback" not in message and "ray::" not in message
    # a hang guard only: that a raised error is never retried is counted exactly by the pool test above (one
    # attempt); under load (a clean-clone CI beside two training runs) this took 319 s
    assert time.perf_counter() - started < 900
    index = json.loads((tmp_path / "exp" / "experiment.json").read_text())
    assert index["runs"] == [] and len(index["planned"]) == 2
    assert not (tmp_path / "exp" / "runs" / "cv-all-s0" / "eval").exists()


def test_without_ray_an_experiment_does_not_import_it(tmp_path: Path) -> None:
    config = write_tiny_experiment(tmp_path, ["cv"], [0])
    probe = ("import sys\nfrom typer.testing import CliRunner\nfrom trajflow_pipeline.cli.app import app\n"
             f"result = CliRunner().invoke(app, ['experiment', {str(config)!r}, '-o', {str(tmp_path / 'exp')!r}, "
             "'--quiet', '-j', '2'])\n"
             "assert result.exit_code == 0, result.output\nprint('ray' in sys.modules)\n")
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300,
                           env={**os.environ, "PYTHONPATH": os.pathsep.join(
                               p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)})
    assert child.returncode == 0, child.stderr
    assert child.stdout.strip().splitlines()[-1] == "False"
