"""Rasterizer and full-step speed on Gaussians of a trained survey (not synthetic ones).

    .venv/bin/python benchmarks/bench_trained.py MODEL.ply SCENE_DIR [--count 50000]
        [--size 320x240] [--threads 2] [--repeats 5]

Takes ``--count`` Gaussians of the trained model (a fixed random subset), renders them at
``--size`` from every 4th camera of the survey (intrinsics scaled to that size), and prints,
per path (eager, numba, compiled; ``--paths``): forward, forward+backward, and a full
training step (forward, 0.8 L1 + 0.2 SSIM loss, backward, Adam), median (min) seconds, with
(pixel, Gaussian) pairs and ns per pair. ``--rounds`` repeats the paths interleaved. OpenSplat's CPU trainer takes about 0.12 s per full step at 320x240 / 50k
on this machine (the speed goal's yardstick, 2026-11-21).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.train.losses import training_loss  # noqa: E402
from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.render.rasterizer import get_kernels, render  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("model", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--count", type=int, default=50_000)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--paths", default="eager,numba,compiled")
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    W, H = (int(v) for v in args.size.split("x"))
    g = read_gaussian_ply(args.model)
    if len(g) > args.count:
        g = g.subset(np.sort(np.random.default_rng(0).choice(len(g), args.count, replace=False)))
    scene = load_scene(args.scene, check_images=False)
    cams = scene.cameras[::4]
    print(f"torch {torch.__version__}, {args.threads} threads; {len(g)} trained Gaussians (SH degree "
          f"{g.sh_degree}) at {W}x{H}, {len(cams)} views; median (min) s")
    print(f"{'path':>9} {'fwd':>15} {'fwd+bwd':>15} {'full step':>15} {'pairs':>9} {'ns/pair':>8}")
    acc: dict = {}
    for path in [p for _ in range(args.rounds) for p in args.paths.split(",")]:
        compiled = {"eager": False, "numba": "numba", "compiled": True}[path]
        times = acc.setdefault(path, {"fwd": [], "fb": [], "step": [], "pairs": []})
        if path == "compiled":
            try:
                get_kernels(True)
            except RuntimeError:      # no C++ compiler here
                continue
        pairs = times["pairs"]
        params = [torch.nn.Parameter(torch.tensor(a)) for a in (g.means, g.log_scales, g.quats, g.logit_opacities, g.sh)]
        opt = torch.optim.Adam(params, lr=1e-4, eps=1e-15)
        views = []
        for cam in cams:
            c = cam.resized(W, H)
            views.append((torch.tensor(cam.viewmat, dtype=torch.float32),
                          torch.tensor(c.K, dtype=torch.float32), torch.rand(H, W, 3)))
        for rep in range(args.repeats + 1):  # the first round warms up (and compiles)
            for viewmat, K, target in views:
                t0 = time.perf_counter()
                with torch.no_grad():
                    render(*params, viewmat, K, W, H, compiled=compiled)
                t1 = time.perf_counter()
                out = render(*params, viewmat, K, W, H, compiled=compiled)
                out.rgb.sum().backward()
                t2 = time.perf_counter()
                opt.zero_grad(set_to_none=True)
                t3 = time.perf_counter()
                out = render(*params, viewmat, K, W, H, compiled=compiled)
                training_loss(out.rgb, target).backward()
                opt.step()
                opt.zero_grad(set_to_none=True)
                t4 = time.perf_counter()
                if out.stats["path"] != path:
                    break
                if rep:
                    times["fwd"].append(t1 - t0)
                    times["fb"].append(t2 - t1)
                    times["step"].append(t4 - t3)
                    pairs.append(out.stats["pairs"])
    fmt = lambda v: f"{statistics.median(v):.3f} ({min(v):.3f})"  # noqa: E731
    for path, times in acc.items():
        if not times["step"]:
            print(f"{path:>9} (unavailable here)")
            continue
        ns = statistics.median(times["fb"]) / (2 * statistics.median(times["pairs"])) * 1e9
        print(f"{path:>9} {fmt(times['fwd']):>15} {fmt(times['fb']):>15} "
              f"{fmt(times['step']):>15} {int(statistics.median(times['pairs'])):>9} {ns:>8.1f}")
    steps = {p: statistics.median(t["step"]) for p, t in acc.items() if t["step"]}
    if steps:
        best = min(steps.values())
        print("full step / fastest: " + ", ".join(f"{p} {v / best:.2f}" for p, v in steps.items()))


if __name__ == "__main__":
    main()
