"""The rasterizer in numba: a fast path that needs no C++ compiler.

numba ships LLVM inside its wheels (Linux, Windows, macOS; x64 and arm64), so these kernels
compile on an artist's machine that has no C++ compiler, where ``torch.compile`` cannot run.
The kernels are in :mod:`._numba_impl`; this module loads them (or says why it cannot) and
wraps them for :func:`..rasterizer._render_numba`, which runs a whole view through them:

* ``cull``: per Gaussian, no gradient: camera transform, EWA covariance, opacity-aware
  radius, screen box (the twin of projection.py's candidate test and ``_cull_rows``); then the
  visible ones in depth order;
* ``bin``: each visible Gaussian's tiles, exact per tile row, as one counting sort by tile
  (stable: depth order inside a tile), no padding;
* ``project_forward`` / ``project_backward``: the differentiable projection and SH colour of
  the visible rows, with the chain rule written out (float64);
* ``forward`` / ``backward``: compositing, one pass over every tile; no per-pair state kept
  (the backward replays each pixel's pass up to where the forward stopped it).

Against the eager torch oracle (tests/test_rasterizer.py) the results differ by float32
summation order and by ``exp`` (both within 1 ulp).

Threads: the kernels are serial over a range of items and release the GIL; this module
splits each call into ranges and runs them on as many threads as torch uses, or inside
:func:`own_threads` as many as torch had (its own pool of plain threads, which sleep between
calls).
torch's OpenMP threads do not sleep at once: after each of torch's parallel operations they
spin, and on a machine with no spare core they take the cores these kernels' threads need.
:func:`own_threads` gives the kernels torch's threads for a block and torch one (the trainer's
step on this path; two cores: 0.064 against 0.079 s a step at 59,733 Gaussians, 0.038 against
0.047 s at 7,000, benchmarks/bench_train_step.py).

The machine code is cached in ``NUMBA_CACHE_DIR`` (the trainer points it at RecGS's per-user
cache folder); compiling it cold takes ~15 s of one core, once per machine and version.
"""
from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Optional

import numpy as np
import torch

_STATE: dict = {}
_POOL: dict = {}
_LOCK = threading.Lock()
_THREADS: dict = {"n": None}   # own_threads' count (None: torch's)


def threads() -> int:
    """Threads the kernels run on: inside :func:`own_threads` the count torch had, else torch's."""
    n = _THREADS["n"]
    return max(1, int(n) if n is not None else torch.get_num_threads())


@contextmanager
def own_threads():
    """Inside the block, the kernels run on the threads torch had and torch on one: torch's
    work between the kernels (loss, Adam, gathers) is small next to theirs, and a single
    torch thread leaves no OpenMP thread spinning on the cores they use."""
    n, prev = threads(), _THREADS["n"]
    t = torch.get_num_threads()
    _THREADS["n"] = n
    if t > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if t > 1:
            torch.set_num_threads(t)
        _THREADS["n"] = prev


def _pool(workers: int) -> ThreadPoolExecutor:
    with _LOCK:
        if _POOL.get("size", 0) < workers:
            if "pool" in _POOL:
                _POOL["pool"].shutdown(wait=False)
            _POOL["pool"] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="recgs-numba")
            _POOL["size"] = workers
        return _POOL["pool"]


def run_ranges(fn: Callable[[int, int], None], bounds) -> None:
    """Call ``fn(lo, hi)`` for consecutive (lo, hi) pairs of ``bounds`` (a list of cut points),
    on :func:`threads` threads: the calling thread and workers pull ranges in order until none is
    left (so uneven ranges balance out). The calls touch disjoint outputs."""
    bounds = list(bounds)
    jobs = [(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]
    n_threads = min(threads(), len(jobs))
    if n_threads <= 1:
        for lo, hi in jobs:
            fn(lo, hi)
        return
    nxt = itertools.count()

    def work():
        while True:
            i = next(nxt)
            if i >= len(jobs):
                return
            fn(*jobs[i])

    futures = [_pool(n_threads - 1).submit(work) for _ in range(n_threads - 1)]
    work()
    for f in futures:
        f.result()


def _cuts(n: int, parts: int) -> list:
    return [n * k // parts for k in range(parts + 1)]


def _parts(n_items: int) -> int:
    """Ranges per call: a few per thread (load balance), none tiny."""
    return max(1, min(4 * threads(), n_items // 256))


class NumbaKernels:
    """The loaded kernels, with numpy-side wrappers (float32 inputs)."""

    def __init__(self, impl, amin: float, amax: float, t_min: float) -> None:
        from ..model import gaussians as gs
        self.impl = impl
        self.consts = (np.float32(amin), np.float32(amax), np.float32(t_min))
        self.shc = np.array(gs.SH_CONSTANTS, np.float64)

    @staticmethod
    def _cst(near: float):
        """What the per-Gaussian kernels read from ``cst`` (projection.kernel_constants)."""
        from . import projection as pj
        return np.array(pj.kernel_constants(near), np.float64)

    @staticmethod
    def _tile_cuts(tile_start) -> list:
        """Tile ranges with about equal numbers of intersections (the work)."""
        n_tiles = tile_start.shape[0] - 1
        parts = _parts(n_tiles)
        targets = np.linspace(0, tile_start[-1], parts + 1)[1:-1]
        cuts = np.searchsorted(tile_start[:-1], targets, side="left")
        return [0, *np.unique(cuts).tolist(), n_tiles] if n_tiles else [0, 0]

    # ---- compositing -----------------------------------------------------------------

    def forward(self, tile_start, rows, pos, geo, vals, tile_size: int, tiles_x: int, tiles_y: int):
        """-> out (C, Hp, Wp) accumulated values, last (Hp, Wp) int32: list entries each
        pixel went through before it stopped."""
        n_c = vals.shape[1]
        hp, wp = tiles_y * tile_size, tiles_x * tile_size
        out = np.empty((n_c, hp, wp), np.float32)
        last = np.empty((hp, wp), np.int32)
        run_ranges(lambda lo, hi: self.impl.composite_forward(
            lo, hi, tile_start, rows, pos, geo, vals, tile_size, tiles_x, *self.consts, out, last),
            self._tile_cuts(tile_start))
        return out, last

    def backward(self, tile_start, rows, pos, geo, vals, tile_size: int, tiles_x: int, out, last,
                 g_out, weights: bool = False):
        """-> d_rows (6 + C, V): per visible Gaussian, gradients wrt centre x, y, l11, l21, l22,
        opacity and the C = 5 values, from ``g_out`` (C, Hp, Wp); with ``weights``, a last row
        (7 + C, V) holds each visible Gaussian's blending weight in the view (pixels)."""
        if vals.shape[1] != 5:
            raise ValueError("the numba backward takes 5 values a Gaussian (rgb, depth, 1)")
        n_f = 6 + vals.shape[1] + int(weights)
        d_isect = np.empty((n_f, rows.shape[0]), np.float32)
        run_ranges(lambda lo, hi: self.impl.composite_backward(
            lo, hi, tile_start, rows, pos, geo, vals, tile_size, tiles_x, *self.consts, out, last,
            g_out, d_isect), self._tile_cuts(tile_start))
        d_rows = np.zeros((n_f, geo.shape[0]), np.float32)
        run_ranges(lambda lo, hi: self.impl.gather_rows(lo, hi, rows, d_isect, d_rows), range(n_f + 1))
        return d_rows

    # ---- per Gaussian: culling, projection and colour; binning -------------------------

    def cull(self, means, log_scales, quats, logits, vm, K, width: int, height: int, near: float,
             antialiased: bool):
        """-> info (N, 14) float64 (see _numba_impl.cull), ids (V,) int64 of the drawn
        Gaussians in depth order (ties by index), radii (N,) int32 (0 = culled)."""
        n = means.shape[0]
        info = np.empty((n, 14))
        cst = self._cst(near)
        run_ranges(lambda lo, hi: self.impl.cull(lo, hi, means, log_scales, quats, logits, vm, K,
                                                 width, height, antialiased, cst, info),
                   _cuts(n, _parts(n)))
        ids = self.impl.visible_in_depth_order(info)
        drawn = info[:, 0] > 0
        radii = np.zeros(n, np.int32)   # a culled row's other columns are never written
        radii[drawn] = np.ceil(info[drawn, 13])
        return info, ids, radii

    def bin(self, info, ids, tile_size: int, tiles_x: int, n_tiles: int):
        """-> tile_start (n_tiles + 1,) int64, rows (M,) int32 (positions in ``ids``), sorted
        by tile, in depth order inside a tile (whatever the number of threads)."""
        n = ids.shape[0]
        parts = max(1, min(threads(), n // 1024))
        cuts = _cuts(n, parts)
        counts = np.zeros((parts, n_tiles), np.int64)
        run_ranges(lambda lo, hi: self.impl.bin_count(cuts[lo], cuts[hi], info, ids, tile_size,
                                                      tiles_x, counts[lo]), range(parts + 1))
        tile_start = np.empty(n_tiles + 1, np.int64)
        self.impl.bin_offsets(counts, tile_start)
        rows = np.empty(tile_start[-1], np.int32)
        run_ranges(lambda lo, hi: self.impl.bin_fill(cuts[lo], cuts[hi], info, ids, tile_size,
                                                     tiles_x, counts[lo], rows), range(parts + 1))
        return tile_start, rows

    def project_forward(self, rows, deg: int, vm, K, campos, width: int, height: int, near: float,
                        antialiased: bool):
        """rows = (means (V, 3), log_scales (V, 3), quats (V, 4), logits (V,), sh (V, K, 3)),
        float32 -> pos (V, 2) float64, geo (V, 4) (l11, l21, l22, opacity), depth (V,),
        colour (V, 3) float32."""
        v = rows[0].shape[0]
        pos = np.empty((v, 2))
        geo = np.empty((v, 4), np.float32)
        depth = np.empty(v, np.float32)
        colour = np.empty((v, 3), np.float32)
        cst = self._cst(near)
        run_ranges(lambda lo, hi: self.impl.project_forward(
            lo, hi, *rows, deg, vm, K, campos, width, height, antialiased, cst, self.shc,
            pos, geo, depth, colour), _cuts(v, _parts(v)))
        return pos, geo, depth, colour

    def project_backward(self, rows, deg: int, vm, K, campos, width: int, height: int,
                         near: float, antialiased: bool, g_pos, g_geo, g_depth, g_colour):
        """Gradients wrt ``rows`` (float32, same shapes) from those of pos (V, 2), geo,
        depth and colour."""
        v = rows[0].shape[0]
        grads = tuple(np.empty(r.shape, np.float32) for r in rows[:4]) + (np.zeros(rows[4].shape, np.float32),)
        cst = self._cst(near)
        run_ranges(lambda lo, hi: self.impl.project_backward(
            lo, hi, *rows, deg, vm, K, campos, width, height, antialiased, cst, self.shc,
            g_pos, g_geo, g_depth, g_colour, *grads), _cuts(v, _parts(v)))
        return grads


def _smoke(k: NumbaKernels) -> None:
    """Compile (or load from the cache) every kernel on a tiny input, with the argument types
    a render passes."""
    rng = np.random.default_rng(0)
    f32 = np.float32
    v = 3
    params = (rng.normal(0, 0.3, (v, 3)).astype(f32) + f32([0, 0, 3]), np.full((v, 3), -2.0, f32),
              rng.normal(size=(v, 4)).astype(f32), np.zeros(v, f32), rng.normal(0, 0.3, (v, 16, 3)).astype(f32))
    vm = np.eye(4)
    K = np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]])
    info, ids, _ = k.cull(*params[:4], vm, K, 8, 8, 0.2, False)
    tile_start, rows = k.bin(info, ids, 4, 2, 4)
    pos, geo, depth, colour = k.project_forward(params, 3, vm, K, np.zeros(3), 8, 8, 0.2, True)
    k.project_backward(params, 3, vm, K, np.zeros(3), 8, 8, 0.2, True, pos.astype(f32), geo, depth, colour)
    vals = np.concatenate([colour, depth[:, None], np.ones((v, 1), f32)], 1)
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
        import numba
        if os.environ.get("NUMBA_CACHE_DIR"):
            numba.config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
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


def load_module(state: dict, importer: Callable[[], object], smoke: Callable[[], None]):
    """A module of kernels the way :func:`load` loads the rasterizer's: ``importer()`` imports
    it after numba's cache has been pointed at ``NUMBA_CACHE_DIR``, ``smoke()`` compiles (or
    loads) and runs it once. Kept in ``state`` (``impl``, or ``error`` with the reason); returns
    the module, or None if numba is missing or fails here."""
    if "impl" in state or "error" in state:
        return state.get("impl")
    try:
        import numba
        if os.environ.get("NUMBA_CACHE_DIR"):
            numba.config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
        state["impl"] = importer()
        smoke()
    except Exception as exc:  # ImportError (no numba), an unsupported platform, ...
        state.clear()
        state["error"] = exc
        return None
    return state["impl"]


def disable(exc: BaseException) -> None:
    """Kernels that failed at run time: :func:`load` returns None from now on (eager torch)."""
    _STATE.clear()
    _STATE["error"] = exc
