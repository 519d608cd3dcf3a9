"""Tests of recgs_addon.core.render.rasterizer against the dense float64 oracle (reference_render.py).

Run: ``pytest tests/test_rasterizer.py -m "not slow"`` (~15-20 s on 2 cores, eager kernels
only); ``-m slow`` adds the torch.compile checks (compiled vs eager, compiled hard cases; up to
a couple of minutes when the inductor cache is cold) and the 640x480 / 200k-Gaussian peak
memory check.
"""
from __future__ import annotations

import functools
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

from reference_render import reference_render  # noqa: E402

from recgs_addon.core.render import kernels, numba_path, rasterizer  # noqa: E402
from recgs_addon.core.model.cameras import quat_to_rotmat  # noqa: E402
from recgs_addon.core.model.gaussians import SH_C0  # noqa: E402
from recgs_addon.core.render.rasterizer import render  # noqa: E402

PARAM_NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh")


# ------------------------------------------------------------------------------ scenes

def make_camera(rng, width, height, fx, fy, cx, cy):
    """A random-ish world-to-camera pose (viewmat) and K."""
    q = np.array([1.0, *rng.normal(0, 0.15, 3)])
    R = quat_to_rotmat(q)
    t = rng.normal(0, 0.3, 3)
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = t
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return vm, K


def make_scene(seed, n=60, width=40, height=30, deg=3, fx=None, fy=None, cx=None, cy=None,
               depth=(1.5, 5.0), scale=(0.02, 0.3), logit=(0.5, 1.5), spread=1.2):
    """Random Gaussians, mostly inside the frustum (some outside), camera-space placement."""
    rng = np.random.default_rng(seed)
    fx = fx if fx is not None else 1.1 * width
    fy = fy if fy is not None else 1.25 * width
    cx = cx if cx is not None else 0.43 * width
    cy = cy if cy is not None else 0.56 * height
    vm, K = make_camera(rng, width, height, fx, fy, cx, cy)
    z = rng.uniform(*depth, n)
    x = rng.uniform(-spread, spread, n) * z * 0.5 * width / fx
    y = rng.uniform(-spread, spread, n) * z * 0.5 * height / fy
    pc = np.stack([x, y, z], 1)
    R, t = vm[:3, :3], vm[:3, 3]
    means = (pc - t) @ R
    log_scales = np.log(rng.uniform(*scale, (n, 3)))
    quats = rng.normal(size=(n, 4))
    logits = rng.normal(logit[0], logit[1], n)
    k = (deg + 1) ** 2
    sh = rng.normal(0, 0.25, (n, k, 3))
    sh[:, 0, :] = rng.normal(0, 0.8, (n, 3))
    bg = rng.uniform(0, 1, 3)
    return dict(params=[means, log_scales, quats, logits, sh], viewmat=vm, K=K,
                width=width, height=height, background=bg)


def torch_params(scene, dtype, requires_grad=False):
    return [torch.tensor(p, dtype=dtype, requires_grad=requires_grad) for p in scene["params"]]


def run(scene, dtype=torch.float32, requires_grad=False, **kw):
    params = torch_params(scene, dtype, requires_grad)
    out = render(*params, torch.tensor(scene["viewmat"], dtype=dtype),
                 torch.tensor(scene["K"], dtype=dtype), scene["width"], scene["height"],
                 background=torch.tensor(scene["background"], dtype=dtype),
                 **{"compiled": False, **kw})
    return out, params


def run_reference(scene, **kw):
    kw.pop("tile_size", None)
    kw.pop("compiled", None)
    return reference_render(*scene["params"], scene["viewmat"], scene["K"], scene["width"],
                            scene["height"], background=scene["background"], **kw)


def loss_weights(scene, seed=123):
    rng = np.random.default_rng(seed)
    h, w = scene["height"], scene["width"]
    return rng.normal(size=(h, w, 3)), rng.normal(size=(h, w)), rng.normal(size=(h, w))


def weighted_loss(rgb, alpha, depth, weights):
    wr, wa, wd = weights
    if isinstance(rgb, torch.Tensor):
        wr, wa, wd = (torch.tensor(x, dtype=rgb.dtype) for x in weights)
    return (rgb * wr).sum() + (alpha * wa).sum() + (depth * wd).sum()


def assert_finite(*tensors):
    for t in tensors:
        assert t is not None
        assert torch.isfinite(t).all(), "non-finite values"


def render_and_backward(scene, dtype=torch.float32, **kw):
    out, params = run(scene, dtype, requires_grad=True, **kw)
    loss = weighted_loss(out.rgb, out.alpha, out.depth, loss_weights(scene))
    loss.backward()
    return out, params


# ------------------------------------------------------------------------------ forward

FORWARD_CASES = [(seed, deg, aa) for seed, (deg, aa) in enumerate(
    [(0, False), (1, False), (2, True), (3, False), (3, True), (3, False)])]


@pytest.mark.parametrize("seed,deg,antialiased", FORWARD_CASES)
def test_forward_matches_reference(seed, deg, antialiased):
    scene = make_scene(seed, deg=deg, width=37, height=29)   # not multiples of the tile
    ref = run_reference(scene, antialiased=antialiased)
    for dtype, tol in ((torch.float32, 1e-5), (torch.float64, 1e-10)):
        out, _ = run(scene, dtype, antialiased=antialiased)
        assert out.stats["visible"] > 20
        for key in ("rgb", "alpha", "depth"):
            err = np.abs(getattr(out, key).numpy() - ref[key]).max()
            assert err < tol, (key, dtype, err)


def test_forward_dense_opaque_scene_with_stops():
    """Many opaque, overlapping layers: alpha clamp and T < 1e-4 stop are exercised."""
    scene = make_scene(11, n=150, width=32, height=24, logit=(4.0, 2.0), scale=(0.1, 0.5))
    ref = run_reference(scene)
    assert ref["n_stopped"] > 50 and ref["n_clamped"] > 10
    out, _ = run(scene, torch.float32)
    for key in ("rgb", "alpha", "depth"):
        assert np.abs(getattr(out, key).numpy() - ref[key]).max() < 1e-5


@pytest.mark.parametrize("seed", [0, 1])
def test_forward_matches_reference_needles(seed):
    """Thin, elongated Gaussians (up to 1000:1): the tight ellipse-to-tile binning and the
    Cholesky-form Mahalanobis distance must not lose any pixel."""
    scene = make_scene(20 + seed, n=80, width=48, height=36, deg=1, spread=1.5)
    rng = np.random.default_rng(seed)
    ls = np.log(rng.uniform(0.003, 0.01, (80, 3)))
    ls[np.arange(80), rng.integers(0, 3, 80)] = np.log(rng.uniform(0.3, 3.0, 80))
    scene["params"][1] = ls
    ref = run_reference(scene)
    for dtype, tol in ((torch.float32, 1e-5), (torch.float64, 1e-10)):
        for ts in (4, 16):
            out, _ = run(scene, dtype, tile_size=ts)
            for key in ("rgb", "alpha", "depth"):
                err = np.abs(getattr(out, key).numpy() - ref[key]).max()
                assert err < tol, (key, dtype, ts, err)


def test_radii_and_culling_match_reference():
    scene = make_scene(3, n=200, spread=2.5, width=40, height=30)
    ref = run_reference(scene)
    out, _ = run(scene, torch.float64)
    radii = out.radii.numpy()
    vis = radii > 0
    assert 0 < vis.sum() < len(radii)
    np.testing.assert_array_equal(radii[vis], ref["radii"][vis])
    # Culled Gaussians draw nothing in the reference either.
    assert not ref["touched"][~vis].any()
    np.testing.assert_allclose(out.means2d.detach().numpy()[vis], ref["means2d"][vis],
                               rtol=0, atol=1e-9)
    assert out.radii.dtype == torch.int32


def _precull_vs_exact(scene):
    """(float64 inputs, the exact cull rows over all Gaussians, drawn (N,), candidates (N,))
    for a 37x23 view of ``scene``."""
    from recgs_addon.core.render import projection

    f64 = torch.float64
    means, log_scales, quats, logits = (torch.tensor(x, dtype=f64) for x in scene["params"][:4])
    vm, K = (torch.tensor(scene[k], dtype=f64) for k in ("viewmat", "K"))
    exact = projection._cull_rows(means, log_scales, quats, logits, vm, K, 37, 23, 0.2, False)
    cand = projection._candidates(means, log_scales, logits, vm, K, 37, 23, 0.2)
    return (means, log_scales, quats, logits, vm, K), exact, exact[:, 0] > 0, cand


@pytest.mark.parametrize("seed", range(4))
def test_precull_never_drops_a_visible_gaussian(seed):
    """The cheap candidate test in front of the cull pass keeps every Gaussian that the exact
    pass over all Gaussians draws, and the radii, order and ellipses are unchanged, on scenes
    with scales over 5 decades, centres up to 4x outside the frustum, rims just off the image
    and opacities from invisible to opaque."""
    from recgs_addon.core.render import projection

    scene = make_scene(100 + seed, n=4000, width=37, height=23, deg=0, depth=(0.1, 30.0),
                       scale=(1e-4, 10.0), logit=(-2.0, 4.0), spread=4.0)
    scene["params"][1] = np.log(np.exp(scene["params"][1]) ** np.random.default_rng(seed).uniform(
        0.5, 1.5, (4000, 3)))
    (means, log_scales, quats, logits, vm, K), exact, drawn, cand = _precull_vs_exact(scene)
    assert not (drawn & ~cand).any()
    assert 0.02 < drawn.float().mean() < 0.9 and cand.float().mean() < 0.95   # a real test
    proj = projection.project_gaussians(means, log_scales, quats, logits, vm, K, 37, 23)
    radii = torch.where(drawn, torch.ceil(exact[:, 13]), torch.zeros_like(exact[:, 13])).to(torch.int32)
    assert torch.equal(proj.radii, radii)
    vis = torch.nonzero(drawn).squeeze(1)
    assert torch.equal(proj.ids, vis[torch.sort(exact[vis, 1], stable=True).indices])
    assert torch.equal(proj.cov2d, exact[proj.ids, 4:8])


def test_precull_bound_is_tight_where_it_matters():
    """Many large, opaque Gaussians whose footprints end near the image edge: the candidate
    test keeps every one the exact pass draws (bounds from the mean scale, or without the
    Jacobian's x/z and y/z terms, drop some of these), and it drops most of those that the
    exact pass culls."""
    scene = make_scene(7, n=20000, width=37, height=23, deg=0, depth=(0.5, 4.0),
                       scale=(0.05, 1.0), logit=(3.0, 6.0), spread=8.0)
    _, _, drawn, cand = _precull_vs_exact(scene)
    assert not (drawn & ~cand).any()
    assert 0.05 < drawn.float().mean() < 0.9
    assert (cand & ~drawn).sum() < 0.5 * (~drawn).sum()


@pytest.mark.parametrize("tile_size", [1, 4, 16, 32])
def test_tile_size_and_chunking_do_not_change_results(tile_size):
    scene = make_scene(4, n=80, width=45, height=27)
    base, _ = run(scene, torch.float64)
    out, _ = run(scene, torch.float64, tile_size=tile_size, chunk_pairs=500)
    assert out.stats["chunks"] > 1
    for key in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(getattr(out, key).numpy(), getattr(base, key).numpy(),
                                   rtol=0, atol=1e-12)


def test_low_memory_mode_is_identical():
    scene = make_scene(9, n=120, width=40, height=30, logit=(3.0, 2.0))
    a, pa = render_and_backward(scene, chunk_pairs=4000)
    b, pb = render_and_backward(scene, chunk_pairs=4000, low_memory=True)
    for x, y in zip([a.rgb, a.means2d.grad] + [p.grad for p in pa],
                    [b.rgb, b.means2d.grad] + [p.grad for p in pb]):
        assert torch.equal(x, y)


def test_output_shapes_and_types():
    scene = make_scene(5, n=30, width=20, height=10)
    out, _ = run(scene)
    assert out.rgb.shape == (10, 20, 3) and out.alpha.shape == (10, 20)
    assert out.depth.shape == (10, 20) and out.means2d.shape == (30, 2)
    assert out.radii.shape == (30,) and out.rgb.dtype == torch.float32


# ------------------------------------------------------------------------------ gradients

def grad_scene(seed, n, deg, antialiased=False):
    """Small scene (16 x 12) used for finite differences. Searches seeds until no sample lies
    within 1e-4 (relative) of a threshold and the stop rule (and, without antialiasing, which
    lowers opacities, the 0.99 clamp) is used."""
    for s in range(seed, seed + 200):
        scene = make_scene(s, n=n, width=16, height=12, deg=deg, fx=15.0, fy=17.0, cx=7.3,
                           cy=6.6, depth=(2.0, 4.0), scale=(0.15, 0.6), logit=(4.0, 2.5),
                           spread=0.9)
        ref = run_reference(scene, antialiased=antialiased)
        if (min(ref["margins"].values()) > 1e-4 and ref["n_stopped"] > 0
                and (antialiased or ref["n_clamped"] > 0)):
            return scene
    raise AssertionError("no threshold-free scene found")


@functools.lru_cache(maxsize=None)
def finite_difference_grads(seed, n, deg, antialiased):
    """Central differences of the weighted loss of the float64 reference.

    The step balances a central difference's two errors: truncation, about h^2 |L'''| / 6, and
    rounding, about eps |L| / h with the loss L near 20 here. At h = 1e-6 rounding alone is
    ~4e-9, which against the smallest gradient scale compared (1 % of the opacity logits'
    largest gradient, ~7e-4) is a relative error of ~5e-6, and the last bits of a float64 sum
    differ between CPUs (vector widths): 3.5e-6 on one machine, 1.3e-5 on another. At
    h = 1e-5 rounding is ten times smaller and truncation still ~1e-8 relative; every
    threshold lies at least 1e-4 (relative) from every sample (grad_scene), so the step
    crosses none.
    """
    scene = grad_scene(seed, n, deg, antialiased)
    weights = loss_weights(scene)
    h = 1e-5

    def loss(params):
        r = reference_render(*params, scene["viewmat"], scene["K"], scene["width"],
                             scene["height"], background=scene["background"],
                             antialiased=antialiased)
        return weighted_loss(r["rgb"], r["alpha"], r["depth"], weights)

    grads = []
    for k, p in enumerate(scene["params"]):
        fd = np.zeros_like(p)
        for idx in np.ndindex(p.shape):
            pp = [q.copy() for q in scene["params"]]
            pp[k][idx] += h
            lp = loss(pp)
            pp[k][idx] -= 2 * h
            fd[idx] = (lp - loss(pp)) / (2 * h)
        grads.append(fd)
    return scene, grads


GRAD_CASES = [(0, 9, 3, False), (40, 12, 1, True), (80, 14, 0, False)]


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-5), (torch.float32, 1e-3)])
@pytest.mark.parametrize("seed,n,deg,antialiased", GRAD_CASES)
def test_gradients_match_finite_differences(seed, n, deg, antialiased, dtype, rtol):
    scene, fd = finite_difference_grads(seed, n, deg, antialiased)
    out, params = render_and_backward(scene, dtype, antialiased=antialiased)
    for name, p, g_fd in zip(PARAM_NAMES, params, fd):
        g = p.grad.numpy()
        scale = np.abs(g_fd).max()
        assert scale > 0, name
        # Relative error where the gradient is not tiny (>= 1% of the largest of its kind),
        # absolute error (relative to that 1%) below.
        err = np.abs(g - g_fd) / np.maximum(np.abs(g_fd), 1e-2 * scale)
        assert err.max() < rtol, (name, err.max())


def test_sh_blocks_equal_one_tensor():
    """SH passed as (DC, rest) blocks renders and differentiates exactly like the joined tensor."""
    scene = make_scene(4, n=80, deg=3)
    a, pa = render_and_backward(scene)
    params = torch_params(scene, torch.float32, requires_grad=False)
    dc = params[4][:, :1].clone().requires_grad_(True)
    rest = params[4][:, 1:].clone().requires_grad_(True)
    geo = [p.requires_grad_(True) for p in params[:4]]
    b = render(*geo, (dc, rest), torch.tensor(scene["viewmat"], dtype=torch.float32),
               torch.tensor(scene["K"], dtype=torch.float32), scene["width"], scene["height"],
               background=torch.tensor(scene["background"], dtype=torch.float32), compiled=False)
    weighted_loss(b.rgb, b.alpha, b.depth, loss_weights(scene)).backward()
    assert torch.equal(a.rgb, b.rgb)
    for x, y in zip(pa[:4], geo):
        assert torch.equal(x.grad, y.grad)
    assert torch.equal(pa[4].grad, torch.cat([dc.grad, rest.grad], 1))
    assert float(pa[4].grad[:, 1:].abs().sum()) > 0   # the rest block does get gradient


def test_means2d_gradient_is_exposed():
    """means2d.grad is filled, zero for culled Gaussians, and its x/y sums equal the
    derivative of the loss wrt the principal point (which shifts every 2D mean)."""
    scene, _ = finite_difference_grads(*GRAD_CASES[0])
    out, _ = render_and_backward(scene, torch.float64)
    g2d = out.means2d.grad
    assert g2d is not None and g2d.shape == (len(scene["params"][0]), 2)
    assert (g2d[out.radii == 0] == 0).all()
    weights = loss_weights(scene)
    h = 1e-6
    for axis, (r, c) in enumerate([(0, 2), (1, 2)]):
        vals = []
        for sign in (1, -1):
            K = scene["K"].copy()
            K[r, c] += sign * h
            ref = reference_render(*scene["params"], scene["viewmat"], K, scene["width"],
                                   scene["height"], background=scene["background"])
            vals.append(weighted_loss(ref["rgb"], ref["alpha"], ref["depth"], weights))
        fd = (vals[0] - vals[1]) / (2 * h)
        assert abs(g2d[:, axis].sum().item() - fd) < 1e-6 * max(1.0, abs(fd))


def test_background_gradient():
    scene = make_scene(6, n=20, width=12, height=10)
    params = torch_params(scene, torch.float64, True)
    bg = torch.tensor(scene["background"], requires_grad=True)
    out = render(*params, torch.tensor(scene["viewmat"]), torch.tensor(scene["K"]),
                 12, 10, background=bg, compiled=False)
    out.rgb.sum().backward()
    expected = (1.0 - out.alpha.detach()).sum().expand(3)
    torch.testing.assert_close(bg.grad, expected)


# ------------------------------------------------------------------------------ hard cases

def single_camera_scene(n, width=24, height=18, deg=1, seed=0):
    """Camera at the origin looking along +z (identity viewmat)."""
    rng = np.random.default_rng(seed)
    k = (deg + 1) ** 2
    sh = rng.normal(0, 0.3, (n, k, 3))
    return dict(params=[np.zeros((n, 3)), np.full((n, 3), np.log(0.1)),
                        np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.full(n, 1.0), sh],
                viewmat=np.eye(4), K=np.array([[20.0, 0, width / 2], [0, 20.0, height / 2],
                                               [0, 0, 1]]),
                width=width, height=height, background=np.array([0.2, 0.3, 0.4]))


def check_hard(scene, compare=True, **kw):
    """No NaN/Inf in any output or gradient, float32; optionally agrees with the oracle
    (given the same float32-rounded parameters)."""
    scene = dict(scene, params=[p.astype(np.float32).astype(np.float64) for p in scene["params"]])
    out, params = render_and_backward(scene, torch.float32, **kw)
    assert_finite(out.rgb, out.alpha, out.depth, out.means2d, out.means2d.grad,
                  *[p.grad for p in params])
    if compare:
        ref = run_reference(scene, **kw)
        for key in ("rgb", "alpha", "depth"):
            err = np.abs(getattr(out, key).detach().numpy() - ref[key]).max()
            assert err < 1e-5 * max(1.0, np.abs(ref[key]).max()), (key, err)
    return out, params


def test_hard_behind_camera_and_near_plane():
    s = single_camera_scene(8)
    means = s["params"][0]
    means[:, 2] = [-3.0, -0.1, 0.0, 0.1, 0.2 - 1e-6, 0.2 + 1e-6, 0.25, 1.0]
    means[:, 0] = [0.0, 0.05, -0.05, 0.0, 0.02, 0.0, 0.01, 0.0]
    s["params"][1][:] = np.log([0.5])        # large: straddle the near plane
    s["params"][1][6] = np.log([2.0, 2.0, 2.0])
    out, _ = check_hard(s)
    assert (out.radii[:5] == 0).all() and (out.radii[5:] > 0).all()


def test_hard_far_outside_image():
    s = single_camera_scene(6)
    m = s["params"][0]
    m[:] = [[1e4, 0, 1.0], [-1e6, 1e6, 2.0], [0, -50.0, 1.0], [30.0, 0, 1.0], [0, 0, 2.0],
            [-1e3, 0, 3.0]]
    s["params"][1][3] = np.log([40.0, 40.0, 40.0])   # centre off-screen, covers the image
    s["params"][1][5] = np.log([1e3, 1.0, 1.0])      # huge needle reaching into view
    check_hard(s)


def test_hard_tiny_and_huge_scales():
    s = single_camera_scene(4)
    s["params"][0][:] = [[0.0, 0.0, 2.0], [0.1, 0.1, 3.0], [0.0, 0.0, 5.0], [0.2, 0, 1.5]]
    s["params"][1][:] = np.log([[1e-7] * 3, [1e3] * 3, [1e-7, 1e3, 1e-7], [1e3, 1e3, 1e-7]])
    for aa in (False, True):
        check_hard(s, antialiased=aa)


def test_hard_anisotropy():
    s = single_camera_scene(6, seed=1)
    rng = np.random.default_rng(2)
    s["params"][0][:, 2] = np.linspace(2.0, 4.0, 6)
    s["params"][0][:, :2] = rng.normal(0, 0.2, (6, 2))
    s["params"][1][:] = np.log([1.0, 1e-5, 1e-5]) + np.log(rng.uniform(0.1, 1.0, (6, 1)))
    s["params"][1][5] = np.log([1e-5, 1.0, 1.0])    # a disc seen edge-on or face-on
    s["params"][2][:] = rng.normal(size=(6, 4))
    # float32 loses the shape of a 1e5:1 needle in the INRIA conic form, not in ours: compare.
    check_hard(s)


def test_hard_extreme_logit_opacities():
    s = single_camera_scene(6)
    s["params"][0][:, 2] = [1.0, 1.5, 2.0, 2.5, 3.0, 3.5]
    s["params"][0][:, 0] = [0.0, 0.1, -0.1, 0.05, 0.0, 0.02]
    s["params"][3][:] = [30.0, -30.0, 30.0, -30.0, 8.0, -8.0]
    out, params = check_hard(s)
    assert out.radii[1] == 0 and out.radii[3] == 0


def one_pixel_stack(n):
    """n Gaussians stacked on the centre pixel of a 4x3 image (depths 1-50, mixed opacities)."""
    rng = np.random.default_rng(3)
    s = single_camera_scene(n, width=4, height=3, deg=0)
    s["params"][0][:] = np.stack([np.zeros(n), np.zeros(n), rng.uniform(1.0, 50.0, n)], 1)
    s["params"][1][:] = np.log(0.01 * s["params"][0][:, 2:3])
    s["params"][3][:] = rng.normal(-1.0, 2.0, n)
    s["K"][0, 2] = s["K"][1, 2] = 1.5
    return s


def test_hard_20000_gaussians_on_one_pixel():
    """Transmittance underflows to 0 in the cumulative product; results must stay exact."""
    out, params = check_hard(one_pixel_stack(20000))
    assert out.alpha.max() > 0.999


def test_hard_equal_depths_are_ordered_by_index():
    s = single_camera_scene(5, deg=0)
    s["params"][0][:] = [[0, 0, 2.0]] * 5
    s["params"][0][:, 0] = [0.0, 0.01, -0.01, 0.02, 0.0]  # same z, different x
    s["params"][4][:, 0, :] = np.eye(5, 3) * 2.0 - 0.5
    s["params"][3][:] = 0.5
    out1, _ = check_hard(s)
    out2, _ = check_hard(s)
    assert torch.equal(out1.rgb, out2.rgb)


def test_hard_zero_gaussians():
    s = single_camera_scene(0)
    out, params = render_and_backward(s, torch.float32)
    bg = torch.tensor(s["background"], dtype=torch.float32)
    assert torch.equal(out.rgb, bg.expand(18, 24, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert all(p.grad is not None and p.grad.numel() == 0 for p in params)


def test_hard_all_culled():
    s = single_camera_scene(3)
    s["params"][0][:, 2] = -1.0
    out, params = check_hard(s)
    assert (out.radii == 0).all()
    assert all((p.grad == 0).all() for p in params)


def test_hard_one_pixel_image():
    s = single_camera_scene(7, width=1, height=1)
    s["params"][0][:, 2] = np.linspace(1.0, 3.0, 7)
    check_hard(s)
    check_hard(s, tile_size=16)


def test_hard_near_zero_quaternion():
    s = single_camera_scene(4)
    s["params"][0][:, 2] = [1.0, 2.0, 3.0, 4.0]
    s["params"][1][:] = np.log([0.3, 0.05, 0.1])
    s["params"][2][:] = [[1e-10, 2e-10, -1e-10, 0.5e-10], [1e-20, 0, 0, 0], [0, 0, 0, 0],
                         [0.5, 0.5, 0.5, 0.5]]
    check_hard(s, compare=False)
    # Above the normalisation floor the rotation is exactly q / |q|:
    s["params"][2][1:3] = [[0.3, 0.1, 0.7, 0.2]] * 2
    check_hard(s)


def test_bit_identical_across_runs():
    scene = make_scene(7, n=300, width=48, height=40, logit=(3.0, 2.0))
    a, pa = render_and_backward(scene)
    b, pb = render_and_backward(scene)
    for x, y in zip([a.rgb, a.alpha, a.depth, a.means2d.grad] + [p.grad for p in pa],
                    [b.rgb, b.alpha, b.depth, b.means2d.grad] + [p.grad for p in pb]):
        assert torch.equal(x, y)


def test_falls_back_to_eager_when_compile_fails(monkeypatch):
    def broken():
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(rasterizer, "_compiled_kernels", broken)
    monkeypatch.setattr(rasterizer, "_KERNEL_CACHE", {})
    scene = make_scene(10, n=20, width=12, height=8)
    with pytest.warns(UserWarning, match="torch.compile unavailable"):
        out, _ = run(scene, compiled=None)
    assert out.stats["compiled"] is False
    with pytest.raises(RuntimeError):
        run(scene, compiled=True)


# ------------------------------------------------------------------------------ slow

def _compile_works():
    try:
        rasterizer.get_kernels(True)
        return True
    except RuntimeError:
        return False


@pytest.mark.slow
def test_compiled_kernels_match_eager():
    if not _compile_works():
        pytest.skip("torch.compile is not available here")
    scene = make_scene(8, n=400, width=64, height=48, logit=(2.0, 2.0))
    a, pa = render_and_backward(scene, compiled=False)
    b, pb = render_and_backward(scene, compiled=True)
    assert b.stats["compiled"]
    for x, y in zip([a.rgb, a.alpha, a.depth], [b.rgb, b.alpha, b.depth]):
        assert (x - y).abs().max() < 1e-6
    for x, y in zip([a.means2d.grad] + [p.grad for p in pa],
                    [b.means2d.grad] + [p.grad for p in pb]):
        assert (x - y).abs().max() <= 1e-5 * max(1.0, x.abs().max().item())


@pytest.mark.slow
def test_compiled_hard_cases():
    """The compiled kernels on shapes that specialise (1x1 image, one tile, huge G)."""
    if not _compile_works():
        pytest.skip("torch.compile is not available here")
    s = single_camera_scene(7, width=1, height=1)
    s["params"][0][:, 2] = np.linspace(1.0, 3.0, 7)
    check_hard(s, compiled=True)
    n = 5000
    rng = np.random.default_rng(3)
    s = single_camera_scene(n, width=4, height=3, deg=0)
    s["params"][0][:] = np.stack([np.zeros(n), np.zeros(n), rng.uniform(1.0, 50.0, n)], 1)
    s["params"][1][:] = np.log(0.01 * s["params"][0][:, 2:3])
    s["K"][0, 2] = s["K"][1, 2] = 1.5
    check_hard(s, compiled=True)
    out, _ = render_and_backward(single_camera_scene(0), compiled=True)
    assert out.rgb.shape == (18, 24, 3)


@pytest.mark.slow
def test_memory_640x480_200k_under_4gb():
    """Peak RSS (VmHWM) of forward + backward at 640 x 480 with 200k Gaussians < 4 GB."""
    code = textwrap.dedent(f"""
        import sys; sys.path.insert(0, {ROOT!r})
        import torch
        from benchmarks.bench_rasterizer import survey_scene, run_once
        torch.set_num_threads(2)
        scene = survey_scene(200_000, 640, 480, seed=0)
        run_once(scene, backward=True, compiled=False)
        for line in open('/proc/self/status'):
            if line.startswith('VmHWM'):
                print(int(line.split()[1]) * 1024)
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=1200)
    assert res.returncode == 0, res.stderr
    peak = int(res.stdout.strip().splitlines()[-1])
    assert peak < 4 * 1024 ** 3, peak


def test_compiled_path_survives_first_call_under_no_grad():
    """The compile smoke test must not mistake torch.no_grad() for a broken compiler."""
    import subprocess
    import sys

    code = ("import warnings, torch\n"
            "from recgs_addon.core.render import rasterizer as r\n"
            "warnings.filterwarnings('error', message='torch.compile unavailable')\n"
            "with torch.no_grad():\n"
            "    kern = r.get_kernels(None)\n"
            "print('compiled' if kern.compiled else 'eager')\n")
    from conftest import ROOT

    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    # where no compiler works the fallback warning turns into an error here, which is what
    # this test would then report; on machines with a compiler it must stay compiled
    assert res.returncode == 0 and res.stdout.strip() == "compiled", res.stderr[-2000:]


# ------------------------------------------------------------------------------ numba

def _numba_works():
    return kernels.numba_kernels_ready()


needs_numba = pytest.mark.skipif(not _numba_works(), reason="numba is not installed here")


def assert_numba_matches_eager(scene, dtype=torch.float32, **kw):
    """The numba path against the eager torch oracle, same float32 inputs: images to 1e-6
    (relative to their size where above 1), radii exactly, gradients (means2d and every
    parameter) to 1e-5 relative to the largest, nothing non-finite. Returns the numba run."""
    a, pa = render_and_backward(scene, dtype, compiled=False, **kw)
    b, pb = render_and_backward(scene, dtype, compiled="numba", **kw)
    assert b.stats["path"] == "numba" and b.stats["compiled"] is False
    assert_finite(b.rgb, b.alpha, b.depth, b.means2d.grad, *[p.grad for p in pb])
    for key in ("rgb", "alpha", "depth"):
        x, y = getattr(a, key), getattr(b, key)
        assert (x - y).abs().max() <= 1e-6 * max(1.0, x.abs().max().item()), key
    assert torch.equal(a.radii, b.radii)
    for name, x, y in zip(("means2d",) + PARAM_NAMES, [a.means2d.grad] + [p.grad for p in pa],
                          [b.means2d.grad] + [p.grad for p in pb]):
        assert (x - y).abs().max() <= 1e-5 * max(1.0, x.abs().max().item()), name
    return b, pb


def _rounded(scene):
    return dict(scene, params=[p.astype(np.float32).astype(np.float64) for p in scene["params"]])


@needs_numba
@pytest.mark.parametrize("seed, deg, antialiased", FORWARD_CASES)
def test_numba_matches_eager(seed, deg, antialiased):
    """Random scenes (SH 0-3, antialiased or not), and a dense one where pixels stop early."""
    assert_numba_matches_eager(make_scene(seed, n=80, deg=deg), antialiased=antialiased)


@needs_numba
def test_numba_matches_eager_dense_opaque_stacks():
    """Near-opaque stacks: the 0.99 clamp and the T_MIN stop fire on most pixels."""
    scene = make_scene(8, n=400, width=64, height=48, logit=(3.0, 2.0))
    b, _ = assert_numba_matches_eager(scene)
    assert b.alpha.max() > 0.9999 - 1e-6


@needs_numba
@pytest.mark.parametrize("tile_size", [1, 3, 16, 32])
def test_numba_matches_eager_other_tile_sizes(tile_size):
    """Tiles of 1, 9, 256 and 1024 pixels (4x4 is the default), image not a multiple."""
    assert_numba_matches_eager(make_scene(3, n=150, width=37, height=29, logit=(2.0, 2.0)),
                               tile_size=tile_size)


@needs_numba
def test_numba_matches_eager_on_one_pixel_stack():
    """5 000 Gaussians on one pixel: the stop after a few, long lists behind it."""
    b, _ = assert_numba_matches_eager(_rounded(one_pixel_stack(5000)))
    assert b.alpha.max() > 0.999


@needs_numba
def test_numba_matches_eager_tiny_huge_and_needles():
    s = single_camera_scene(4)
    s["params"][0][:] = [[0.0, 0.0, 2.0], [0.1, 0.1, 3.0], [0.0, 0.0, 5.0], [0.2, 0, 1.5]]
    s["params"][1][:] = np.log([[1e-7] * 3, [1e3] * 3, [1e-7, 1e3, 1e-7], [1e3, 1e3, 1e-7]])
    for aa in (False, True):
        assert_numba_matches_eager(_rounded(s), antialiased=aa)
    s = single_camera_scene(6, seed=1)
    rng = np.random.default_rng(2)
    s["params"][0][:, 2] = np.linspace(2.0, 4.0, 6)
    s["params"][0][:, :2] = rng.normal(0, 0.2, (6, 2))
    s["params"][1][:] = np.log([1.0, 1e-5, 1e-5]) + np.log(rng.uniform(0.1, 1.0, (6, 1)))
    s["params"][2][:] = rng.normal(size=(6, 4))
    assert_numba_matches_eager(_rounded(s))
    assert_numba_matches_eager(make_scene(5, n=60, scale=(0.001, 0.6)))


@needs_numba
def test_numba_matches_eager_with_empty_tiles_and_off_screen():
    """Gaussians in one corner only (most tiles empty), some far off-screen or behind."""
    s = single_camera_scene(6)
    s["params"][0][:] = [[-0.5, -0.4, 1.0], [-0.45, -0.38, 1.2], [1e4, 0, 1.0], [0, -50.0, 1.0],
                         [30.0, 0, 1.0], [0.0, 0.0, -2.0]]
    s["params"][1][:] = np.log(0.02)
    s["params"][1][4] = np.log([40.0, 40.0, 40.0])     # centre off-screen, covers the image
    assert_numba_matches_eager(_rounded(s))
    s["params"][1][4] = np.log(0.02)                    # now nothing reaches most tiles
    b, _ = assert_numba_matches_eager(_rounded(s))
    assert (b.alpha[-6:, -6:] == 0).all()


@needs_numba
def test_numba_degenerate_inputs():
    """Zero Gaussians, all culled, a 1x1 image, equal depths, near-zero quaternions."""
    out, params = render_and_backward(single_camera_scene(0), compiled="numba")
    assert out.rgb.shape == (18, 24, 3) and (out.alpha == 0).all()
    assert all(p.grad is not None and p.grad.numel() == 0 for p in params)
    s = single_camera_scene(3)
    s["params"][0][:, 2] = -1.0
    b, pb = assert_numba_matches_eager(s)
    assert all((p.grad == 0).all() for p in pb)
    s = single_camera_scene(7, width=1, height=1)
    s["params"][0][:, 2] = np.linspace(1.0, 3.0, 7)
    assert_numba_matches_eager(s)
    s = single_camera_scene(5, deg=0)
    s["params"][0][:] = [[0, 0, 2.0]] * 5
    s["params"][0][:, 0] = [0.0, 0.01, -0.01, 0.02, 0.0]
    s["params"][3][:] = 0.5
    assert_numba_matches_eager(s)
    s = single_camera_scene(4)
    s["params"][0][:, 2] = [1.0, 2.0, 3.0, 4.0]
    s["params"][1][:] = np.log([0.3, 0.05, 0.1])
    s["params"][2][:] = [[1e-10, 2e-10, -1e-10, 0.5e-10], [1e-20, 0, 0, 0], [0, 0, 0, 0],
                         [0.5, 0.5, 0.5, 0.5]]
    assert_numba_matches_eager(s)


@needs_numba
def test_numba_is_deterministic_and_float64_stays_eager():
    scene = make_scene(7, n=300, width=48, height=40, logit=(3.0, 2.0))
    a, pa = render_and_backward(scene, compiled="numba")
    b, pb = render_and_backward(scene, compiled="numba")
    for x, y in zip([a.rgb, a.means2d.grad] + [p.grad for p in pa], [b.rgb, b.means2d.grad] + [p.grad for p in pb]):
        assert torch.equal(x, y)
    out, _ = run(scene, torch.float64, compiled="numba")
    assert out.stats["path"] == "eager"      # numba's kernels are float32


def test_numba_missing_means_eager(monkeypatch):
    """No numba (or numba failing to import): ``compiled="numba"`` renders eagerly, with one
    warning, and gives the eager numbers."""
    from recgs_addon.core.render import numba_kernels
    monkeypatch.setattr(numba_kernels, "_STATE", {"error": ImportError("No module named 'numba'")})
    monkeypatch.setattr(rasterizer, "_KERNEL_CACHE", dict(rasterizer._KERNEL_CACHE))
    assert not kernels.numba_kernels_ready()
    scene = make_scene(3, n=50)
    with pytest.warns(UserWarning, match="numba kernels unavailable"):
        out, _ = run(scene, compiled="numba")
    ref, _ = run(scene, compiled=False)
    assert out.stats["path"] == "eager" and torch.equal(out.rgb, ref.rgb)


@needs_numba
def test_numba_failing_at_run_time_falls_back_to_eager(monkeypatch):
    """A numba kernel that raises mid-run: this render and every later one take the eager
    path (with a warning), and give the eager numbers."""
    from recgs_addon.core.render import numba_kernels
    monkeypatch.setattr(numba_kernels, "_STATE", dict(numba_kernels._STATE))   # restored after
    monkeypatch.setattr(rasterizer, "_KERNEL_CACHE", dict(rasterizer._KERNEL_CACHE))

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(rasterizer, "_render_numba", boom)
    scene = make_scene(3, n=50)
    ref, _ = run(scene, compiled=False)
    with pytest.warns(UserWarning, match="numba kernels failed"):
        out, _ = run(scene, compiled="numba")
    assert out.stats["path"] == "eager" and torch.equal(out.rgb, ref.rgb)
    assert not kernels.numba_kernels_ready() and "boom" in repr(numba_kernels.error())
    with pytest.warns(UserWarning, match="numba kernels unavailable"):
        again, _ = run(scene, compiled="numba")
    assert again.stats["path"] == "eager"


@needs_numba
@pytest.mark.parametrize("deg, antialiased", [(0, False), (1, True), (2, False), (3, True)])
def test_numba_projection_gradients_match_float64_autograd(deg, antialiased):
    """numba's projection + colour kernel (hand-written backward) against torch autograd through
    projection._project_rows and sh.eval_sh_colour in float64, on the same float32 inputs,
    with random gradients on every output: each parameter's gradient to 1e-6 of its largest
    (float32 rounding of the outputs and of the SH basis is all that may differ: ~1e-7)."""
    from recgs_addon.core.model.sh import eval_sh_colour
    from recgs_addon.core.render import projection

    # spread 2: a third of the centres lie outside the frustum clamp (1.3 x the half-width)
    scene = _rounded(make_scene(20 + deg, n=200, deg=3, scale=(0.005, 0.4), logit=(0.0, 3.0), spread=2.0))
    p32 = torch_params(scene, torch.float32)
    nk = rasterizer.get_kernels("numba").numba
    vm = np.asarray(scene["viewmat"], np.float64)
    K = np.asarray(scene["K"], np.float64)
    w, h = scene["width"], scene["height"]
    _, ids, _ = nk.cull(*(p.numpy() for p in p32[:4]), vm, K, w, h, 0.2, antialiased)
    ids = torch.from_numpy(ids)
    assert len(ids) > 50
    rows32 = [p.index_select(0, ids).requires_grad_() for p in p32]
    campos = projection.camera_centre(torch.from_numpy(vm)).numpy()
    outs = numba_path._ProjectNumba.apply(*rows32, (nk, deg, vm, K, campos, w, h, 0.2, antialiased))
    rows64 = [r.detach().double().requires_grad_() for r in rows32]
    q = projection._project_rows(*rows64[:4], torch.from_numpy(vm), torch.from_numpy(K), w, h, 0.2,
                                 antialiased)
    dirs = rows64[0] - torch.from_numpy(campos)
    colour = eval_sh_colour(deg, rows64[4], dirs / dirs.norm(dim=1, keepdim=True))
    ref = [torch.stack([q["u"], q["v"]], 1), torch.stack([q["l11"], q["l21"], q["l22"], q["opacity"]], 1),
           q["z"], colour]
    assert ((q["u"] - K[0, 2]).abs() > 1.3 * 0.5 * w).any()     # the frustum clamp is active
    gen = torch.Generator().manual_seed(deg)
    weights = [torch.randn(r.shape, generator=gen, dtype=torch.float64) for r in ref]
    for o, r in zip(outs[:4], ref):
        assert (o.double() - r).abs().max() <= 1e-6 * max(1.0, r.abs().max().item())
    sum((o.double() * g).sum() for o, g in zip(outs[:4], weights)).backward()
    sum((r * g).sum() for r, g in zip(ref, weights)).backward()
    for name, a, b in zip(PARAM_NAMES, rows32, rows64):
        err = (a.grad.double() - b.grad).abs().max().item()
        assert err <= 1e-6 * b.grad.abs().max().item(), (name, err, b.grad.abs().max().item())


@needs_numba
def test_numba_cull_reads_nothing_of_a_culled_row(monkeypatch):
    """A culled Gaussian's row of the cull table is never written past its flag: its radius
    is 0 whatever that memory holds (a signalling NaN here, as an uninitialised buffer may:
    rounding one raises numpy's "invalid value" warning), with no floating-point warning, and
    the drawn ones keep their radii."""
    import warnings

    scene = _rounded(make_scene(5, n=200, deg=0, scale=(0.005, 0.4), logit=(0.0, 3.0), spread=2.0))
    p32 = torch_params(scene, torch.float32)
    nk = rasterizer.get_kernels("numba").numba
    args = ([p.numpy() for p in p32[:4]], np.asarray(scene["viewmat"], np.float64),
            np.asarray(scene["K"], np.float64), scene["width"], scene["height"], 0.2, False)
    info, ids, radii = nk.cull(*args[0], *args[1:])
    real = nk.impl.cull

    def poisoned(lo, hi, *rest):
        rest[-1][lo:hi].view(np.uint64)[:] = 0x7FF0000000000001   # the info table: signalling NaN
        return real(lo, hi, *rest)

    monkeypatch.setattr(nk.impl, "cull", poisoned)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        info2, ids2, radii2 = nk.cull(*args[0], *args[1:])
    drawn = info2[:, 0] > 0
    assert 0 < drawn.sum() < len(drawn)
    np.testing.assert_array_equal(radii2, radii)
    assert (radii2[~drawn] == 0).all() and (radii2[drawn] > 0).all()
    np.testing.assert_array_equal(ids2, ids)


# ------------------------------------------------------------------------------ blending weights

def _weights_of(scene, dtype, **kw):
    """(render output, params, weights) of a render whose backward filled ``weights``."""
    n = len(scene["params"][0])
    w = torch.zeros(n, dtype=torch.float64)
    out, params = run(scene, dtype, requires_grad=True, weights=w, **kw)
    weighted_loss(out.rgb, out.alpha, out.depth, loss_weights(scene)).backward()
    return out, params, w


def test_blending_weights_match_float64_finite_differences():
    """A Gaussian's weight in a view is the pixels it supplies, sum_p alpha_i T_i: the
    derivative of the summed image wrt its (unclamped) colour, taken here by central
    differences of the float64 reference renderer, dense stacks (stops) included."""
    scene = make_scene(5, n=40, deg=0, logit=(1.5, 1.5))
    scene["params"][4][:, 0, :] = np.abs(scene["params"][4][:, 0, :]) + 0.2   # colour > 0: no clamp
    out, _, w = _weights_of(scene, torch.float64)
    h = 1e-4
    fd = np.zeros(len(w))
    for i in range(len(w)):
        sums = []
        for sign in (1, -1):
            sh = scene["params"][4].copy()
            sh[i, 0, 0] += sign * h
            s = dict(scene, params=scene["params"][:4] + [sh])
            sums.append(run_reference(s)["rgb"][..., 0].sum())
        fd[i] = (sums[0] - sums[1]) / (2 * h * SH_C0)
    assert (fd > 1.0).sum() >= 5 and fd.min() < 0.05   # carried and nearly hidden ones both
    np.testing.assert_allclose(w.numpy(), fd, rtol=1e-6, atol=1e-7)
    assert (w[out.radii == 0] == 0).all()


@pytest.mark.parametrize("compiled", [False, pytest.param("numba", marks=needs_numba)])
def test_blending_weights_leave_the_gradients_alone(compiled):
    """Asking for the weights changes no output and no gradient, bit for bit."""
    scene = make_scene(11, n=120, width=48, height=36, logit=(2.0, 2.0))
    a, pa = render_and_backward(scene, torch.float32, compiled=compiled)
    b, pb, w = _weights_of(scene, torch.float32, compiled=compiled)
    assert torch.equal(a.rgb, b.rgb) and float(w.sum()) > 0
    for x, y in zip([a.means2d.grad] + [p.grad for p in pa], [b.means2d.grad] + [p.grad for p in pb]):
        assert torch.equal(x, y)


@needs_numba
@pytest.mark.parametrize("seed, logit", [(3, (0.5, 1.5)), (8, (3.0, 2.0))])
def test_numba_blending_weights_match_eager(seed, logit):
    """numba's weights (a sum in its backward) against the eager path's, float32 inputs,
    with the clamp and the stop firing on the dense scene; their sum is the image's alpha."""
    scene = make_scene(seed, n=300, width=64, height=48, logit=logit)
    a, _, wa = _weights_of(scene, torch.float32, compiled=False)
    b, _, wb = _weights_of(scene, torch.float32, compiled="numba")
    assert (wa - wb).abs().max() <= 1e-5 * wa.abs().max()
    alpha = float(b.alpha.detach().sum())
    assert abs(float(wb.sum()) - alpha) <= 1e-4 * alpha
