"""The per-pair compositing kernels in numba: compiled without a C++ compiler.

numba ships LLVM inside its wheels (Linux, Windows, macOS; x64 and arm64), so these loops
compile on an artist's machine that has no C++ compiler, where ``torch.compile`` cannot run.
Same signatures and layout as :func:`..rasterizer._chunk_forward` / ``_chunk_backward``
(the eager torch oracle the tests compare them with):

    forward(pxl (P,), pyl (P,), geo (6, Tc, G), vals (C, Tc, G))
        -> out (C, Tc, P), g (Tc, G, P), t_excl (Tc, G, P)
    backward(pxl, pyl, geo, vals, g, t_excl, g_out (C, Tc, P))
        -> d_geo (6, Tc, G), d_vals (C, Tc, G)

One loop per pixel, front to back, stopping where the transmittance would fall below
``T_MIN`` (the eager kernels evaluate every slot and mask). Past that stop ``g`` and
``t_excl`` are 0, which the backward reads as "not composited", as the eager mask does, so
outputs and gradients are the eager ones up to float32 summation order. Tiles run in
parallel (``prange``): each owns its rows of the outputs, so there are no write races.

The machine code is cached (``NUMBA_CACHE_DIR``; the trainer points it at RecGS's per-user
cache folder); the first use on a machine compiles for a few seconds.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

_KERNELS: Optional[tuple] = None
_ERROR: Optional[BaseException] = None


def _build(alpha_min: float, alpha_max: float, t_min: float):
    import numba
    from numba import prange

    @numba.njit(parallel=True, cache=True, fastmath=False)
    def forward(pxl, pyl, geo, vals, out, g, t_excl):
        n_c, n_t, n_g = vals.shape
        n_p = pxl.shape[0]
        for t in prange(n_t):
            for p in range(n_p):
                T = np.float32(1.0)
                for c in range(n_c):
                    out[c, t, p] = 0.0
                stopped = False
                for i in range(n_g):
                    if stopped:
                        g[t, i, p] = 0.0
                        t_excl[t, i, p] = 0.0
                        continue
                    dx = pxl[p] - geo[0, t, i]
                    dy = pyl[p] - geo[1, t, i]
                    p1 = geo[2, t, i] * dx + geo[3, t, i] * dy
                    p2 = geo[4, t, i] * dy
                    gg = math.exp(np.float32(-0.5) * (p1 * p1 + p2 * p2))
                    g[t, i, p] = gg
                    t_excl[t, i, p] = T
                    alpha = min(geo[5, t, i] * gg, alpha_max)
                    if alpha >= alpha_min:
                        t_next = T * (np.float32(1.0) - alpha)
                        if t_next < t_min:
                            stopped = True
                            continue
                        w = alpha * T
                        for c in range(n_c):
                            out[c, t, p] += w * vals[c, t, i]
                        T = t_next

    @numba.njit(parallel=True, cache=True, fastmath=False)
    def backward(pxl, pyl, geo, vals, g, t_excl, g_out, d_geo, d_vals):
        n_c, n_t, n_g = vals.shape
        n_p = pxl.shape[0]
        for t in prange(n_t):
            for p in range(n_p):
                # sum over composited slots of w_i <g_out, v_i>, for the "behind" sums
                total = np.float32(0.0)
                for i in range(n_g):
                    T = t_excl[t, i, p]
                    if T == 0.0:
                        break
                    alpha = min(geo[5, t, i] * g[t, i, p], alpha_max)
                    if alpha >= alpha_min and T * (np.float32(1.0) - alpha) >= t_min:
                        gv = np.float32(0.0)
                        for c in range(n_c):
                            gv += vals[c, t, i] * g_out[c, t, p]
                        total += alpha * T * gv
                done = np.float32(0.0)
                for i in range(n_g):
                    T = t_excl[t, i, p]
                    if T == 0.0:
                        break
                    gg = g[t, i, p]
                    oa = geo[5, t, i] * gg
                    alpha = min(oa, alpha_max)
                    om = np.float32(1.0) - alpha
                    if not (alpha >= alpha_min and T * om >= t_min):
                        continue
                    gv = np.float32(0.0)
                    for c in range(n_c):
                        gv += vals[c, t, i] * g_out[c, t, p]
                    w = alpha * T
                    done += w * gv
                    behind = total - done
                    for c in range(n_c):
                        d_vals[c, t, i] += w * g_out[c, t, p]
                    if oa > alpha_max:        # the clamp: no gradient to opacity or falloff
                        continue
                    d_oa = gv * T - behind / om
                    dx = pxl[p] - geo[0, t, i]
                    dy = pyl[p] - geo[1, t, i]
                    p1 = geo[2, t, i] * dx + geo[3, t, i] * dy
                    p2 = geo[4, t, i] * dy
                    d_q = np.float32(-0.5) * oa * d_oa
                    e1 = d_q * p1
                    e2 = d_q * p2
                    d_geo[0, t, i] += np.float32(-2.0) * geo[2, t, i] * e1
                    d_geo[1, t, i] += np.float32(-2.0) * (geo[3, t, i] * e1 + geo[4, t, i] * e2)
                    d_geo[2, t, i] += np.float32(2.0) * e1 * dx
                    d_geo[3, t, i] += np.float32(2.0) * e1 * dy
                    d_geo[4, t, i] += np.float32(2.0) * e2 * dy
                    d_geo[5, t, i] += gg * d_oa

    return forward, backward


def _np(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().numpy(), dtype=np.float32)


def load(alpha_min: float, alpha_max: float, t_min: float):
    """(forward, backward) taking and returning torch tensors, or None if numba is missing
    or fails to compile here (the reason: :func:`error`). The constants are the
    rasterizer's (passed in: this module does not import it)."""
    global _KERNELS, _ERROR
    if _KERNELS is not None or _ERROR is not None:
        return _KERNELS
    try:
        fwd_nb, bwd_nb = _build(np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min))
    except Exception as exc:  # ImportError (no numba), an unsupported platform, ...
        _ERROR = exc
        return None

    import numba

    def threads() -> None:   # as many as torch uses (fewer while a compile warm-up borrows one)
        numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))

    def forward(pxl, pyl, geo, vals, fused=False):
        threads()
        c, tc, n = vals.shape
        p = pxl.shape[0]
        out = np.empty((c, tc, p), np.float32)
        g = np.empty((tc, n, p), np.float32)
        t_excl = np.empty((tc, n, p), np.float32)
        fwd_nb(_np(pxl), _np(pyl), _np(geo), _np(vals), out, g, t_excl)
        return torch.from_numpy(out), torch.from_numpy(g), torch.from_numpy(t_excl)

    def backward(pxl, pyl, geo, vals, g, t_excl, g_out, fused=False):
        threads()
        d_geo = np.zeros(tuple(geo.shape), np.float32)
        d_vals = np.zeros(tuple(vals.shape), np.float32)
        bwd_nb(_np(pxl), _np(pyl), _np(geo), _np(vals), _np(g), _np(t_excl), _np(g_out), d_geo, d_vals)
        return torch.from_numpy(d_geo), torch.from_numpy(d_vals)

    try:   # compile now (a few seconds the first time on a machine, then from the cache)
        gen = torch.Generator().manual_seed(0)
        pix = torch.arange(4, dtype=torch.float32) - 1.5
        geo = torch.rand(6, 2, 3, generator=gen)
        vals = torch.rand(2, 2, 3, generator=gen)
        out, g, te = forward(pix, pix, geo, vals)
        backward(pix, pix, geo, vals, g, te, torch.ones_like(out))
    except Exception as exc:
        _ERROR = exc
        return None
    _KERNELS = (forward, backward)
    return _KERNELS


def error() -> Optional[BaseException]:
    return _ERROR
