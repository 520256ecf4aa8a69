"""Our ROME (trajflow_pipeline.metrics.rome) against scikit-learn's OPTICS / Xi / DBSCAN and against romepy itself."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from trajflow_pipeline.metrics import rome
from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score
from trajflow_pipeline.metrics.rome.candidates import XI_VALUES, candidate_clusterings
from trajflow_pipeline.metrics.rome.mixture import fit_mixture
from trajflow_pipeline.metrics.rome.optics import optics_graph
from trajflow_pipeline.metrics.rome.reference import ReferenceDensity


def _synthetic_sets(n_sets: int, n: int, dim: int, seed: int) -> np.ndarray:
    """Multi-modal sets in world-like coordinates (an offset of tens of metres), with a tight knot of near-duplicates."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n_sets, n, dim)) * rng.uniform(0.2, 3, size=(n_sets, 1, dim))
    points += rng.normal(size=(n_sets, 1, dim)) * 20
    points[:, : n // 3] += rng.uniform(0, 4, size=(n_sets, 1, 1))
    points[:, n // 2:n // 2 + 5] = points[:, n // 2:n // 2 + 1] + rng.normal(size=(n_sets, 5, dim)) * 0.01
    return points


def _eth_futures(steps: int = 12) -> np.ndarray:
    """Every `steps`-long stretch of a pedestrian track in the real ETH file (world metres), flattened (N, 2 steps)."""
    root = os.environ.get("TRAJFLOW_DATA")
    path = Path(root or "/nonexistent") / "eth_ucy" / "eth" / "test" / "biwi_eth.txt"
    if not path.is_file():
        pytest.skip(f"real ETH/UCY data not found at {path} (set TRAJFLOW_DATA)")
    rows = np.loadtxt(path)
    futures = []
    for ped in np.unique(rows[:, 1]):
        track = rows[rows[:, 1] == ped]
        track = track[np.argsort(track[:, 0])]
        for start in range(0, len(track) - steps + 1, 3):
            window = track[start:start + steps]
            if np.all(np.diff(window[:, 0]) == 10):
                futures.append(window[:, 2:4].ravel())
    return np.array(futures)


@pytest.mark.parametrize("shape", [(60, 100, 24), (40, 100, 48), (40, 30, 4), (8, 300, 24), (60, 12, 2), (30, 10, 24)])
def test_optics_graph_is_scikit_learns_bit_for_bit(shape: tuple[int, int, int]) -> None:
    from sklearn.cluster import OPTICS

    points = _synthetic_sets(*shape, seed=sum(shape))
    graph = optics_graph(points)
    for b in range(shape[0]):
        library = OPTICS(min_samples=graph.min_samples).fit(points[b])
        assert np.array_equal(library.ordering_, graph.ordering[b])
        assert np.array_equal(library.core_distances_, graph.core[b])
        assert np.array_equal(library.reachability_, graph.reachability[b])
        assert np.array_equal(library.predecessor_, graph.predecessor[b])


def _reference_candidates(graph, b: int) -> np.ndarray:
    """ROME's candidate loop written out with scikit-learn's public extraction functions."""
    from sklearn.cluster import cluster_optics_dbscan, cluster_optics_xi

    reach, finite = graph.reachability[b], graph.reachability[b][np.isfinite(graph.reachability[b])]
    eps = np.linspace(0, 1, 100) ** 2 * (finite.max() - finite.min()) + finite.min()
    out = np.zeros((199, reach.size), dtype=np.int64)
    for i in range(199):
        if i < 100:
            labels = cluster_optics_dbscan(reachability=reach, core_distances=graph.core[b],
                                           ordering=graph.ordering[b], eps=eps[i])
        else:
            labels, _ = cluster_optics_xi(reachability=reach, predecessor=graph.predecessor[b],
                                          ordering=graph.ordering[b], min_samples=graph.min_samples,
                                          min_cluster_size=2, xi=XI_VALUES[i - 100], predecessor_correction=True)
        if len(np.unique(labels)) > 1:
            values, sizes = np.unique(labels, return_counts=True)
            labels[np.isin(labels, values[sizes == 1])] = -1
            labels[labels > -1] = np.unique(labels[labels > -1], return_inverse=True)[1]
            out[i] = labels
    return out


@pytest.mark.parametrize("shape", [(60, 100, 24), (30, 100, 48), (60, 30, 4), (6, 300, 24), (60, 12, 2)])
def test_candidate_clusterings_are_the_references(shape: tuple[int, int, int]) -> None:
    points = _synthetic_sets(*shape, seed=7 + sum(shape))
    graph = optics_graph(points)
    ours = candidate_clusterings(graph)
    for b in range(shape[0]):
        assert np.array_equal(ours[b], _reference_candidates(graph, b)), b


def test_exact_mixture_is_the_reference_density_where_its_kd_tree_is_exact() -> None:
    """Clusters of at most 80 points make scikit-learn's KD-tree a single leaf, whose KDE sum is exact: there the
    batched mixture equals the reference density; far from bigger clusters the reference loses precision."""
    points = _synthetic_sets(30, 60, 24, seed=5)
    labels = rome.cluster(points)
    queries = np.concatenate([points[:, :3] + 0.3, points[:, :1] + 5.0, points[:, :1] + 50.0], axis=1)
    exact = fit_mixture(points, labels, 0.1).log_density(queries)
    reference = np.stack([ReferenceDensity(points[b], labels[b], 0.1).log_density(queries[b]) for b in range(30)])
    np.testing.assert_allclose(exact, reference, rtol=1e-12)




def _romepy():
    """romepy's ROME class, or a skip saying why the reference comparison does not run."""
    try:
        from rome.ROME import ROME
    except ImportError:
        pytest.skip("romepy is not installed (pip install '.[reference]' in a numpy < 2 environment): "
                    "the comparison with the reference code does not run")
    return ROME


def _assert_same_as_romepy(points: np.ndarray, queries: np.ndarray) -> None:
    """A whole fit and score through the evaluation's entry point against romepy: same clustering, same bits."""
    ROME = _romepy()
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        library = ROME().fit(points)
        expected = library.score_samples(queries)
    (ours,) = fit_and_score(RomeTask(fit=points, queries=(queries,)))
    labels = rome.cluster(points[None])[0]
    assert np.array_equal(np.asarray(library.labels_), labels)
    assert np.array_equal(expected, ours)


@pytest.mark.parametrize("shape", [(20, 100, 24), (10, 100, 48), (6, 100, 70), (4, 400, 24), (20, 30, 4),
                                   (20, 10, 24)])
def test_rome_equals_romepy_on_synthetic_sets(shape: tuple[int, int, int]) -> None:
    points = _synthetic_sets(*shape, seed=11 + sum(shape))
    rng = np.random.default_rng(1)
    for b in range(shape[0]):
        queries = np.concatenate([points[b, :3] + rng.normal(size=(3, shape[2])) * 0.5, points[b, :1] + 5.0,
                                  points[b, :1] + 50.0])
        _assert_same_as_romepy(points[b], queries)


def test_rome_equals_romepy_on_real_eth_futures() -> None:
    """Sets of 100 real 12-step futures (world metres) and 2-agent joint sets (48 dimensions) from the ETH file."""
    futures = _eth_futures()
    rng = np.random.default_rng(0)
    for _ in range(15):
        chosen = rng.choice(len(futures), size=101, replace=False)
        _assert_same_as_romepy(futures[chosen[:100]], futures[chosen[100:]] + np.array([[0.0, 0.5] * 12]))
    for _ in range(5):
        pairs = rng.choice(len(futures), size=(101, 2), replace=False)
        joint = futures[pairs].reshape(101, 48)
        _assert_same_as_romepy(joint[:100], joint[100:])


@pytest.mark.parametrize("case", ["two distinct points", "fewer draws than dimensions", "single cluster",
                                  "four points", "far queries"])
def test_degenerate_sets_behave_as_romepy(case: str) -> None:
    rng = np.random.default_rng(4)
    if case == "two distinct points":
        points = np.repeat(rng.normal(size=(2, 6)), 50, axis=0) + 0.0
        points[::2] += 1e-3 * rng.normal(size=(50, 6))
    elif case == "fewer draws than dimensions":
        points = rng.normal(size=(12, 48))
    elif case == "single cluster":
        points = rng.normal(size=(100, 24)) * 0.05
    elif case == "four points":
        points = rng.normal(size=(4, 24))
    else:
        points = rng.normal(size=(100, 24))
    queries = np.concatenate([points[:2] + 0.1, points[:1] + (1e3 if case == "far queries" else 1.0)])
    _assert_same_as_romepy(points, queries)


def test_batched_and_single_fits_agree() -> None:
    """A set's clustering does not depend on the other sets it is batched with."""
    points = _synthetic_sets(12, 100, 24, seed=9)
    together = rome.cluster(points)
    for b in (0, 5, 11):
        assert np.array_equal(rome.cluster(points[b:b + 1])[0], together[b])


def test_silhouette_distances_do_not_depend_on_their_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Big pooled sets are computed a few rows at a time (bounded memory); every distance keeps its bits."""
    from trajflow_pipeline.metrics.rome import selection

    points = _synthetic_sets(3, 90, 24, seed=2)
    whole = np.sqrt(((points[:, :, None, :] - points[:, None, :, :]) ** 2).sum(-1))
    monkeypatch.setattr(selection, "SCORE_BLOCK_BYTES", 8 * 90 * 24 * 7)  # 7 rows of one set per block
    assert np.array_equal(selection.silhouette_distances(points), whole)
