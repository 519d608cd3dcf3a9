"""The compositing step in numba: a fast rasterizer path that needs no C++ compiler.

numba ships LLVM inside its wheels (Linux, Windows, macOS; x64 and arm64), so these kernels
compile on an artist's machine that has no C++ compiler, where ``torch.compile`` cannot run.
The kernels themselves are in :mod:`._numba_impl`; this module loads them (or says why it
cannot) and wraps them for :class:`..rasterizer._CompositeNumba`:

    forward(tile_start, rows, pos, geo, vals, tile_size, tiles_x, tiles_y)
        -> out (C, Hp, Wp) accumulated values, last (Hp, Wp) entries each pixel went through
    backward(tile_start, rows, pos, geo, vals, tile_size, tiles_x, out, last, g_out)
        -> d_rows (6 + C, V): per visible Gaussian, gradients wrt centre x, y, l11, l21, l22,
           opacity and the C values

One kernel call composites every tile of a view and one computes every gradient, with no
per-pair state kept in between (the backward replays each pixel's pass up to where it
stopped). Compared with the eager torch oracle (``rasterizer._chunk_forward`` /
``_chunk_backward``) the results differ by float32 summation order and by ``exp`` (both within
1 ulp); tests/test_rasterizer.py checks images and gradients against it.

Threads: numba's own pool, as many threads as torch uses, and the ``workqueue`` layer unless
``NUMBA_THREADING_LAYER`` says otherwise: its workers sleep as soon as a kernel is done,
where an OpenMP pool (a second one: numba's is not torch's) would spin on the cores torch's
next operation needs. The machine code is cached in ``NUMBA_CACHE_DIR`` (the trainer points
it at RecGS's per-user cache folder): compiling the kernels cold takes ~10-20 s, once.
"""
from __future__ import annotations

import os
from typing import Optional

import numpy as np
import torch

_STATE: dict = {}


class NumbaKernels:
    """The loaded kernels, with torch-side wrappers (float32 only)."""

    def __init__(self, impl, amin: float, amax: float, t_min: float) -> None:
        self.impl = impl
        self.consts = (np.float32(amin), np.float32(amax), np.float32(t_min))

    @staticmethod
    def _threads() -> None:   # as many as torch uses (fewer while a compile warm-up borrows one)
        import numba
        numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))

    def forward(self, tile_start, rows, pos, geo, vals, tile_size: int, tiles_x: int, tiles_y: int):
        self._threads()
        n_c = vals.shape[1]
        hp, wp = tiles_y * tile_size, tiles_x * tile_size
        out = np.empty((n_c, hp, wp), np.float32)
        last = np.empty((hp, wp), np.int32)
        self.impl.composite_forward(tile_start, rows, pos, geo, vals, tile_size, tiles_x,
                                    *self.consts, out, last)
        return out, last

    def backward(self, tile_start, rows, pos, geo, vals, tile_size: int, tiles_x: int, out, last,
                 g_out):
        self._threads()
        if vals.shape[1] != 5:
            raise ValueError("the numba backward takes 5 values a Gaussian (rgb, depth, 1)")
        n_f = 6 + vals.shape[1]
        d_isect = np.empty((n_f, rows.shape[0]), np.float32)
        self.impl.composite_backward(tile_start, rows, pos, geo, vals, tile_size, tiles_x,
                                     *self.consts, out, last, g_out, d_isect)
        d_rows = np.zeros((n_f, geo.shape[0]), np.float32)
        self.impl.gather_rows(rows, d_isect, d_rows)
        return d_rows


def _smoke(k: NumbaKernels) -> None:
    """Compile (or load from the cache) every kernel on a tiny input."""
    rng = np.random.default_rng(0)
    v = 3
    pos = rng.uniform(0, 8, (v, 2))
    geo = np.concatenate([rng.uniform(0.3, 1.0, (v, 3)), rng.uniform(0.2, 1.0, (v, 1))], 1).astype(np.float32)
    vals = rng.uniform(0, 1, (v, 5)).astype(np.float32)
    rows = np.array([0, 1, 2, 0, 2], np.int32)
    tile_start = np.array([0, 3, 3, 4, 5], np.int64)
    out, last = k.forward(tile_start, rows, pos, geo, vals, 4, 2, 2)
    k.backward(tile_start, rows, pos, geo, vals, 4, 2, out, last, np.ones_like(out))


def load(alpha_min: float, alpha_max: float, t_min: float) -> Optional[NumbaKernels]:
    """The kernels, or None if numba is missing or fails here (the reason: :func:`error`).
    The constants are the rasterizer's (passed in: this module does not import it). The first
    call compiles or loads from the cache (``NUMBA_CACHE_DIR``, read now, not only when numba
    was imported)."""
    if "kernels" in _STATE or "error" in _STATE:
        return _STATE.get("kernels")
    try:
        os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
        import numba
        if os.environ.get("NUMBA_CACHE_DIR"):
            numba.config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
        if numba.config.THREADING_LAYER == "default":
            numba.config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]
        from . import _numba_impl
        k = NumbaKernels(_numba_impl, alpha_min, alpha_max, t_min)
        _smoke(k)
    except Exception as exc:  # ImportError (no numba), an unsupported platform, ...
        _STATE["error"] = exc
        return None
    _STATE["kernels"] = k
    return k


def error() -> Optional[BaseException]:
    return _STATE.get("error")
