"""Speed and memory of recgs_addon.core.render.rasterizer.render on survey-like scenes.

Usage (from the repository root):
    python benchmarks/bench_rasterizer.py            # 320x240 and 640x480, 10k/50k/200k
    python benchmarks/bench_rasterizer.py --quick    # 320x240 with 50k only
    python benchmarks/bench_rasterizer.py --paths eager --sizes 320x240 --counts 50000
    python benchmarks/bench_rasterizer.py --paths eager,numba,compiled --sizes 320x240,1280x960 \
        --counts 10000,50000,200000,1000000

Each (scene, path) runs in its own subprocess so that its peak memory (VmHWM from
/proc/self/status, i.e. peak resident set size including torch's allocations, reset after
the warm-up so compilation is not counted) is its own. Timings are medians (and minima)
over --repeats runs after warm-up runs with and without autograd (the warm-up triggers
torch.compile; its time is reported separately as "warmup s"). "pairs" are the (pixel, Gaussian)
pairs evaluated per compositing pass, padding included; ns/pair = forward+backward time /
pairs (the backward replays the forward, so every pair is evaluated twice).
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


def measure(n, width, height, path, repeats, threads=2, **kw):
    """Time forward and forward+backward for one scene and path (in this process)."""
    torch.set_num_threads(threads)
    scene = survey_scene(n, width, height)
    compiled = {"compiled": True, "eager": False, "numba": "numba"}[path]
    t0 = time.perf_counter()
    run_once(scene, backward=True, compiled=compiled, **kw)    # warm-up (+ compile)
    with torch.no_grad():                                       # (no-grad graphs too)
        run_once(scene, backward=False, compiled=compiled, **kw)
    warm = time.perf_counter() - t0
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
    f, b = float(np.median(fwd)), float(np.median(both))
    pairs = stats["pairs"]
    return dict(n=n, size=f"{width}x{height}", path=path, forward_s=f, fwd_bwd_s=b,
                forward_min_s=min(fwd), fwd_bwd_min_s=min(both), threads=threads,
                warmup_s=warm, peak_rss_mb=_vm_hwm() / 2 ** 20, visible=stats["visible"],
                intersections=stats["intersections"], pairs=pairs,
                pairs_per_s_fwd=pairs / f, ns_per_pair_fwd_bwd=b / (2 * pairs) * 1e9,
                compiled=stats["compiled"], **kw)


def accuracy(n=400, width=64, height=48):
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
        return out.rgb.detach().double().numpy(), [p.grad.double() for p in params]

    _, g64 = run(torch.float64, False)
    figures = dict(n=n, size=f"{width}x{height}")
    for path, compiled in (("eager", False), ("numba", "numba")):
        rgb, g32 = run(torch.float32, compiled)
        figures[f"{path}_forward_max_abs"] = float(np.abs(rgb - ref["rgb"]).max())
        figures[f"{path}_grad_max_rel"] = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
                                              for a, b in zip(g32, g64))
    return figures


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="only 320x240 with 50k Gaussians")
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--counts", default="10000,50000,200000")
    ap.add_argument("--paths", default="eager,compiled")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tile-size", type=int, default=None)
    ap.add_argument("--chunk-pairs", type=int, default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    kw = {}
    if args.tile_size:
        kw["tile_size"] = args.tile_size
    if args.chunk_pairs:
        kw["chunk_pairs"] = args.chunk_pairs
    if args.child:
        n, w, h, path = args.child.split(":")
        print(json.dumps(measure(int(n), int(w), int(h), path, args.repeats, args.threads,
                                 **kw)))
        return
    sizes = ["320x240"] if args.quick else args.sizes.split(",")
    counts = [50000] if args.quick else [int(c) for c in args.counts.split(",")]
    print(f"torch {torch.__version__}, threads {args.threads}, repeats {args.repeats}, "
          f"options {kw}; times: median (min) in seconds")
    acc = accuracy()
    for path in ("eager", "numba"):
        print(f"{path} error at {acc['n']} Gaussians, {acc['size']}: forward max |rgb - float64 oracle| "
              f"{acc[path + '_forward_max_abs']:.2e}; gradients max |float32 - float64| / max |float64| "
              f"{acc[path + '_grad_max_rel']:.2e}")
    hdr = (f"{'size':>8} {'N':>7} {'path':>8} {'fwd s':>15} {'fwd+bwd s':>15} {'peak MB':>8} "
           f"{'visible':>7} {'isect':>8} {'pairs':>10} {'Mpairs/s':>8} {'ns/pair':>7} "
           f"{'warmup s':>8}")
    print(hdr)
    for size in sizes:
        w, h = (int(x) for x in size.split("x"))
        for n in counts:
            for path in args.paths.split(","):
                cmd = [sys.executable, os.path.abspath(__file__), "--child", f"{n}:{w}:{h}:{path}",
                       "--repeats", str(args.repeats), "--threads", str(args.threads)]
                if args.tile_size:
                    cmd += ["--tile-size", str(args.tile_size)]
                if args.chunk_pairs:
                    cmd += ["--chunk-pairs", str(args.chunk_pairs)]
                res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
                if res.returncode != 0:
                    print(f"{size:>8} {n:>7} {path:>8} FAILED: {res.stderr.strip()[-300:]}")
                    continue
                r = json.loads(res.stdout.strip().splitlines()[-1])
                if path == "compiled" and not r["compiled"]:
                    print(f"{size:>8} {n:>7} {path:>8} (torch.compile unavailable, skipped)")
                    continue
                print(f"{size:>8} {n:>7} {path:>8} "
                      f"{r['forward_s']:7.3f} ({r['forward_min_s']:5.3f}) "
                      f"{r['fwd_bwd_s']:7.3f} ({r['fwd_bwd_min_s']:5.3f}) "
                      f"{r['peak_rss_mb']:8.0f} {r['visible']:7d} {r['intersections']:8d} "
                      f"{r['pairs']:10d} {r['pairs_per_s_fwd'] / 1e6:8.1f} "
                      f"{r['ns_per_pair_fwd_bwd']:7.2f} {r['warmup_s']:8.1f}", flush=True)


if __name__ == "__main__":
    main()
