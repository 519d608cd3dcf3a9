"""The numpy k-nearest-neighbour distances against scipy's cKDTree (a test-only dependency)."""
import numpy as np
import pytest

from recgs_addon.core.model.gaussians import knn_mean_distance
from recgs_addon.core.model.knn import knn_distances

cKDTree = pytest.importorskip("scipy.spatial").cKDTree


def _scenes():
    rng = np.random.default_rng(0)
    flat = rng.uniform(0, 10, (3000, 3))
    flat[:, 2] *= 0.02                                        # a seafloor: thin in z
    clusters = np.concatenate([rng.normal(c, 0.01, (400, 3)) for c in rng.uniform(-50, 50, (5, 3))])
    outliers = np.concatenate([rng.normal(0, 1, (2000, 3)), [[1e3, 0, 0], [-1e3, 5, 5], [0, 0, 1e4]]])
    grid = np.stack(np.meshgrid(*[np.arange(6.0)] * 3), -1).reshape(-1, 3)   # many exact ties
    dup = np.concatenate([rng.uniform(0, 1, (50, 3))] * 3)                   # every point three times
    line = np.stack([np.linspace(0, 1, 500), np.zeros(500), np.zeros(500)], 1)
    return {"flat": flat, "clusters": clusters, "outliers": outliers, "grid": grid, "dup": dup, "line": line}


@pytest.mark.parametrize("name", list(_scenes()))
@pytest.mark.parametrize("k", [1, 3, 8])
def test_knn_matches_kdtree(name, k):
    pts = _scenes()[name]
    ref = cKDTree(pts).query(pts, k=k + 1)[0][:, 1:]
    assert np.array_equal(knn_distances(pts, k), ref) or np.abs(knn_distances(pts, k) - ref).max() < 1e-12


def test_small_and_degenerate_inputs():
    assert np.array_equal(knn_mean_distance(np.zeros((1, 3))), np.ones(1))
    assert np.allclose(knn_mean_distance(np.array([[0.0, 0, 0], [3.0, 4, 0]])), [5.0, 5.0])
    assert np.array_equal(knn_distances(np.zeros((5, 3)), 3), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="more than k"):
        knn_distances(np.zeros((3, 3)), 3)
