"""The water in front of a render through numba's kernels (:mod:`._numba_water`): the fast path
that goes with the rasterizer's numba path. Torch runs a step's elementwise work on one thread
there (numba's kernels own the threads), and the water's dozen passes over every pixel took
about a third of a 320x240 step at 37,000 Gaussians; here it is one pass forward and one back,
on the kernels' threads.

:func:`see` is :meth:`..model.medium.Medium.see` given the range, differentiable in the surface
and the three coefficient vectors; the torch definition is the oracle (values and gradients
agree to float32 rounding, tests/test_medium.py).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..render.numba_kernels import load_module, run_ranges, threads

_STATE: dict = {}


def load():
    """The kernel module, or None if numba is missing or fails here (why: :func:`error`)."""
    def smoke():
        s = torch.rand(2, 2, 3, requires_grad=True)
        coef = [torch.full((3,), 0.2, requires_grad=True) for _ in range(3)]
        see(s, torch.ones(2, 2), *coef).sum().backward()

    def kernels():
        from . import _numba_water
        _STATE["tables"] = _numba_water.tables()   # the curves and exponentials, built once
        return _numba_water
    return load_module(_STATE, kernels, smoke)


def error() -> Optional[BaseException]:
    return _STATE.get("error")


def _cuts(rows: int) -> list:
    parts = max(1, min(4 * threads(), rows // 8))
    return [rows * k // parts for k in range(parts + 1)]


class _See(torch.autograd.Function):
    @staticmethod
    def forward(ctx, surface, rng, att, back, veil):
        impl = _STATE["impl"]
        s = surface.detach().to(torch.float32).contiguous().numpy()
        r = rng.detach().to(torch.float32).contiguous().numpy()
        coef = [t.detach().to(torch.float32).numpy() for t in (att, back, veil)]
        out = np.empty_like(s)
        parts = np.empty((5,) + s.shape, np.float32)
        cuts = _cuts(s.shape[0])
        tabs = _STATE["tables"]
        run_ranges(lambda lo, hi: impl.forward(lo, hi, s, r, *coef, *tabs, out, parts), cuts)
        ctx.saved = (parts, cuts)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        impl = _STATE["impl"]
        parts, cuts = ctx.saved
        g_out = g.detach().to(torch.float32).contiguous().numpy()
        g_s = np.empty_like(g_out)
        g_coef = np.empty((g_out.shape[0], 9))
        run_ranges(lambda lo, hi: impl.backward(lo, hi, parts, g_out, g_s, g_coef), cuts)
        sums = torch.from_numpy(g_coef.sum(0)).to(torch.float32)
        return torch.from_numpy(g_s), None, sums[0:3], sums[3:6], sums[6:9]


def see(surface: torch.Tensor, rng: torch.Tensor, att: torch.Tensor, back: torch.Tensor,
        veil: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) sRGB as seen through the water: ``surface`` (H, W, 3) sRGB, ``rng`` (H, W) the
    range (not differentiated), ``att``, ``back``, ``veil`` (3,). Call :func:`load` first."""
    return _See.apply(surface, rng, att, back, veil)
