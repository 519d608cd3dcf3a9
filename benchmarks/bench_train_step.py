"""The trainer's step on a large model: what each speed-up buys, and what it changes.

    .venv/bin/python benchmarks/bench_train_step.py MODEL.ply SCENE_DIR [--images clean]
        [--steps 8] [--rounds 2] [--threads 2] [--count 0] [--preset vanilla|default]

Loads a trained model (e.g. a vanilla run's ``point_cloud.ply``, a million Gaussians or more)
into a ``vanilla`` (or ``--preset default``) trainer on the survey and runs ``--steps`` full training steps (render,
loss, backward, gradient statistics, Adam) from the same state with each speed-up turned off
in turn, then with all of them off (the trainer as it was before them):

* ``fused Adam``: one fused kernel per parameter group, against torch's foreach Adam;
* ``row grads``: gradients only at the rows in view, written into persistent buffers
  (:mod:`recgs_addon.core.render.rowgrads`), against autograd's full-size index_select backward;
* ``SH blocks``: DC and higher SH coefficients joined only for the Gaussians in view, against
  joining them for every Gaussian before the render (timed with autograd's gradients, as it
  was; with row grads the join is of the rows only anyway);
* ``pre-cull``: a conservative candidate test before the exact cull pass, against the exact
  pass over every Gaussian;
* ``numba SSIM``: on numba's path, the loss's SSIM term through numba's kernels
  (:mod:`recgs_addon.core.train.numba_ssim`), against the eager term;
* ``own threads``: on numba's path, the step with the kernels on torch's threads and torch on
  one (:func:`recgs_addon.core.render.numba_kernels.own_threads`), against both sharing
  torch's count (torch's OpenMP threads spinning on the cores the kernels need).

Prints seconds per step (median over the steps after a warm-up step, best of ``--rounds``
interleaved rounds) and, for every path, the
largest parameter difference from the fast path after the steps and the PSNR between the two
paths' renders of the first held-out view: the error each speed-up costs. A warm-up path
runs first (torch.compile).
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recgs_addon.core.render import numba_kernels, projection  # noqa: E402
from recgs_addon.core.train.losses import psnr  # noqa: E402
from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.render.rowgrads import RowGrads  # noqa: E402
from recgs_addon.core.train import numba_ssim  # noqa: E402
from recgs_addon.core.train.config import preset  # noqa: E402
from recgs_addon.core.train.trainer import Trainer, make_trainer  # noqa: E402


def _all_candidates(means, *args):
    return torch.ones(means.shape[0], dtype=torch.bool)


class _JoinedSH(RowGrads):
    """Autograd gradients, and every Gaussian's SH coefficients joined before the render."""

    def __init__(self):
        super().__init__(sparse=False)

    def track(self, name, param, cols=None):
        if name == "sh_dc":
            self._dc = param
            return param[:, :0]          # an empty block: render skips it
        if name == "sh_rest":
            return torch.cat([self._dc, param[:, :cols]], 1)
        return super().track(name, param, cols)


def run_path(tr: Trainer, state: dict, steps: int, fused: bool, grads: str, precull: bool, fast_ssim: bool = True,
             own: bool = True):
    """(seconds per step, trainer after the steps): ``tr`` from ``state`` on the given path;
    grads: "rows" (RowGrads), "dense" (autograd) or "joined" (autograd, SH joined);
    fast_ssim False: the eager SSIM term on numba's path; own False: numba's kernels and torch
    share torch's thread count."""
    tr.load_state_dict(copy.deepcopy(state))
    tr.row_grads = {"rows": RowGrads, "dense": lambda: RowGrads(sparse=False), "joined": _JoinedSH}[grads]()
    for g in tr.optimizer.param_groups:
        g["fused"], g["foreach"] = (True, None) if fused else (None, True)
    real = projection._candidates
    projection._candidates = real if precull else _all_candidates
    real_load = numba_ssim.load
    numba_ssim.load = real_load if fast_ssim else (lambda: None)
    real_own = numba_kernels.own_threads
    numba_kernels.own_threads = real_own if own else contextlib.nullcontext
    try:
        times = []
        for _ in range(steps + 1):
            t0 = time.perf_counter()
            tr.train_step()
            times.append(time.perf_counter() - t0)
    finally:
        projection._candidates = real
        numba_ssim.load = real_load
        numba_kernels.own_threads = real_own
    return statistics.median(times[1:]), tr


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("model", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--images", default=None, help="image folder (e.g. clean)")
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--count", type=int, default=0, help="use this many of the model's Gaussians (0 = all)")
    ap.add_argument("--preset", default="vanilla", help="trainer preset whose step is timed (vanilla or default)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    g = read_gaussian_ply(args.model)
    if args.count and len(g) > args.count:
        g = g.subset(np.sort(np.random.default_rng(0).choice(len(g), args.count, replace=False)))
    cfg = preset(args.preset, sh_degree=g.sh_degree)
    base = make_trainer(args.scene, cfg, images=args.images, gaussians=g)
    base.sh_degree = g.sh_degree
    base.step = 5000                      # mid-densification: statistics are accumulated
    state = copy.deepcopy(base.state_dict())
    print(f"torch {torch.__version__}, {args.threads} threads; {len(g):,} Gaussians (SH {g.sh_degree}); "
          f"{args.steps} steps per path, best of {args.rounds} rounds; {args.preset} preset, rasterizer path "
          f"{base.compiler.compiled()!r}")
    paths = [("all speed-ups", True, "rows", True, True, True), ("foreach Adam", False, "rows", True, True, True),
             ("autograd grads", True, "dense", True, True, True), ("+ joined SH", True, "joined", True, True, True),
             ("no pre-cull", True, "rows", False, True, True), ("eager SSIM", True, "rows", True, False, True),
             ("shared threads", True, "rows", True, True, False),
             ("none (before)", False, "joined", False, False, False)]
    results, times = {}, {name: [] for name, *_ in paths}
    run_path(make_trainer(args.scene, cfg, images=args.images, gaussians=g), state, 2, True, "rows", True)  # warm-up
    for r in range(args.rounds):   # interleaved rounds, best round per path: a shared machine is noisy
        for name, fused, grads, precull, fast_ssim, own in (paths if r % 2 == 0 else paths[::-1]):
            t, tr = run_path(make_trainer(args.scene, cfg, images=args.images, gaussians=g),
                             state, args.steps, fused, grads, precull, fast_ssim, own)
            times[name].append(t)
            results[name] = (min(times[name]), tr)
    fast_t, fast = results["all speed-ups"]
    view = fast.data.test_ids[0] if fast.data.test_ids else fast.data.train_ids[0]
    ref = fast.render_view(view).clamp(0, 1)
    print(f"{'path':>15} {'s/step':>8} {'x fast':>7} {'max |param diff|':>17} {'render PSNR vs fast':>20}")
    for name, (t, tr) in results.items():
        diff = max(float((tr.params[k] - fast.params[k]).detach().abs().max()) for k in fast.params
                   if fast.params[k].numel())   # sh_rest is empty at SH degree 0
        p = psnr(tr.render_view(view).clamp(0, 1), ref) if tr is not fast else float("inf")
        print(f"{name:>15} {t:8.3f} {t / fast_t:7.2f} {diff:17.2e} {p:20.1f}")


if __name__ == "__main__":
    main()
