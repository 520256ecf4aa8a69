"""Our ROME (trajflow_pipeline.metrics.rome) against scikit-learn's OPTICS / Xi / DBSCAN, against romepy itself and
against ROME's density written out independently in extended precision."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from trajflow_pipeline.metrics import rome
from trajflow_pipeline.metrics.parallel import RomeTask, fit_and_score
from trajflow_pipeline.metrics.rome.candidates import XI_VALUES, candidate_clusterings
from trajflow_pipeline.metrics.rome.mixture import fit_mixture
from trajflow_pipeline.metrics.rome.distances import distance_matrices
from trajflow_pipeline.metrics.rome.optics import optics_graph
from trajflow_pipeline.metrics.rome.reference import ReferenceDensity

#: how close the exact density is to romepy's wherever romepy's own arithmetic is exact (the issue's contract)
RELATIVE = 1e-9


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
    graph = optics_graph(points, distance_matrices(points)[0])
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
    graph = optics_graph(points, distance_matrices(points)[0])
    ours = candidate_clusterings(graph)
    for b in range(shape[0]):
        assert np.array_equal(ours[b], _reference_candidates(graph, b)), b


def test_exact_mixture_is_the_reference_density_where_its_kd_tree_is_exact() -> None:
    """Clusters of at most 80 points make scikit-learn's KD-tree a single leaf, whose KDE sum is exact: there the
    batched mixture equals the reference density; far from bigger clusters the reference loses precision."""
    pytest.importorskip("sklearn", reason="the reference density needs scikit-learn (the dev or reference extra)")
    points = _synthetic_sets(30, 60, 24, seed=5)
    labels = rome.cluster(points)
    queries = np.concatenate([points[:, :3] + 0.3, points[:, :1] + 5.0, points[:, :1] + 50.0], axis=1)
    exact = fit_mixture(points, labels, 0.1).log_density(queries)
    reference = np.stack([ReferenceDensity(points[b], labels[b], 0.1).log_density(queries[b]) for b in range(30)])
    np.testing.assert_allclose(exact, reference, rtol=1e-12)




def _extended_precision_density(points: np.ndarray, labels: np.ndarray, queries: np.ndarray,
                                min_std: float = 0.1) -> np.ndarray:
    """ROME's density written out on its own, as docs/rome.md states it: per cluster the full PCA of ROME's tiled
    rows by LAPACK's QR-based SVD (gesvd, not the divide-and-conquer one scikit-learn calls), each KDE summed in
    extended precision (np.longdouble) over all its points; noise as one KDE on axis-scaled coordinates."""
    from scipy.linalg import svd

    n, dim = points.shape
    wide = np.longdouble
    values, stds = [], []
    for label in (label for label in np.unique(labels) if label >= 0):
        members = points[labels == label]
        mean = members.mean(0)
        stds.append(members.std(0))
        centred = members - mean
        tiled = np.tile(centred, (-(-dim // len(members)), 1)) if len(members) < dim else centred
        _, singular, vt = svd(tiled - tiled.mean(0), full_matrices=False, lapack_driver="gesvd")
        std = singular / np.sqrt(tiled.shape[0] - 1)
        std = std * (std.max() - min_std) / std.max() + min_std
        transform = vt.T / std
        values.append(_kde(centred @ transform, (queries - mean) @ transform, len(members), dim)
                      - wide(np.log(std).sum()) + wide(np.log(len(members) / n)))
    if (labels == -1).any():
        scale = np.maximum(np.mean(stds, axis=0), min_std) if stds else np.ones(dim)
        noise = points[labels == -1] / scale
        values.append(_kde(noise, queries / scale, 1, dim) - wide(np.log(scale).sum())
                      + wide(np.log(len(noise) / n)))
    stacked = np.stack(values, axis=1)
    top = stacked.max(axis=1)
    return (top + np.log(np.exp(stacked - top[:, None]).sum(axis=1))).astype(np.float64)


def _kde(points: np.ndarray, queries: np.ndarray, silverman_n: int, dim: int) -> np.ndarray:
    """log of the Gaussian KDE of `points` at `queries` with Silverman's bandwidth for `silverman_n` points, in
    extended precision."""
    wide = np.longdouble
    bandwidth = wide((silverman_n * (dim + 2) / 4) ** (-1 / (dim + 4)))
    squared = ((queries.astype(wide)[:, None, :] - points.astype(wide)[None]) ** 2).sum(-1)
    log_kernel = -squared / (2 * bandwidth ** 2)
    top = log_kernel.max(axis=1)
    return (top + np.log(np.exp(log_kernel - top[:, None]).sum(axis=1)) - np.log(wide(len(points)))
            - dim * np.log(bandwidth) - wide(0.5 * dim) * np.log(2 * wide(np.pi)))


@pytest.mark.parametrize("case", ["all noise", "clusters and noise", "fewer points than dimensions", "chosen"])
def test_exact_density_is_the_extended_precision_one(case: str) -> None:
    """The batched exact density against ROME's density written out in extended precision, for labellings ROME's
    clustering rarely or never chooses and for the ones it chooses (no romepy needed, so numpy 2 runs it too)."""
    rng = np.random.default_rng(3)
    points = _synthetic_sets(4, 60, 48 if case == "fewer points than dimensions" else 24, seed=8)
    labels = rome.cluster(points)
    if case == "all noise":
        labels[:] = -1
    elif case == "clusters and noise":
        labels = rng.integers(-1, 3, size=labels.shape)
    elif case == "fewer points than dimensions":
        labels = np.where(np.arange(60) < 30, 0, 1)[None].repeat(4, axis=0)   # 30 points per cluster, D = 48
    queries = np.concatenate([points[:, :3] + rng.normal(size=(4, 3, points.shape[2])) * 0.3, points[:, :1] + 3.0],
                             axis=1)
    exact = fit_mixture(points, labels, 0.1).log_density(queries)
    for b in range(4):
        np.testing.assert_allclose(exact[b], _extended_precision_density(points[b], labels[b], queries[b]),
                                   rtol=1e-10)


def _romepy():
    """romepy's ROME class, or a skip saying why the reference comparison does not run."""
    try:
        from rome.ROME import ROME
    except ImportError:
        pytest.skip("romepy is not installed (pip install '.[romepy]' in a numpy < 2 environment): "
                    "the comparison with the reference code does not run")
    return ROME


def _assert_same_as_romepy(points: np.ndarray, queries: np.ndarray) -> int:
    """A whole fit and score through the evaluation's entry point against romepy: the same clustering; with the
    reference KDE the same bits; with the exact KDE (the default) the extended-precision density within 1e-10, and
    romepy's within 1e-9 wherever romepy's own value is that close to it. Returns how many values romepy has wrong
    by more than 1e-9 (rounding residue of its KD-tree or its SVD, docs/rome.md)."""
    ROME = _romepy()
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        library = ROME().fit(points)
        expected = library.score_samples(queries)
    labels = rome.cluster(points[None])[0]
    assert np.array_equal(np.asarray(library.labels_), labels)
    (reference,) = fit_and_score(RomeTask(fit=points, queries=(queries,), kde=rome.KDE_REFERENCE))
    assert np.array_equal(expected, reference)
    (exact,) = fit_and_score(RomeTask(fit=points, queries=(queries,)))
    truth = _extended_precision_density(points, labels, queries)
    np.testing.assert_allclose(exact, truth, rtol=1e-10)
    romepy_exact = np.isclose(expected, truth, rtol=RELATIVE, atol=0.0)
    np.testing.assert_allclose(exact[romepy_exact], expected[romepy_exact], rtol=RELATIVE)
    return int((~romepy_exact).sum())


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
    """Sets of 100 real 12-step futures (world metres), 2-agent joint sets (48 dimensions) and 6-agent joint sets
    (144 dimensions: fewer draws than dimensions, so ROME tiles each cluster) from the ETH file. Where the joint
    queries lie far from the draws romepy's KD-tree sums are rounding residue: the exact values differ there."""
    futures = _eth_futures()
    rng = np.random.default_rng(0)
    for _ in range(15):
        chosen = rng.choice(len(futures), size=101, replace=False)
        _assert_same_as_romepy(futures[chosen[:100]], futures[chosen[100:]] + np.array([[0.0, 0.5] * 12]))
    for agents in (2, 6):
        for _ in range(4):
            picks = rng.choice(len(futures), size=(102, agents), replace=False)
            joint = futures[picks].reshape(102, agents * 24)
            _assert_same_as_romepy(joint[:100], joint[100:])


def test_romepy_is_wrong_far_from_big_clusters() -> None:
    """The documented difference, shown: 100 points in one cluster (a KD-tree of two leaves), queries a few
    bandwidths away. romepy's log-densities are far above the true ones; ours are the extended-precision values."""
    rng = np.random.default_rng(7)
    points = rng.normal(size=(100, 48)) * 0.2
    queries = points[:4] + 1.5
    assert _assert_same_as_romepy(points, queries) >= 1


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
    """A set's clustering and density do not depend on the other sets it is batched with (to the bit): clusters
    are decomposed on exactly their own rows, so `trajflow eval` gives the same numbers for any worker count."""
    from trajflow_pipeline.metrics.parallel import _fit_batch

    rng = np.random.default_rng(9)
    points = _synthetic_sets(12, 100, 48, seed=9)
    points[3] = points[3][:, :1] * 0.01 + np.linspace(0, 1, 100)[:, None]  # one set of a very different shape
    for b in range(6, 12):  # well-separated modes of different sizes, some clusters smaller than D = 48
        sizes = [60, 25, 15] if b < 9 else [34, 33, 33]
        points[b] = rng.normal(size=(100, 48)) * 0.3 + np.repeat([0.0, 6.0, 12.0], sizes)[:, None]
    together = rome.cluster(points)
    tasks = [RomeTask(fit=p, queries=(p[:3] + 0.2, p[:1] + 4.0)) for p in points]
    batched = _fit_batch(tasks)
    for b in range(12):
        assert np.array_equal(rome.cluster(points[b:b + 1])[0], together[b])
        alone = _fit_batch(tasks[b:b + 1])[0]
        assert all(np.array_equal(x, y) for x, y in zip(alone[0], batched[b][0])), b


def test_distance_matrices_have_scipys_and_numpys_bits_in_any_block(monkeypatch: pytest.MonkeyPatch) -> None:
    """OPTICS's distances are scipy's cdist (squared differences summed in coordinate order) and ROME's silhouette
    distances numpy's sqrt(((x - y)**2).sum(-1)) (numpy's pairwise order: sequential below 8 terms, interleaved
    sums up to 128, halves above); both come from one pass, a few sets at a time, and keep those bits for any
    dimension and any block."""
    from scipy.spatial.distance import cdist

    from trajflow_pipeline.metrics.rome import distances

    for dim in (1, 7, 8, 24, 131, 300):
        points = _synthetic_sets(3, 40, dim, seed=dim)
        numpy_order = np.sqrt(((points[:, :, None, :] - points[:, None, :, :]) ** 2).sum(-1))
        scipy_order = np.stack([cdist(p, p) for p in points])
        for block in (8 * 40 * 40, 1 << 30):  # one set per block, all sets in one
            monkeypatch.setattr(distances, "PLANE_BLOCK_BYTES", block)
            in_order, pairwise = distances.distance_matrices(points)
            assert np.array_equal(in_order, scipy_order) and np.array_equal(pairwise, numpy_order), (dim, block)


def test_rome_on_the_draws_of_a_shipped_trajflow_model(eth_ucy_dataset: Path, tmp_path: Path) -> None:
    """Real TrajFlow draws: the shipped fold-eth model samples the test problems (100 draws each); per agent
    (24 dimensions) and per 2-agent joint group (48) the exact density is the extended-precision one and, where
    romepy is installed, romepy's clustering and (where romepy is exact) its values."""
    import shutil

    import polars as pl

    from trajflow_pipeline.stages.evaluate import EvalOptions, evaluate

    shipped = Path(__file__).resolve().parents[2] / "docs" / "results" / "eth_ucy" / "models" / "trajflow-eth-s0"
    run = Path(shutil.copytree(shipped, tmp_path / "run"))
    out = evaluate(run, data=eth_ucy_dataset, options=EvalOptions(metrics=("min_ade",), workers=1), quiet=True)
    draws = pl.read_parquet(out / "predictions.parquet").sort("sample_id", "draw", "step")
    truth = pl.read_parquet(out / "ground_truth.parquet").filter(pl.col("step") >= 1).sort("sample_id", "step")
    ids = truth["sample_id"].unique().sort().to_numpy()
    pred = draws.select("x", "y").to_numpy().reshape(ids.size, 100, -1)[:, :, :24]
    gt = truth.filter(pl.col("step") <= 12).select("x", "y").to_numpy().reshape(ids.size, 24)
    joint = truth.filter(pl.col("step") == 1)["joint_id"].to_numpy()
    pairs = [np.flatnonzero(joint == key) for key, count in zip(*np.unique(joint, return_counts=True)) if count == 2]
    cases = [(pred[a], gt[a:a + 1] + np.array([[0.0, 0.3] * 12])) for a in range(0, ids.size, ids.size // 8)][:8]
    cases += [(pred[p].transpose(1, 0, 2).reshape(100, 48), gt[p].reshape(1, 48)) for p in pairs[:4]]
    assert len(cases) >= 10
    for points, queries in cases:
        try:
            _romepy()
        except pytest.skip.Exception:
            labels = rome.cluster(points[None])[0]
            (exact,) = fit_and_score(RomeTask(fit=points, queries=(queries,)))
            np.testing.assert_allclose(exact, _extended_precision_density(points, labels, queries), rtol=1e-10)
        else:
            _assert_same_as_romepy(points, queries)


def test_rome_equals_romepy_on_pooled_synthetic_bimodal_futures(synthetic_dataset: Path) -> None:
    """The synthetic bimodal benchmark's pooled fits: many 14-step futures (28 dimensions) of one past, in two modes
    (here the dataset's own futures stand in for a model's draws: 500 pooled, as an evaluation pools a group's)."""
    import polars as pl

    from trajflow_pipeline.data.loader import load_problems

    problems = load_problems(synthetic_dataset, split="test")
    futures = problems.batch.future.double().flatten(1).numpy()
    rng = np.random.default_rng(4)
    chosen = rng.permutation(len(futures))
    queries = np.concatenate([futures[chosen[500:505]], futures[chosen[:2]] + 0.3, futures[chosen[:1]] + 5.0])
    assert pl.Series(problems.group_id).n_unique() == 1  # one identical-input group: one pooled fit
    _assert_same_as_romepy(futures[chosen[:500]], queries)
