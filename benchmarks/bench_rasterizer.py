"""Speed, peak memory and error of recgs_addon.core.render.rasterizer.render, per path, on
survey-like scenes.

Usage (from the repository root):
    python benchmarks/bench_rasterizer.py            # every path, 320x240 and 1280x960,
                                                     # 10k/50k/200k/1M Gaussians
    python benchmarks/bench_rasterizer.py --quick    # 320x240 with 50k only
    python benchmarks/bench_rasterizer.py --paths eager,numba --sizes 320x240 --counts 50000
    python benchmarks/bench_rasterizer.py --threads 1 --rounds 2

Paths: ``eager`` (torch, the oracle), ``numba`` (numba's kernels: no C++ compiler needed) and
``compiled`` (torch.compile; skipped where no C++ compiler works). Each (scene, path) runs in
its own subprocess so that its peak memory (VmHWM from /proc/self/status, i.e. peak resident
set size including torch's allocations, reset after the warm-up so compilation is not counted)
is its own; the paths of a scene run one after another, ``--rounds`` times over (interleaved:
on a shared machine compare the paths of one run, not runs). Timings are medians (and minima)
over every round's ``--repeats`` runs after warm-up runs with and without autograd (the warm-up
triggers torch.compile; its time is reported separately as "warmup s"). "pairs" are the
(pixel, Gaussian) pairs evaluated per compositing pass (padding included for eager and
compiled, which composite padded chunks; numba walks each tile's list unpadded).

Error against the eager oracle, same scene and float32 inputs: "img err" is the largest
absolute difference of rgb, alpha and depth/|depth|max; "grad err" the largest over the
parameters and means2d of max |grad - eager grad| / max |eager grad|.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from recgs_addon.core.render.rasterizer import render  # noqa: E402


def survey_scene(n, width, height, seed=0, sh_degree=3):
    """Gaussians on an undulating seafloor seen by a camera ~3 m above it, pitched down 50 deg.

    Means: rays through uniformly drawn pixel positions (over 1.2x the image, so ~30% are
    off-screen) hit the floor, plus a little jitter along the normal. Scales: flattened discs
    whose in-plane standard deviation covers ~1.5 px (log-normal), 0.2x that along the normal.
    Opacities mostly high (logit ~ N(2.5, 1.5)). Returns a dict of float32 torch tensors.
    """
    rng = np.random.default_rng(seed)
    fx = fy = 0.95 * width
    cx, cy = 0.5 * width, 0.5 * height
    pitch = math.radians(50.0)
    # Camera looks along +z_cam; world: z up, floor at z ~ 0, camera at height 3.
    c, s = math.cos(pitch), math.sin(pitch)
    # camera axes in world coords: x right, y down, z forward (pitched down)
    x_ax = np.array([1.0, 0.0, 0.0])
    z_ax = np.array([0.0, c, -s])
    y_ax = np.cross(z_ax, x_ax)
    R_c2w = np.stack([x_ax, y_ax, z_ax], 1)
    centre = np.array([0.0, 0.0, 3.0])
    u = rng.uniform(-0.1 * width, 1.1 * width, n)
    v = rng.uniform(-0.1 * height, 1.1 * height, n)
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(n)], 1)
    d_w = d_cam @ R_c2w.T
    t_hit = (centre[2] - 0.0) / np.maximum(-d_w[:, 2], 0.05)
    p = centre + t_hit[:, None] * d_w
    p[:, 2] += 0.15 * np.sin(1.3 * p[:, 0]) * np.cos(0.9 * p[:, 1]) + rng.normal(0, 0.01, n)
    depth = (p - centre) @ z_ax
    sigma_px = np.exp(rng.normal(math.log(1.5), 0.35, n))
    s_world = sigma_px * depth / fx
    log_scales = np.log(np.stack([s_world, s_world * rng.uniform(0.6, 1.0, n),
                                  0.2 * s_world], 1))
    ang = rng.uniform(0, math.pi, n)            # spin about the (world z) normal
    quats = np.stack([np.cos(ang / 2), np.zeros(n), np.zeros(n), np.sin(ang / 2)], 1)
    quats += rng.normal(0, 0.05, (n, 4))
    logits = rng.normal(2.5, 1.5, n)
    k = (sh_degree + 1) ** 2
    sh = rng.normal(0, 0.05, (n, k, 3))
    sh[:, 0, :] = rng.normal(0, 0.5, (n, 3))
    viewmat = np.eye(4)
    viewmat[:3, :3] = R_c2w.T
    viewmat[:3, 3] = -R_c2w.T @ centre
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    f32 = torch.float32
    return dict(params=[torch.tensor(a, dtype=f32) for a in (p, log_scales, quats, logits, sh)],
                viewmat=torch.tensor(viewmat, dtype=f32), K=torch.tensor(K, dtype=f32),
                width=width, height=height)


def run_once(scene, backward=True, compiled=False, **kw):
    """One render (and backward); returns (seconds, stats)."""
    params = [p.detach().clone().requires_grad_(backward) for p in scene["params"]]
    t0 = time.perf_counter()
    out = render(*params, scene["viewmat"], scene["K"], scene["width"], scene["height"],
                 compiled=compiled, **kw)
    if backward:
        loss = out.rgb.square().mean() + out.alpha.mean() + 0.01 * out.depth.mean()
        loss.backward()
    return time.perf_counter() - t0, out.stats


def _vm_hwm():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM"):
                return int(line.split()[1]) * 1024
    return -1


def _reset_peak():
    """Reset VmHWM (Linux: writing 5 to clear_refs), so compilation is not counted."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _outputs(scene, compiled, **kw):
    """Images and gradients of the benchmark loss (numpy), for the error against eager."""
    params = [p.detach().clone().requires_grad_(True) for p in scene["params"]]
    out = render(*params, scene["viewmat"], scene["K"], scene["width"], scene["height"],
                 compiled=compiled, **kw)
    loss = out.rgb.square().mean() + out.alpha.mean() + 0.01 * out.depth.mean()
    loss.backward()
    res = {k: getattr(out, k).detach().numpy() for k in ("rgb", "alpha", "depth")}
    res["g_means2d"] = out.means2d.grad.numpy()
    for name, p in zip(("means", "log_scales", "quats", "logits", "sh"), params):
        res["g_" + name] = p.grad.numpy()
    return res


def _errors(res, ref):
    depth_scale = max(1.0, float(np.abs(ref["depth"]).max()))
    img = max(float(np.abs(res["rgb"] - ref["rgb"]).max()), float(np.abs(res["alpha"] - ref["alpha"]).max()),
              float(np.abs(res["depth"] - ref["depth"]).max()) / depth_scale)
    grad = max(float(np.abs(res[k] - ref[k]).max() / max(np.abs(ref[k]).max(), 1e-30))
               for k in ref if k.startswith("g_"))
    return img, grad


def measure(n, width, height, path, repeats, threads=2, oracle=None, **kw):
    """Time forward and forward+backward for one scene and path (in this process). With
    ``oracle`` (a .npz path): the eager path writes its outputs there, the others report
    their error against it."""
    torch.set_num_threads(threads)
    scene = survey_scene(n, width, height)
    compiled = {"compiled": True, "eager": False, "numba": "numba"}[path]
    t0 = time.perf_counter()
    run_once(scene, backward=True, compiled=compiled, **kw)    # warm-up (+ compile)
    with torch.no_grad():                                       # (no-grad graphs too)
        run_once(scene, backward=False, compiled=compiled, **kw)
    warm = time.perf_counter() - t0
    errs = (0.0, 0.0)
    if oracle:
        res = _outputs(scene, compiled, **kw)
        if path == "eager":
            np.savez(oracle, **res)
        elif os.path.exists(oracle):
            with np.load(oracle) as ref:
                errs = _errors(res, dict(ref))
        else:
            errs = (float("nan"), float("nan"))
        del res
    _reset_peak()
    fwd = []
    with torch.no_grad():
        for _ in range(repeats):
            t, stats = run_once(scene, backward=False, compiled=compiled, **kw)
            fwd.append(t)
    both = []
    for _ in range(repeats):
        t, stats = run_once(scene, backward=True, compiled=compiled, **kw)
        both.append(t)
    pairs = stats["pairs"]
    return dict(n=n, size=f"{width}x{height}", path=path, forward=fwd, fwd_bwd=both, threads=threads,
                warmup_s=warm, peak_rss_mb=_vm_hwm() / 2 ** 20, visible=stats["visible"],
                intersections=stats["intersections"], pairs=pairs, path_taken=stats.get("path"),
                compiled=stats["compiled"], img_err=errs[0], grad_err=errs[1], **kw)


def accuracy(paths, n=400, width=64, height=48):
    """Error of the float32 render against the float64 references on a small survey scene:
    forward colour against the dense numpy oracle (tests/reference_render.py), and the
    gradients of the benchmark loss against the same rasterizer in float64 (which the test
    suite checks against central differences of the oracle). Returns a dict of figures."""
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from reference_render import reference_render

    scene = survey_scene(n, width, height)
    ref = reference_render(*[p.double().numpy() for p in scene["params"]], scene["viewmat"].double().numpy(),
                           scene["K"].double().numpy(), width, height)

    def run(dtype, compiled):
        params = [p.detach().to(dtype).clone().requires_grad_(True) for p in scene["params"]]
        out = render(*params, scene["viewmat"].to(dtype), scene["K"].to(dtype), width, height, compiled=compiled)
        loss = out.rgb.square().mean() + out.alpha.mean() + 0.01 * out.depth.mean()
        loss.backward()
        return out.rgb.detach().double().numpy(), [p.grad.double() for p in params], out.stats["path"]

    _, g64, _ = run(torch.float64, False)
    figures = dict(n=n, size=f"{width}x{height}")
    for path in paths:
        compiled = {"compiled": True, "eager": False, "numba": "numba"}[path]
        try:
            rgb, g32, taken = run(torch.float32, compiled)
        except RuntimeError:         # torch.compile unavailable
            continue
        if taken != path:
            continue
        figures[f"{path}_forward_max_abs"] = float(np.abs(rgb - ref["rgb"]).max())
        figures[f"{path}_grad_max_rel"] = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
                                              for a, b in zip(g32, g64))
    return figures


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="only 320x240 with 50k Gaussians")
    ap.add_argument("--sizes", default="320x240,1280x960")
    ap.add_argument("--counts", default="10000,50000,200000,1000000")
    ap.add_argument("--paths", default="eager,numba,compiled")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=1, help="times over each scene's paths (interleaved)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tile-size", type=int, default=None)
    ap.add_argument("--chunk-pairs", type=int, default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--oracle", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    kw = {}
    if args.tile_size:
        kw["tile_size"] = args.tile_size
    if args.chunk_pairs:
        kw["chunk_pairs"] = args.chunk_pairs
    if args.child:
        n, w, h, path = args.child.split(":")
        print(json.dumps(measure(int(n), int(w), int(h), path, args.repeats, args.threads,
                                 oracle=args.oracle, **kw)))
        return
    import tempfile

    sizes = ["320x240"] if args.quick else args.sizes.split(",")
    counts = [50000] if args.quick else [int(c) for c in args.counts.split(",")]
    paths = args.paths.split(",")
    if "eager" in paths:                        # the oracle first
        paths = ["eager"] + [p for p in paths if p != "eager"]
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    print(f"torch {torch.__version__}, threads {args.threads}, repeats {args.repeats} x {args.rounds} rounds, "
          f"options {kw}, load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; "
          f"times: median (min) in seconds", flush=True)
    acc = accuracy(paths)
    for path in paths:
        if f"{path}_forward_max_abs" in acc:
            print(f"{path} error at {acc['n']} Gaussians, {acc['size']}: forward max |rgb - float64 oracle| "
                  f"{acc[path + '_forward_max_abs']:.2e}; gradients max |float32 - float64| / max |float64| "
                  f"{acc[path + '_grad_max_rel']:.2e}", flush=True)
    hdr = (f"{'size':>9} {'N':>7} {'path':>8} {'fwd+bwd s':>15} {'fwd s':>15} {'x fastest':>9} "
           f"{'peak MB':>8} {'img err':>8} {'grad err':>8} {'visible':>7} {'isect':>8} {'pairs':>10} "
           f"{'ns/pair':>7} {'warmup s':>8}")
    print(hdr, flush=True)
    table = []
    with tempfile.TemporaryDirectory(prefix="recgs-bench-") as tmp:
        for size in sizes:
            w, h = (int(x) for x in size.split("x"))
            for n in counts:
                oracle = os.path.join(tmp, f"eager-{n}-{w}x{h}.npz")
                runs: dict = {}
                for _ in range(args.rounds):
                    for path in paths:
                        if runs.get(path) == "skip":
                            continue
                        cmd = [sys.executable, os.path.abspath(__file__), "--child", f"{n}:{w}:{h}:{path}",
                               "--repeats", str(args.repeats), "--threads", str(args.threads), "--oracle", oracle]
                        if args.tile_size:
                            cmd += ["--tile-size", str(args.tile_size)]
                        if args.chunk_pairs:
                            cmd += ["--chunk-pairs", str(args.chunk_pairs)]
                        res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
                        if res.returncode != 0:
                            print(f"{size:>9} {n:>7} {path:>8} FAILED: {res.stderr.strip()[-300:]}", flush=True)
                            runs[path] = "skip"
                            continue
                        r = json.loads(res.stdout.strip().splitlines()[-1])
                        if r["path_taken"] != path:
                            print(f"{size:>9} {n:>7} {path:>8} (unavailable here: ran {r['path_taken']}; skipped)",
                                  flush=True)
                            runs[path] = "skip"
                            continue
                        if path in runs:          # pool the rounds
                            for key in ("forward", "fwd_bwd"):
                                runs[path][key] += r[key]
                            runs[path]["peak_rss_mb"] = max(runs[path]["peak_rss_mb"], r["peak_rss_mb"])
                        else:
                            runs[path] = r
                done = {p: r for p, r in runs.items() if r != "skip"}
                if not done:
                    continue
                best = min(float(np.median(r["fwd_bwd"])) for r in done.values())
                for path in paths:
                    if path not in done:
                        continue
                    r = done[path]
                    b, f = float(np.median(r["fwd_bwd"])), float(np.median(r["forward"]))
                    r.update(fwd_bwd_s=b, forward_s=f)
                    table.append(r)
                    print(f"{size:>9} {n:>7} {path:>8} {b:7.3f} ({min(r['fwd_bwd']):5.3f}) "
                          f"{f:7.3f} ({min(r['forward']):5.3f}) {b / best:9.2f} {r['peak_rss_mb']:8.0f} "
                          f"{r['img_err']:8.1e} {r['grad_err']:8.1e} {r['visible']:7d} {r['intersections']:8d} "
                          f"{r['pairs']:10d} {b / (2 * r['pairs']) * 1e9:7.2f} {r['warmup_s']:8.1f}", flush=True)
    print("\nratios of median fwd+bwd times (same scene, same run):")
    for size in sizes:
        for n in counts:
            rows = {r["path"]: r["fwd_bwd_s"] for r in table if r["size"] == size and r["n"] == n}
            pairs = [(a, b) for a, b in (("numba", "compiled"), ("numba", "eager"), ("compiled", "eager"))
                     if a in rows and b in rows]
            if pairs:
                print(f"  {size} {n}: " + ", ".join(f"{a}/{b} {rows[a] / rows[b]:.2f}" for a, b in pairs))
    try:
        load = os.getloadavg()
        print(f"load average at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    except OSError:
        pass


if __name__ == "__main__":
    main()
