import numpy as np

from recgs_addon.core.model.gaussians import (SH_C0, GaussianSet, init_from_points, knn_mean_distance,
                                        sigmoid, sh_dc_to_rgb)


def test_knn_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    ref = np.sort(d, axis=1)[:, :3].mean(1)
    assert np.allclose(knn_mean_distance(pts), ref, rtol=1e-12)


def test_init_from_points():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3))
    cols = rng.integers(0, 256, (500, 3), dtype=np.uint8)
    g = init_from_points(pts, cols, sh_degree=2)
    assert len(g) == 500 and g.sh.shape == (500, 9, 3) and g.sh_degree == 2
    assert np.allclose(g.opacities, 0.1, atol=1e-6)
    assert np.allclose(sh_dc_to_rgb(g.sh[:, 0]), cols / 255.0, atol=1e-6)
    assert np.all(g.sh[:, 1:] == 0)
    assert np.allclose(np.exp(g.log_scales[:, 0]), knn_mean_distance(pts), rtol=1e-5)
    assert np.allclose(g.quats, [1, 0, 0, 0])
    assert SH_C0 == 0.28209479177387814


def test_init_duplicates_and_tiny_sets_are_finite():
    g = init_from_points(np.zeros((5, 3)), np.zeros((5, 3), np.uint8))
    assert np.isfinite(g.log_scales).all()
    g1 = init_from_points(np.ones((1, 3)), np.zeros((1, 3), np.uint8))
    assert len(g1) == 1 and np.isfinite(g1.log_scales).all()


def test_sigmoid_stable():
    assert np.isfinite(sigmoid(np.array([-1e4, 0, 1e4]))).all()


def test_subset_and_degree_change():
    g = init_from_points(np.random.default_rng(2).normal(size=(10, 3)), np.zeros((10, 3), np.uint8), 1)
    s = g.subset(np.arange(10) % 2 == 0)
    assert len(s) == 5
    g3 = g.with_sh_degree(3)
    assert g3.sh.shape == (10, 16, 3) and np.array_equal(g3.sh[:, :4], g.sh)
    assert GaussianSet.empty(2).sh.shape == (0, 9, 3)
