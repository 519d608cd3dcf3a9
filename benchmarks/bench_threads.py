"""How a training step scales with cores, part by part.

    .venv/bin/python benchmarks/bench_threads.py SCENE_DIR [--gaussians 50000,500000]
        [--threads 1,2,4,8,16] [--steps 6] [--max-side 1280] [--densifying [--prune-weight 0]]
        [--device cuda]

Builds models of each size from the survey's sparse points (jittered copies, SH degree 3), and
times full training steps on numba's path (the default on the CPU), with the allocator set as
the train job sets it (``--system-malloc``: glibc's defaults), at each thread count
(counts above the machine's cores are skipped), at the survey's training size (its photos
capped at ``--max-side``; 1280x960 for a 4:3 survey scaled with benchmarks/scale_survey.py).
Each part of the step is timed on its own: numba's cull, tile binning, projection forward and
backward, compositing forward and backward, the loss's SSIM term, Adam, and the rest (torch's
glue: gathers, the loss, gradient writes). It prints seconds per step and per part, the speed-
up over one thread, and the part whose share grows most with threads: what stops scaling.
``--densifying`` times the steps of a model that is still growing: each also gathers what density
control reads (screen gradients, and the blending weights unless ``--prune-weight 0``).
``--device cuda`` (or mps) times the same steps on a GPU instead, on the plain-PyTorch path the
trainer takes there (whole steps, each ended by a device synchronisation; Adam apart).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recgs_addon.commands.train import tune_allocator  # noqa: E402
from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.model.gaussians import init_from_points  # noqa: E402
from recgs_addon.core.render import numba_kernels  # noqa: E402
from recgs_addon.core.render.rasterizer import ALPHA_MAX, ALPHA_MIN, T_MIN  # noqa: E402
from recgs_addon.core.train import numba_ssim  # noqa: E402
from recgs_addon.core.train.config import preset  # noqa: E402
from recgs_addon.core.train.trainer import make_trainer  # noqa: E402

PARTS = ("cull", "bin", "project_forward", "project_backward", "forward", "backward")


def model(scene_dir: Path, n: int, seed: int = 0):
    sc = load_scene(scene_dir)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(sc.points), n)
    pts = sc.points[idx] + rng.normal(0, 0.01 * sc.extent(), (n, 3)).astype(np.float32)
    g = init_from_points(pts, sc.colors[idx], sh_degree=3)
    g.sh[:, 1:] = rng.normal(0, 0.05, g.sh[:, 1:].shape).astype(np.float32)
    return g


def timed_steps(tr, steps: int) -> tuple[float, dict]:
    """Median seconds per step and median seconds per part over ``steps`` steps (after one)."""
    nk = numba_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN)
    spent: dict = defaultdict(float)
    originals = {}
    for name in PARTS:
        fn = getattr(nk, name)
        originals[name] = fn

        def wrap(*a, _fn=fn, _name=name, **k):
            t = time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                spent[_name] += time.perf_counter() - t
        setattr(nk, name, wrap)
    real_ssim = numba_ssim.ssim_term

    def ssim_wrap(*a, **k):
        t = time.perf_counter()
        out = real_ssim(*a, **k)
        spent["ssim forward"] += time.perf_counter() - t
        return out
    numba_ssim.ssim_term = ssim_wrap
    real_step = tr.optimizer.step

    def adam(*a, **k):
        t = time.perf_counter()
        try:
            return real_step(*a, **k)
        finally:
            spent["adam"] += time.perf_counter() - t
    tr.optimizer.step = adam
    totals, parts = [], defaultdict(list)
    try:
        for k in range(steps + 1):
            spent.clear()
            t0 = time.perf_counter()
            tr.train_step()
            total = time.perf_counter() - t0
            if k:
                totals.append(total)
                for name, v in spent.items():
                    parts[name].append(v)
                parts["rest"].append(total - sum(spent.values()))
    finally:
        for name, fn in originals.items():
            setattr(nk, name, fn)
        numba_ssim.ssim_term = real_ssim
    return statistics.median(totals), {k: statistics.median(v) for k, v in parts.items()}


def timed_device_steps(tr, steps: int) -> tuple[float, dict]:
    """Median seconds per step and for Adam over ``steps`` steps (after two) on a GPU: each step
    ends with the device's synchronisation, so the time is the kernels', not their launch."""
    dev = tr.device.type
    sync = {"cuda": lambda: torch.cuda.synchronize(tr.device),
            "mps": lambda: torch.mps.synchronize()}.get(dev, lambda: None)
    real_step = tr.optimizer.step
    spent: dict = defaultdict(float)

    def adam(*a, **k):
        sync()
        t = time.perf_counter()
        try:
            return real_step(*a, **k)
        finally:
            sync()
            spent["adam"] += time.perf_counter() - t
    tr.optimizer.step = adam
    totals, parts = [], defaultdict(list)
    try:
        for k in range(steps + 2):
            spent.clear()
            sync()
            t0 = time.perf_counter()
            tr.train_step()
            sync()
            total = time.perf_counter() - t0
            if k >= 2:
                totals.append(total)
                parts["adam"].append(spent["adam"])
                parts["rest"].append(total - spent["adam"])
    finally:
        tr.optimizer.step = real_step
    return statistics.median(totals), {k: statistics.median(v) for k, v in parts.items()}


def device_row(args, n: int) -> None:
    """One model size on ``args.device``: seconds per step on the plain-PyTorch path, or with
    the compositing in Triton's kernels (``--gpu-path triton``)."""
    g = model(args.scene, n)
    growing = dict(densify_from=10**9, densify_until=10**9 + 1) if args.densifying else dict(densify_until=0)
    if args.prune_weight is not None:
        growing["prune_weight"] = args.prune_weight
    cfg = preset("default", sh_degree=3, max_side=args.max_side, pyramid=(), budget=n, device=args.device,
                 compiled=None if args.gpu_path == "triton" else False, **growing)
    tr = make_trainer(args.scene, cfg, gaussians=g)
    tr.sh_degree = 3
    tr.data.load_all()
    total, parts = timed_device_steps(tr, args.steps)
    w, h = tr.data.sizes[tr.data.train_ids[0]]
    peak = ""
    if tr.device.type == "cuda":
        peak = f", peak GPU memory {torch.cuda.max_memory_allocated(tr.device) / 2**30:.2f} GiB"
    path = {"triton": "Triton's kernels"}.get(str(tr.compiler.compiled()), "plain PyTorch")
    print(f"\n{n:,} Gaussians at {w}x{h} on {args.device} ({path}): {total:.4f} s a step "
          f"({1 / total:.1f} steps/s), Adam {parts['adam']:.4f} s, the rest {parts['rest']:.4f} s{peak}",
          flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--gaussians", default="50000,500000")
    ap.add_argument("--threads", default="1,2,4,8,16")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--max-side", type=int, default=1280)
    ap.add_argument("--system-malloc", action="store_true",
                    help="keep glibc's allocator defaults instead of the train job's (commands/train.tune_allocator)")
    ap.add_argument("--densifying", action="store_true",
                    help="steps of a growing model: they gather density control's statistics (no densification runs)")
    ap.add_argument("--prune-weight", type=float, default=None,
                    help="the strategy's prune_weight (0: no blending weights gathered)")
    ap.add_argument("--device", default="cpu",
                    help="cuda or mps: time the steps on that GPU (plain PyTorch) instead of numba's threads")
    ap.add_argument("--gpu-path", choices=("eager", "triton"), default="eager",
                    help="on a GPU: the plain-PyTorch path, or the compositing in Triton's kernels")
    args = ap.parse_args(argv)
    if args.device != "cpu":
        print(f"torch {torch.__version__}, device {args.device}"
              + (f" ({torch.cuda.get_device_name(args.device)})" if args.device.startswith("cuda") else ""))
        for n in (int(x) for x in args.gaussians.split(",")):
            device_row(args, n)
        return 0
    cores = os.cpu_count() or 1
    counts = [t for t in (int(x) for x in args.threads.split(",")) if t <= cores]
    # the allocator as the train job sets it: with glibc's defaults each step's large buffers are
    # fresh mappings, and faulting their pages in runs on one thread at a time
    allocator = "system" if args.system_malloc else tune_allocator()
    print(f"torch {torch.__version__}, {cores} cores; thread counts {counts}; numba path; allocator {allocator}")
    from recgs_addon.core.train import compiling
    if not compiling.numba_is_warm():
        print("warming numba's cache (once)", flush=True)
        compiling.warm_up_numba()
    for n in (int(x) for x in args.gaussians.split(",")):
        g = model(args.scene, n)
        base = None
        rows = []
        for threads in counts:
            torch.set_num_threads(threads)
            growing = dict(densify_from=10**9, densify_until=10**9 + 1) if args.densifying else dict(densify_until=0)
            if args.prune_weight is not None:
                growing["prune_weight"] = args.prune_weight
            cfg = preset("default", sh_degree=3, max_side=args.max_side, pyramid=(), budget=n, **growing)
            tr = make_trainer(args.scene, cfg, gaussians=g)
            tr.sh_degree = 3
            tr.data.load_all()
            waited = time.perf_counter()
            while tr.compiler.compiled() != "numba" and time.perf_counter() - waited < 120:
                time.sleep(0.5)   # the switch loads the warm kernels in the background
            if tr.compiler.compiled() != "numba":
                raise SystemExit("numba's path is not available here (install numba, warm its cache)")
            total, parts = timed_steps(tr, args.steps)
            tr.compiler.close()
            base = base or (total, parts)
            rows.append((threads, total, parts))
            w, h = tr.data.sizes[tr.data.train_ids[0]]
        print(f"\n{n:,} Gaussians at {w}x{h}: seconds per step (speed-up over {counts[0]} thread)")
        names = [k for k in base[1] if k != "rest"] + ["rest"]
        print(f"{'threads':>8} {'step':>14} " + " ".join(f"{k:>16}" for k in names))
        for threads, total, parts in rows:
            cells = " ".join(f"{parts.get(k, 0):8.3f} ({base[1].get(k, 0) / max(parts.get(k, 1e-9), 1e-9):4.1f}x)"
                             for k in names)
            print(f"{threads:>8} {total:7.3f} ({base[0] / total:4.1f}x) {cells}")
        if len(rows) > 1:
            last = rows[-1]
            grow = max(names, key=lambda k: last[2].get(k, 0) / last[1] - base[1].get(k, 0) / base[0])
            print(f"stops scaling first: {grow} ({100 * base[1].get(grow, 0) / base[0]:.0f} % of the step at "
                  f"{counts[0]} thread, {100 * last[2].get(grow, 0) / last[1]:.0f} % at {last[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
