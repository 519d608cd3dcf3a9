"""The training loss's SSIM term through numba's kernels (:mod:`._numba_ssim`): the fast
path that goes with the rasterizer's numba path (no C++ compiler needed).

:func:`ssim_term` is :func:`.losses.ssim_term` (the weighted mean of ``1 - SSIM`` that
:func:`.losses.training_loss` adds to its photometric term), differentiable in the render
only. The eager definition is the oracle: the two agree to float32 rounding, values and
gradients (tests/test_losses.py). A training step on a 320x240 view, one thread
(benchmarks/bench_train_step.py): 0.047 s with these kernels against 0.058 s with the eager
term at 7,000 Gaussians, 0.108 against 0.114 s at 59,733 (benchmarks/RESULTS.md#training-numba-ssim).

:func:`load` imports and compiles (or loads from numba's cache) the kernels; the trainer asks
for this path only once its :class:`.compiling.CompileSwitch` is on numba's, whose background
warm-up compiles these kernels with the rasterizer's, so a cold cache never stalls a step.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..render.numba_kernels import load_module, run_ranges, threads
from .losses import SSIM_C1, SSIM_C2, gaussian_window

_STATE: dict = {}


def load():
    """The kernel module, or None if numba is missing or fails here (why: :func:`error`)."""
    def smoke():
        g = torch.rand(2, 3, 3, generator=torch.Generator().manual_seed(0))
        b = torch.rand(2, 3, 3, generator=torch.Generator().manual_seed(1))
        ssim_term(g.requires_grad_(), b, torch.ones(2, 3)).backward()   # both signatures the loss uses
        ssim_term(g, b).backward()

    def kernels():
        from . import _numba_ssim
        return _numba_ssim
    return load_module(_STATE, kernels, smoke)


def error() -> Optional[BaseException]:
    return _STATE.get("error")


def _row_cuts(rows: int) -> list:
    parts = max(1, min(4 * threads(), rows // 16))
    return [rows * k // parts for k in range(parts + 1)]


_TAPS = gaussian_window(dtype=torch.float32).numpy()


class _SSIMTerm(torch.autograd.Function):
    @staticmethod
    def forward(ctx, render, target, weight, norm):
        impl = _STATE["impl"]
        a = render.detach().contiguous().numpy()
        b = target.detach().contiguous().numpy()
        h, w, n_c = a.shape
        cuts = _row_cuts(n_c * h)
        tmp = np.empty((5, n_c, h, w), np.float32)
        run_ranges(lambda lo, hi: impl.forward_rows(lo, hi, a, b, _TAPS, tmp), cuts)
        row_sums = np.empty(n_c * h)
        grads = np.empty((3, n_c, h, w), np.float32)
        run_ranges(lambda lo, hi: impl.forward_cols(lo, hi, tmp, _TAPS, np.float32(SSIM_C1), np.float32(SSIM_C2),
                                                    weight, np.float32(norm), row_sums, grads), cuts)
        ctx.saved = (a, b, grads, cuts)
        return torch.tensor(float(row_sums.sum()), dtype=render.dtype)

    @staticmethod
    def backward(ctx, g):
        impl = _STATE["impl"]
        a, b, grads, cuts = ctx.saved
        tmp = np.empty_like(grads)
        run_ranges(lambda lo, hi: impl.backward_rows(lo, hi, grads, _TAPS, tmp), cuts)
        grad_a = np.empty_like(a)
        run_ranges(lambda lo, hi: impl.backward_cols(lo, hi, tmp, _TAPS, a, b, np.float32(float(g)), grad_a), cuts)
        return torch.from_numpy(grad_a), None, None, None


def ssim_term(render: torch.Tensor, target: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """:func:`.losses.ssim_term` through numba's kernels: ``1 - SSIM(render, target)``
    (``weight`` None), or ``sum_pixels weight (1 - mean_c S) / sum weight`` with S the
    per-pixel SSIM map. ``render``, ``target``: (H, W, 3) float32 on the CPU; ``weight``:
    (H, W) or None. Differentiable in ``render`` only. Call :func:`load` first."""
    h, w, n_c = render.shape
    if weight is None:
        return _SSIMTerm.apply(render, target, np.empty((0, 0), np.float32), 1.0 / (n_c * h * w))
    total = float(weight.sum().clamp_min(1e-12))
    return _SSIMTerm.apply(render, target, weight.detach().to(torch.float32).contiguous().numpy(), 1.0 / (n_c * total))
