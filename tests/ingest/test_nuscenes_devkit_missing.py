"""Without nuscenes-devkit the nuScenes ingest says, in one line, how to install the extra.

Runs whether or not the devkit is installed: the import is made to fail by hiding the package.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import typer
from nuscenes_fixture import write_release
from typer.testing import CliRunner

from trajflow_pipeline.cli.ingest_cmd import ingest_nuscenes_command
from trajflow_pipeline.errors import TrajflowError
from trajflow_pipeline.ingest.nuscenes import ingest_nuscenes


@pytest.fixture()
def no_devkit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make every `import nuscenes...` fail as if the package were not installed."""
    for name in [name for name in sys.modules if name == "nuscenes" or name.startswith("nuscenes.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "nuscenes", None)


def test_missing_devkit_names_the_extra(no_devkit: None, tmp_path: Path) -> None:
    release = write_release(tmp_path / "nuscenes")
    with pytest.raises(TrajflowError, match=r"nuscenes-devkit is not available .*pip install -e '\.\[nuscenes\]'"):
        ingest_nuscenes(release.root, tmp_path / "data", quiet=True)
    app = typer.Typer()
    app.command()(ingest_nuscenes_command)
    result = CliRunner().invoke(app, [str(release.root), "-o", str(tmp_path / "data")])
    assert result.exit_code == 1
    text = result.output.replace("\n", "")
    assert text.startswith("error: nuscenes-devkit is not available") and "Traceback" not in text
    assert "pip install -e '.[nuscenes]'" in text and "numpy<2" in text
    assert not (tmp_path / "data").exists()
