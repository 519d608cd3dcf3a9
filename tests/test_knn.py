"""The numpy k-nearest-neighbour distances against scipy's cKDTree (a test-only dependency)."""
import numpy as np
import pytest

from recgs_addon.core.model.gaussians import knn_mean_distance
from recgs_addon.core.model.knn import MAX_OCCUPANCY, cell_size, knn_distances, occupancy

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
    # a survey's sparse cloud: a floor and a wall seen forward, and points far off in open water
    # that stretch the bounding box a hundred times the floor's thickness
    floor = np.c_[rng.uniform(0, 40, (6000, 2)), rng.normal(0, 0.05, 6000)]
    wall = np.c_[rng.uniform(0, 40, 2000), np.full(2000, 40.0), rng.uniform(0, 8, 2000)]
    far = rng.uniform([-40, -15, 0], [45, 35, 100], (60, 3))
    survey = np.concatenate([floor, wall, far])
    return {"flat": flat, "clusters": clusters, "outliers": outliers, "grid": grid, "dup": dup, "line": line,
            "survey": survey}


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


def test_cells_fit_the_points_not_their_bounding_box():
    """Points on surfaces with outliers far off: the grid's cells hold a few points each, as
    over a full box (sized over the box they would hold fifty, and every query would
    compare with thousands of candidates)."""
    pts = _scenes()["survey"]
    span = pts.max(0) - pts.min(0)
    box = float(np.prod(span) * 2.0 / len(pts)) ** (1 / 3)
    assert occupancy(pts, box) > 10 * MAX_OCCUPANCY
    assert occupancy(pts, cell_size(pts)) <= MAX_OCCUPANCY
    uniform = np.random.default_rng(2).uniform(0, 1, (5000, 3))
    assert cell_size(uniform) == pytest.approx((2.0 / 5000) ** (1 / 3), rel=0.01)   # a full box: as before
