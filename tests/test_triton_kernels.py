"""The GPU path's kernels (core/render/triton_kernels.py: projection + SH colour and
compositing) against the eager torch oracle, run in Triton's interpreter (no GPU needed): images, radii, every gradient and
the blending weights, on the scenes that break rasterizers (the clamp and the stop on dense
stacks, one pixel under thousands of Gaussians, empty tiles, frames not a multiple of the
tile). Triton fixes interpreter or compiler when it is first imported, so the cases run in
one child process with ``TRITON_INTERPRET=1`` and report their errors; the tests read them.

Run alone: ``TRITON_INTERPRET=1 .venv/bin/python tests/test_triton_kernels.py`` prints them."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

needs_triton = pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                                  reason="Triton is not installed here (requirements-dev.txt has it)")


# ------------------------------------------------------------------------------ the child

def _errors(a, pa, b, pb, names):
    """Largest differences: images relative to max(1, |eager|), gradients relative to the
    largest eager gradient of each input; whether all are finite; the paths taken."""
    import torch
    out = {"path": b.stats["path"], "radii_equal": bool(torch.equal(a.radii, b.radii))}
    for key in ("rgb", "alpha", "depth"):
        x, y = getattr(a, key).detach(), getattr(b, key).detach()
        out[key] = float((x - y).abs().max()) / max(1.0, float(x.abs().max()))
    finite = all(bool(torch.isfinite(t).all()) for t in [b.rgb, b.alpha, b.depth, b.means2d.grad]
                 + [p.grad for p in pb])
    for name, x, y in zip(("means2d",) + names, [a.means2d.grad] + [p.grad for p in pa],
                          [b.means2d.grad] + [p.grad for p in pb]):
        out["d_" + name] = float((x - y).abs().max()) / max(1.0, float(x.abs().max()))
    out["finite"] = finite
    out["alpha_max"] = float(b.alpha.detach().max())
    return out


def _cases():
    import torch

    sys.path[:0] = [HERE, ROOT]
    import test_rasterizer as tr

    def compare(scene, dtype=torch.float32, **kw):
        a, pa = tr.render_and_backward(scene, dtype, compiled=False, **kw)
        b, pb = tr.render_and_backward(scene, dtype, compiled="triton", **kw)
        return _errors(a, pa, b, pb, tr.PARAM_NAMES)

    res = {}
    for seed, deg, aa in [(0, 3, False), (1, 0, True), (2, 1, False), (4, 2, True)]:
        res[f"random-{seed}"] = compare(tr.make_scene(seed, n=60, deg=deg), antialiased=aa)
    res["dense"] = compare(tr.make_scene(8, n=150, width=36, height=20, logit=(3.0, 2.0)))
    res["odd-frame"] = compare(tr.make_scene(3, n=80, width=37, height=29, logit=(2.0, 2.0)))
    res["one-pixel"] = compare(tr._rounded(tr.one_pixel_stack(2000)))
    s = tr.single_camera_scene(6)
    s["params"][0][:] = [[-0.5, -0.4, 1.0], [-0.45, -0.38, 1.2], [1e4, 0, 1.0], [0, -50.0, 1.0],
                         [30.0, 0, 1.0], [0.0, 0.0, -2.0]]
    s["params"][1][:] = np.log(0.02)
    s["params"][1][4] = np.log([40.0, 40.0, 40.0])     # centre off-screen, covers the image
    s = dict(s, width=40, height=34)
    res["off-screen"] = compare(tr._rounded(s))
    s["params"][1][4] = np.log(0.02)                    # now nothing reaches most tiles
    res["empty-tiles"] = compare(tr._rounded(s))
    b, _ = tr.run(s, torch.float32, compiled="triton")
    res["empty-tiles"]["corner_alpha"] = float(b.alpha[-6:, -6:].abs().max())
    res["float64"] = {"path": tr.run(tr.make_scene(0, n=20), torch.float64, compiled="triton")[0].stats["path"]}
    # the culling kernel against the eager projection: the same Gaussians in the same order,
    # the same pixel ranges, the same covariances and extents (float64)
    from recgs_addon.core.render import rasterizer as rz
    from recgs_addon.core.render.projection import camera_centre, project_gaussians
    cull = {}
    for name, sc in [("random-0", tr.make_scene(0, n=60, deg=3)), ("off-screen", tr._rounded(s))]:
        for aa in (False, True):
            params = tr.torch_params(sc, torch.float32, False)
            vm = torch.tensor(sc["viewmat"], dtype=torch.float64)
            K = torch.tensor(sc["K"], dtype=torch.float64)
            ref = project_gaussians(*params[:4], vm, K, sc["width"], sc["height"], antialiased=aa)
            tk = rz._triton_kernels(params[0].device)
            info = tk.cull(tuple(x.contiguous() for x in params[:4]), tk.view_arrays(vm, K, camera_centre(vm), 0.2),
                           sc["width"], sc["height"], aa)
            ok = info[:, 0] > 0
            same = bool(torch.equal(torch.nonzero(ok).squeeze(1), torch.sort(ref.ids).values))
            got = info[ref.ids] if same else info[:0]
            cull[f"{name}-{int(aa)}"] = {
                "same_ids": same, "visible": int(ok.sum()), "culled": int((~ok).sum()),
                "bbox_equal": same and bool(torch.equal(got[:, 9:13].long(), ref.bbox)),
                "cov2d": float((got[:, 4:8] - ref.cov2d).abs().max() / ref.cov2d.abs().max()) if same else 1.0,
                "extent": float((got[:, 8] - ref.extent).abs().max()) if same else 1.0}
    res["cull"] = cull
    # the binning kernels against the eager binning: the same intersections in the same order
    from recgs_addon.core.render.tiles import _sort_by_tile, _tile_intersections
    binning = {}
    scenes = [("random-0", tr.make_scene(0, n=60, deg=3)), ("off-screen", tr._rounded(s)),
              ("dense", tr.make_scene(8, n=150, width=36, height=20, logit=(3.0, 2.0))),
              ("big", dict(tr.make_scene(5, n=400, width=70, height=53), width=70, height=53))]
    for name, sc in scenes:
        params = tr.torch_params(sc, torch.float32, False)
        vm = torch.tensor(sc["viewmat"], dtype=torch.float64)
        K = torch.tensor(sc["K"], dtype=torch.float64)
        w, h = sc["width"], sc["height"]
        ref = project_gaussians(*params[:4], vm, K, w, h)
        tiles_x, tiles_y = -(-w // 16), -(-h // 16)
        rows, count = _sort_by_tile(*_tile_intersections(ref, w, h, 16, False), tiles_x * tiles_y)
        tk = rz._triton_kernels(params[0].device)
        info = tk.cull(tuple(x.contiguous() for x in params[:4]), tk.view_arrays(vm, K, camera_centre(vm), 0.2), w, h,
                       False)
        start, got = tk.bin(info[ref.ids].contiguous(), 16, tiles_x, tiles_x * tiles_y)
        binning[name] = {"intersections": int(rows.shape[0]), "rows_equal": bool(torch.equal(got.long(), rows)),
                         "starts_equal": bool(torch.equal(start[1:] - start[:-1], count))}
    res["binning"] = binning
    res["training"] = _training()
    # blending weights: against the eager path's, and their sum is the image's alpha
    scene = tr.make_scene(8, n=150, width=36, height=20, logit=(3.0, 2.0))
    a, _, wa = tr._weights_of(scene, torch.float32, compiled=False)
    b, _, wb = tr._weights_of(scene, torch.float32, compiled="triton")
    alpha = float(b.alpha.detach().sum())
    res["weights"] = {"err": float((wa - wb).abs().max() / wa.abs().max()),
                      "sum_err": abs(float(wb.sum()) - alpha) / alpha, "path": b.stats["path"]}
    return res


def _training():
    """The same training on the eager path and on Triton's kernels (the trainer's render, row
    gathers, densification from the screen-space gradients and the blending weights, Adam):
    held-out PSNR and Gaussians after 24 steps from one seed (small: the interpreter takes
    about a second a step)."""
    import tempfile
    from pathlib import Path

    from conftest import write_rendered_scene
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer
    root = Path(tempfile.mkdtemp()) / "scene"
    write_rendered_scene(root, n_views=6, width=32, height=24, n_gauss=60)
    from recgs_addon.core.render import triton_kernels
    calls = [0]
    composite = triton_kernels.TritonKernels.forward

    def counted(self, *a, **k):
        calls[0] += 1
        return composite(self, *a, **k)
    triton_kernels.TritonKernels.forward = counted
    out = {}
    for path in (False, "triton"):
        cfg = preset("default", iterations=24, eval_every=1000, log_every=1000, holdout_every=3, compiled=False,
                     densify_from=8, densify_every=8, densify_until=20, pyramid=((8, 2),))
        t = make_trainer(root, cfg)
        t.compiler.compiled = lambda path=path: path
        t.train_until()
        ev = t.evaluate()
        out[str(path)] = {"psnr": ev["psnr"], "gaussians": int(t.params["means"].shape[0]),
                          "iterations": int(t.step), "triton_renders": calls[0]}
    triton_kernels.TritonKernels.forward = composite
    return out


# ------------------------------------------------------------------------------ the tests

@pytest.fixture(scope="module")
def results():
    env = dict(os.environ, TRITON_INTERPRET="1")
    res = subprocess.run([sys.executable, os.path.abspath(__file__)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


FIELDS = ("rgb", "alpha", "depth")
GRADS = ("d_means2d", "d_means", "d_log_scales", "d_quats", "d_logit_opacities", "d_sh")


def _assert_matches(r):
    """As numba's path against the eager one: images to 1e-6, gradients to 1e-5 (float32
    summation order and exp), radii exactly (the same projection), nothing non-finite."""
    assert r["path"] == "triton"
    assert r["finite"] and r["radii_equal"]
    for k in FIELDS:
        assert r[k] <= 1e-6, (k, r[k])
    for k in GRADS:
        assert r[k] <= 1e-5, (k, r[k])


@needs_triton
@pytest.mark.parametrize("case", ["random-0", "random-1", "random-2", "random-4", "odd-frame"])
def test_triton_matches_eager(results, case):
    """Random scenes (SH 0-3, antialiased or not), a frame not a multiple of the 16-px tile."""
    _assert_matches(results[case])


@needs_triton
def test_triton_matches_eager_where_the_clamp_and_the_stop_fire(results):
    _assert_matches(results["dense"])
    assert results["dense"]["alpha_max"] > 0.9999 - 1e-6


@needs_triton
def test_triton_matches_eager_on_one_pixel_under_2000_gaussians(results):
    """The list goes on long after every pixel stopped: the loops end at the stop."""
    _assert_matches(results["one-pixel"])
    assert results["one-pixel"]["alpha_max"] > 0.999


@needs_triton
def test_triton_matches_eager_with_off_screen_and_empty_tiles(results):
    _assert_matches(results["off-screen"])
    _assert_matches(results["empty-tiles"])
    assert results["empty-tiles"]["corner_alpha"] == 0.0


@needs_triton
def test_the_culling_kernel_keeps_what_the_eager_projection_keeps(results):
    """The same Gaussians drawn (behind the camera, far off-screen and covering the image
    among them), the same pixel ranges, the covariances and extents to float64 rounding."""
    for case, r in results["cull"].items():
        assert r["same_ids"] and r["bbox_equal"], (case, r)
        assert r["visible"] > 0 and r["cov2d"] <= 1e-12 and r["extent"] <= 1e-12, (case, r)
    assert results["cull"]["off-screen-0"]["culled"] >= 2


@needs_triton
def test_the_binning_kernels_give_the_eager_intersections_in_its_order(results):
    """Every (tile, Gaussian) intersection the eager ellipse cut gives, in (tile, depth) order."""
    for case, r in results["binning"].items():
        assert r["rows_equal"] and r["starts_equal"], (case, r)
        assert r["intersections"] > 0, case
    assert results["binning"]["big"]["intersections"] > 1000


@needs_triton
def test_training_on_the_triton_kernels_is_training_on_the_eager_path(results):
    """Equal steps give the same model: held-out PSNR within 0.05 dB, the same Gaussians."""
    r = results["training"]
    eager, gpu = r["False"], r["triton"]
    assert eager["iterations"] == gpu["iterations"] == 24
    assert eager["triton_renders"] == 0 and gpu["triton_renders"] >= 24
    assert eager["psnr"] > 12 and abs(eager["psnr"] - gpu["psnr"]) < 0.05, r
    assert abs(eager["gaussians"] - gpu["gaussians"]) <= 0.02 * eager["gaussians"], r


@needs_triton
def test_triton_blending_weights_match_eager(results):
    r = results["weights"]
    assert r["path"] == "triton"
    assert r["err"] <= 1e-5 and r["sum_err"] <= 1e-4


@needs_triton
def test_float64_renders_stay_on_the_eager_path(results):
    """The kernels composite in float32; a float64 render (the checks' precision) is eager."""
    assert results["float64"]["path"] == "eager"


def test_cpu_tensors_outside_the_interpreter_fall_back_to_eager():
    """In a process that compiles Triton's kernels (or has no Triton), CPU tensors asked for
    the Triton path render eagerly, with one warning that says why."""
    import torch

    sys.path[:0] = [HERE, ROOT]
    import test_rasterizer as tr
    from recgs_addon.core.render import kernels, triton_kernels

    if triton_kernels.interpreting():
        pytest.skip("this process runs Triton's interpreter")
    kernels._KERNEL_CACHE.pop("warned_triton", None)
    scene = tr.make_scene(0, n=20)
    with pytest.warns(UserWarning, match="Triton kernels unavailable"):
        out, _ = tr.run(scene, torch.float32, compiled="triton")
    ref, _ = tr.run(scene, torch.float32, compiled=False)
    assert out.stats["path"] == "eager" and torch.equal(out.rgb, ref.rgb)


def test_a_cuda_device_trains_on_the_triton_path_where_it_loads(monkeypatch):
    """The compile switch's choice on a GPU: Triton's kernels where they load, the eager path
    where they do not, and the eager path whenever it is asked for (the oracle)."""
    sys.path[:0] = [ROOT]
    from recgs_addon.core.train import compiling

    monkeypatch.setattr(compiling, "_triton_ready", lambda: True)
    sw = compiling.CompileSwitch(None, device="cuda")
    assert sw.state == "triton" and sw.compiled() == "triton"
    assert compiling.CompileSwitch(False, device="cuda").compiled() is False
    monkeypatch.setattr(compiling, "_triton_ready", lambda: False)
    sw = compiling.CompileSwitch(None, device="cuda")
    assert sw.compiled() is False and "Triton" in " ".join(sw.messages)


# ------------------------------------------------------------------------------ the compiler

_P = "*fp32"
_PROJECT_SIG = dict(means=_P, log_scales=_P, quats=_P, logits=_P, sh=_P, vm="*fp64", kk="*fp64",
                    campos="*fp64", shc="*fp64", cst="*fp64")
_COMPOSITE_SIG = dict(tile_start="*i64", rows="*i32", pos="*fp64", geo=_P, vals=_P, out=_P, last="*i32")
_SCALARS = dict(tiles_x="i32", hp="i32", wp="i32", amin="fp32", amax="fp32", tmin="fp32")


def _compile_cases():
    from recgs_addon.core.render import _triton_project as tp
    from recgs_addon.core.render import triton_kernels as tk
    proj_out = dict(pos="*fp64", geo=_P, depth=_P, colour=_P)
    proj_grads = dict(g_pos=_P, g_geo=_P, g_depth=_P, g_colour=_P, d_means=_P, d_log_scales=_P, d_quats=_P,
                      d_logits=_P, d_sh=_P)
    sizes = dict(V="i32", width="i32", height="i32")
    for deg, aa in [(0, True), (3, False)]:
        ce = dict(KS=16, DEG=deg, AA=aa, BLOCK=tk._PROJECT_BLOCK)
        yield f"project-forward-{deg}", tp._forward_kernel, {**_PROJECT_SIG, **proj_out, **sizes}, ce
        yield f"project-backward-{deg}", tp._backward_kernel, {**_PROJECT_SIG, **proj_grads, **sizes}, ce
    yield "cull", tp._cull_kernel, dict(means=_P, log_scales=_P, quats=_P, logits=_P, vm="*fp64", kk="*fp64",
                                         cst="*fp64", info="*fp64", N="i32", width="i32", height="i32"), \
        dict(AA=True, BLOCK=tk._PROJECT_BLOCK)
    for count in (True, False):
        yield f"bin-{count}", tp._bin_kernel, dict(info="*fp64", offsets="*i64", tile_of="*i32", row_of="*i32",
                                                    V="i32", tiles_x="i32"), \
            dict(COUNT=count, TS=16, BLOCK=tk._PROJECT_BLOCK)
    yield "composite-forward", tk.triton.jit(tk._forward_kernel), {**_COMPOSITE_SIG, **_SCALARS}, \
        dict(TS=16, C=5, CB=8)
    yield "composite-backward", tk.triton.jit(tk._backward_kernel), \
        {**_COMPOSITE_SIG, "g_out": _P, "d_isect": _P, "n_isect": "i32", **_SCALARS}, \
        dict(TS=16, C=5, CB=8, WEIGHTS=True)


@needs_triton
def test_the_kernels_compile_for_nvidia_gpus():
    """Every kernel compiles to machine code for a Turing (GeForce RTX 20, the oldest with
    Triton's support) and a Hopper GPU, with Triton's own ptxas, on a machine without one: what
    the interpreter cannot check (typing, the compiler's limits) is checked here."""
    from recgs_addon.core.render import triton_kernels as tk
    if tk.interpreting():
        pytest.skip("this process runs Triton's interpreter")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource
    done = []
    for arch in (75, 90):
        for name, fn, sig, ce in _compile_cases():
            for k in ce:
                sig[k] = "constexpr"
            kernel = tk.triton.compile(ASTSource(fn=fn, signature=sig, constexprs=ce),
                                       target=GPUTarget("cuda", arch, 32))
            assert kernel.asm["cubin"], (name, arch)
            done.append((name, arch))
    assert len(done) == 18


if __name__ == "__main__":
    print(json.dumps(_cases()))
