"""The code revision recorded with runs and evaluations (util.provenance), on a throw-away git checkout."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from trajflow_pipeline.util import provenance
from trajflow_pipeline.util.provenance import revision_of

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    """A git repository laid out like trajflow's, with one commit."""
    root = tmp_path / "repo"
    (root / "trajflow_pipeline").mkdir(parents=True)
    (root / "trajflow_pipeline" / "model.py").write_text("WIDTH = 32\n")
    (root / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    (root / "README.md").write_text("readme\n")
    git(root, "init", "-q")
    git(root, "add", ".")
    git(root, "commit", "-q", "-m", "one")
    return root


@needs_git
def test_a_clean_checkout_is_its_commit_and_package_changes_are_marked(checkout: Path) -> None:
    head = git(checkout, "rev-parse", "HEAD")
    assert revision_of(checkout) == head
    (checkout / "README.md").write_text("other readme\n")          # not the package: still the commit
    assert revision_of(checkout) == head
    (checkout / "trajflow_pipeline" / "model.py").write_text("WIDTH = 64\n")
    first = revision_of(checkout)
    assert first is not None and first.startswith(f"{head}+changes.")
    (checkout / "trajflow_pipeline" / "model.py").write_text("WIDTH = 16\n")
    second = revision_of(checkout)
    assert second is not None and second.startswith(f"{head}+changes.") and second != first
    (checkout / "trajflow_pipeline" / "model.py").write_text("WIDTH = 32\n")
    (checkout / "trajflow_pipeline" / "new_module.py").write_text("X = 1\n")  # untracked code runs too
    assert (revision_of(checkout) or "").startswith(f"{head}+changes.")


@needs_git
def test_no_revision_outside_a_checkout_of_trajflow(checkout: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    plain = tmp_path / "plain"
    plain.mkdir()
    assert revision_of(plain) is None                               # not a repository
    assert revision_of(checkout / "trajflow_pipeline") is None       # inside one, but not its top
    other = tmp_path / "other"
    shutil.copytree(checkout, other)
    git(other, "commit", "-q", "--allow-empty", "-m", "two")
    monkeypatch.setenv("GIT_DIR", str(other / ".git"))               # inherited variables do not redirect git
    assert revision_of(checkout) == git(checkout, "--git-dir", str(checkout / ".git"), "rev-parse", "HEAD")


@needs_git
def test_git_failing_half_way_is_unknown_not_clean(checkout: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_run = subprocess.run

    def failing_status(command: list[str], **kwargs: object) -> subprocess.CompletedProcess:
        if "status" in command:
            raise subprocess.TimeoutExpired(command, 20)
        return real_run(command, **kwargs)

    monkeypatch.setattr(provenance.subprocess, "run", failing_status)
    assert (revision_of(checkout) or "").endswith("+unknown")


def test_machines_are_described_and_listed_as_they_change() -> None:
    cpu = provenance.machine_description("cpu")
    assert cpu.startswith("CPU: ") and cpu.endswith(" cores")
    assert provenance.machines_after(None, "cpu") == ["unrecorded", cpu]
    assert provenance.appended(["GPU: Y"], cpu) == ["GPU: Y", cpu] and provenance.appended([cpu], cpu) == [cpu]
