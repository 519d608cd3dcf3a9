"""The per-pair kernel sets and their cache: the eager ones (:mod:`.chunks`), their
``torch.compile``d twins with the smoke test that surfaces a broken compiler, the (eager or
compiled) SH colour, and whether numba's kernels load. :func:`.rasterizer.get_kernels` picks
a set per render; ``_KERNEL_CACHE`` also memoises the compiled binning and slot-table
functions of :mod:`.tiles`."""
from __future__ import annotations

from typing import NamedTuple

import torch

from .chunks import ALPHA_MAX, T_MIN, _chunk_backward, _chunk_forward
from .projection import ALPHA_MIN, allow_variants
from ..model.sh import eval_sh_colour


class _Kernels(NamedTuple):
    forward: object
    backward: object
    compiled: bool
    #: numba's whole-view kernels (:class:`.numba_kernels.NumbaKernels`): they replace the
    #: per-chunk ones of :mod:`.chunks` for float32 renders (float64 ones take the eager kernels)
    numba: object = None
    #: True: a float32 render takes Triton's kernels for the whole view
    #: (:func:`.rasterizer._render_triton`) where they load for its device; the per-chunk ones
    #: of :mod:`.chunks` stay for the eager path it falls back to
    triton: bool = False


_KERNEL_CACHE: dict = {}


def _mark_dynamic(*tensors_dims):
    """Tell torch.compile which dims vary (Tc, G) so it compiles once, keeping P static."""
    mark = torch._dynamo.maybe_mark_dynamic
    for t, dims in tensors_dims:
        for d in dims:
            mark(t, d)


def _compiled_kernels() -> _Kernels:
    allow_variants()
    fwd_c = torch.compile(_chunk_forward, fullgraph=True, dynamic=False)
    bwd_c = torch.compile(_chunk_backward, fullgraph=True, dynamic=False)

    # Always without autograd (also inside autograd.Function), so one graph per kernel.
    def fwd(pxl, pyl, geo, vals):
        _mark_dynamic((geo, (1, 2)), (vals, (1, 2)))
        with torch.no_grad():
            return fwd_c(pxl, pyl, geo, vals, True)

    def bwd(pxl, pyl, geo, vals, g, t_excl, g_out):
        _mark_dynamic((geo, (1, 2)), (vals, (1, 2)), (g, (0, 1)), (t_excl, (0, 1)),
                      (g_out, (1,)))
        with torch.no_grad():
            return bwd_c(pxl, pyl, geo, vals, g, t_excl, g_out, True)

    return _Kernels(fwd, bwd, True)


def _smoke_test(kern: _Kernels) -> None:
    """Run the kernels once on a small input (forces compilation, surfaces failures)."""
    gen = torch.Generator().manual_seed(0)
    pxl = torch.arange(4, dtype=torch.float32) - 1.5
    geo = torch.rand(6, 3, 5, generator=gen)
    vals = torch.rand(5, 3, 5, generator=gen)
    out, g, te = kern.forward(pxl, pxl, geo, vals)
    kern.backward(pxl, pxl, geo, vals, g, te, torch.ones_like(out))


def numba_kernels_ready() -> bool:
    """Whether ``compiled="numba"`` runs numba's kernels here (numba installed and working)."""
    from . import numba_kernels
    return numba_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN) is not None


def _sh_fn(compiled: bool):
    """SH colour evaluation, eager or compiled (per Gaussian, fused forward and backward)."""
    if not compiled:
        return eval_sh_colour
    if "sh" not in _KERNEL_CACHE:
        allow_variants()
        _KERNEL_CACHE["sh"] = torch.compile(eval_sh_colour, dynamic=True)
    return _KERNEL_CACHE["sh"]
