"""Atomic outputs after a kill: what a killed write leaves is cleaned up or put back by the next write or read."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.util import atomic

from test_inspect import write_dataset

KILLED_INSIDE_THE_BLOCK = """
import os, signal, sys
from pathlib import Path
from trajflow_pipeline.util.atomic import atomic_directory, atomic_file
target = Path(sys.argv[1])
with atomic_file(target.parent / "notes.txt") as tmp:
    tmp.write_text("half")
    with atomic_directory(target) as folder:
        (folder / "half").write_text("half-written")
        os.kill(os.getpid(), signal.SIGKILL)
"""

KILLED_BETWEEN_THE_RENAMES = """
import os, signal, sys
from pathlib import Path
from trajflow_pipeline.util import atomic
atomic._exchange = lambda first, second: False  # a system without an atomic exchange: two renames
renames = []
real_replace = os.replace
def replace_then_die(source, target):
    real_replace(source, target)
    renames.append(target)
    if len(renames) == 1:
        os.kill(os.getpid(), signal.SIGKILL)  # the old version is aside, the new one not yet in place
os.replace = replace_then_die
target = Path(sys.argv[1])
with atomic.atomic_directory(target) as folder:
    (folder / "new").write_text("new")
"""


def run_killed(script: str, target: Path) -> None:
    """Run `script` in a child process that SIGKILLs itself; check that it did."""
    child = subprocess.run([sys.executable, "-c", textwrap.dedent(script), str(target)], capture_output=True,
                           text=True, timeout=120)
    assert child.returncode == -9, child.stderr


def siblings(folder: Path) -> list[str]:
    return sorted(entry.name for entry in folder.iterdir())


def test_what_a_killed_write_leaves_is_cleaned_by_the_next_write(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    run_killed(KILLED_INSIDE_THE_BLOCK, out / "result")
    left = siblings(out)
    assert len(left) == 2 and all(".tmp-" in name for name in left), left
    with atomic.atomic_directory(out / "result") as folder:
        (folder / "whole").write_text("done")
    assert siblings(out) == ["result"]
    assert siblings(out / "result") == ["whole"]
    said = capsys.readouterr().err
    assert said.count("left by an interrupted run") == 2 and all(name in said for name in left)


def test_a_replacement_killed_between_its_renames_is_put_back_by_the_next_reader(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "toy")
    run_killed(KILLED_BETWEEN_THE_RENAMES, data)
    left = siblings(tmp_path)
    assert not data.exists() and len(left) == 2 and sum("tmp-old-" in name for name in left) == 1, left
    result = CliRunner().invoke(app, ["inspect", str(data), "--json"])
    assert result.exit_code == 0, result.output
    assert f"recovered {data}: put back the previous version" in result.output
    assert siblings(tmp_path) == ["toy"] and (data / "dataset.json").is_file()


def test_a_replacement_killed_between_its_renames_is_put_back_by_the_next_write(tmp_path: Path) -> None:
    target = tmp_path / "folder"
    target.mkdir()
    (target / "old").write_text("old")
    run_killed(KILLED_BETWEEN_THE_RENAMES, target)
    assert not target.exists() and len(siblings(tmp_path)) == 2
    with pytest.raises(RuntimeError):
        with atomic.atomic_directory(target):  # recovers first; then this write fails and leaves the old one
            raise RuntimeError("the new result failed")
    assert siblings(tmp_path) == ["folder"] and siblings(target) == ["old"]


def test_temporaries_of_live_processes_are_left_alone(tmp_path: Path) -> None:
    host = atomic._host_tag()
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        mine = tmp_path / f".result.tmp-{host}-{os.getpid()}-abcdefgh"
        theirs = tmp_path / f".result.tmp-{host}-{sleeper.pid}-abcdefgh"
        other_host = tmp_path / f".result.tmp-{'0' * 12 if host != '0' * 12 else '1' * 12}-1-abcdefgh"
        for path in (mine, theirs, other_host):
            path.mkdir()
        atomic.recover(tmp_path / "result")
        assert siblings(tmp_path) == sorted(p.name for p in (mine, theirs, other_host))
    finally:
        sleeper.kill()
        sleeper.wait()
    atomic.recover(tmp_path / "result")
    assert siblings(tmp_path) == sorted(p.name for p in (mine, other_host))


def test_an_old_version_whose_replacement_is_in_place_is_removed(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    old = tmp_path / f".result.tmp-old-{atomic._host_tag()}-{dead.stdout.strip()}-abcdefgh"
    old.mkdir()
    (tmp_path / "result").mkdir()
    atomic.recover(tmp_path / "result")
    assert siblings(tmp_path) == ["result"]


@pytest.mark.parametrize("length", [120, 250])
def test_replacing_keeps_no_sibling_and_names_stay_legal(tmp_path: Path, length: int) -> None:
    target = tmp_path / ("n" * length)
    for content in ("first", "second"):
        with atomic.atomic_directory(target) as folder:
            (folder / "f").write_text(content)
            assert all(len(os.fsencode(name)) <= atomic.NAME_MAX for name in siblings(tmp_path))
        assert siblings(tmp_path) == [target.name] and (target / "f").read_text() == content


def test_a_fifo_named_like_an_input_is_refused_not_waited_on(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "toy")
    (data / "dataset.json").unlink()
    os.mkfifo(data / "dataset.json")
    child = subprocess.run([sys.executable, "-m", "trajflow_pipeline", "inspect", str(data)],
                           capture_output=True, text=True, timeout=120)
    assert child.returncode == 1
    assert child.stderr.strip() == f"error: {data / 'dataset.json'}: is a FIFO, not a file that can be read"


def test_a_name_that_only_looks_like_a_temporary_is_left_alone(tmp_path: Path) -> None:
    """A pid no process can have (beyond pid_t) is not taken for a dead process, and nothing raises."""
    odd = tmp_path / f".result.tmp-{atomic._host_tag()}-9999999999-abcdefgh"
    odd.mkdir()
    atomic.recover(tmp_path / "result")
    with atomic.atomic_directory(tmp_path / "result") as folder:
        (folder / "f").write_text("x")
    assert siblings(tmp_path) == sorted([odd.name, "result"])
