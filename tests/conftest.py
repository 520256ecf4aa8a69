"""Shared fixtures: the real ETH/UCY copy (skipped when absent) and small generated datasets."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

#: the tests mirror the package, a folder per package (tests/model for trajflow_pipeline/model, ...); test modules
#: import fixture writers and fakes from other folders by module name, so every folder is on the import path
TEST_FOLDERS = sorted(path for path in Path(__file__).resolve().parent.iterdir()
                      if path.is_dir() and not path.name.startswith(("_", ".")))
sys.path[:0] = [str(path) for path in TEST_FOLDERS if str(path) not in sys.path]

# Tests run on 2-core CI machines: keep torch from oversubscribing them.
torch.set_num_threads(1)

# The fuzz suite (tests/test_fuzz.py): a fixed seed and few examples by default (CI); `pytest
# --hypothesis-profile long tests/test_fuzz.py` for a longer local search.
try:
    from hypothesis import HealthCheck, settings
except ImportError:  # the dev extra installs it; without it test_fuzz.py skips
    pass
else:
    _FUZZ = dict(deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
    settings.register_profile("ci", max_examples=30, derandomize=True, database=None, **_FUZZ)
    settings.register_profile("long", max_examples=1000, **_FUZZ)
    settings.load_profile("ci")


def _data_root() -> Path | None:
    root = os.environ.get("TRAJFLOW_DATA")
    if root:
        return Path(root)
    sibling = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return sibling if sibling.is_dir() else None


@pytest.fixture(scope="session")
def eth_ucy_raw() -> Path:
    """The shared ETH/UCY copy in the Trajectron++ layout (TRAJFLOW_DATA/eth_ucy)."""
    root = _data_root()
    if root is None or not (root / "eth_ucy").is_dir():
        pytest.skip("real ETH/UCY data not found: set TRAJFLOW_DATA to a folder holding eth_ucy/ "
                    "(CI sets it to ../shared/data)")
    return root / "eth_ucy"


@pytest.fixture(scope="session")
def eth_ucy_dataset(eth_ucy_raw: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shared ETH/UCY copy ingested once per test session."""
    from trajflow_pipeline.ingest.eth_ucy import ingest_eth_ucy

    return ingest_eth_ucy(eth_ucy_raw, tmp_path_factory.mktemp("eth") / "eth_ucy", quiet=True)


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small synthetic bimodal dataset (600 samples)."""
    from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal

    return ingest_synthetic_bimodal(tmp_path_factory.mktemp("syn") / "bimodal", samples=600, seed=3, quiet=True)


@pytest.fixture
def rome_pca_fails_twice(monkeypatch: pytest.MonkeyPatch) -> None:
    """The first SVDs of ROME's PCA (in this process) raise, as a degenerate cluster can make them: the batch's
    decomposition, then one cluster's first two attempts, so ROME takes its own fallback twice for that cluster:
    it re-runs the PCA with added jitter."""
    import numpy as np

    real_svd = np.linalg.svd
    failures = {"left": 3}

    def flaky_svd(*args, **kwargs):
        if failures["left"] > 0:
            failures["left"] -= 1
            raise np.linalg.LinAlgError("SVD did not converge")
        return real_svd(*args, **kwargs)

    monkeypatch.setattr(np.linalg, "svd", flaky_svd)
