"""The scripts under docs/results (not part of the package) as modules, for their tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"


def load_results_script(relative: str) -> ModuleType:
    """docs/results/`relative` (e.g. "publish.py") imported as a module named after the file."""
    path = RESULTS / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
