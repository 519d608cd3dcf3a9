"""The GPU path's kernels in Triton and their launches (:class:`TritonKernels`): the
compositing here, one program a tile, forward and backward, nothing kept per (pixel,
Gaussian) pair; culling, binning and projection + SH colour in :mod:`._triton_project`.

Triton ships with the CUDA builds of torch (``pip install torch`` on a machine with an NVIDIA
GPU brings it), compiles its kernels itself and needs no C++ compiler or CUDA toolkit on the
artist's machine. The kernels are the twins of numba's (:mod:`._numba_tiles`): the same
front-to-back loop over a tile's depth-sorted list, the same 1/255 skip, 0.99 clamp and
transmittance stop, and a backward that replays each pixel's pass up to where the forward
stopped it (``last``) and uses ``dC/dalpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) /
(1 - alpha_i)``, the sum behind being ``<g_out, out>`` less the running sum in front. Each
(tile, Gaussian) intersection belongs to one tile, so a program writes its intersections'
gradients without atomics; :func:`backward` sums them per Gaussian with one ``index_add_``.

The pixels of a tile are the lanes of one program (16x16 by default on a GPU); the loop over
the tile's list is sequential and stops when every pixel has stopped.

Without a GPU the same kernels run in Triton's interpreter (``TRITON_INTERPRET=1`` in the
environment before Triton is imported; CPU tensors, numpy underneath): that is how the tests
check them against the eager path on any machine. :func:`load` returns ``None`` (and :func:`error` says why) where Triton is missing.
"""
from __future__ import annotations

import os
from typing import Optional

import torch

from ..model.gaussians import SH_CONSTANTS
from .projection import kernel_constants

from ._triton_project import _IMPORT_ERROR, _jit, tl, triton

_STATE: dict = {}
#: Values a Gaussian carries into the compositing at most (rgb, depth, 1 and spares): the
#: channel axis of a program's accumulator is padded to a power of two.
_MAX_VALUES = 8
#: Gaussians a program of the per-Gaussian kernels takes (lanes).
_PROJECT_BLOCK = 128


@_jit
def _tile(tile_start, tiles_x, wp, TS: tl.constexpr):
    """This program's tile: its list's range in ``rows`` (s0, s1), its centre (cx, cy) (float64),
    its pixels' offsets from it (float32) and their index in a (Hp, Wp) image."""
    t = tl.program_id(0)
    s0 = tl.load(tile_start + t)
    s1 = tl.load(tile_start + t + 1)
    ty = t // tiles_x
    tx = t - ty * tiles_x
    cx = (tx * TS).to(tl.float64) + 0.5 * TS
    cy = (ty * TS).to(tl.float64) + 0.5 * TS
    p = tl.arange(0, TS * TS)
    pxl = (p % TS).to(tl.float32) + (0.5 - 0.5 * TS)
    pyl = (p // TS).to(tl.float32) + (0.5 - 0.5 * TS)
    pix = (ty * TS + p // TS) * wp + tx * TS + p % TS
    return s0, s1, cx, cy, pxl, pyl, pix


@_jit
def _falloff(rows, pos, geo, k, cx, cy, pxl, pyl):
    """Entry k of the list: its Gaussian's row, conic factor (l11, l21, l22) and opacity, the
    pixels' offsets from its centre, the whitened offsets and the falloff exp(-d^T S^-1 d / 2)."""
    r = tl.load(rows + k).to(tl.int64)
    mx = (tl.load(pos + 2 * r) - cx).to(tl.float32)
    my = (tl.load(pos + 2 * r + 1) - cy).to(tl.float32)
    l11 = tl.load(geo + 4 * r)
    l21 = tl.load(geo + 4 * r + 1)
    l22 = tl.load(geo + 4 * r + 2)
    o = tl.load(geo + 4 * r + 3)
    dx = pxl - mx
    dy = pyl - my
    p1 = l11 * dx + l21 * dy
    p2 = l22 * dy
    g = tl.exp(-0.5 * (p1 * p1 + p2 * p2))
    return r, l11, l21, l22, o, dx, dy, p1, p2, g


def _forward_kernel(tile_start, rows, pos, geo, vals, out, last, tiles_x, hp, wp, amin, amax, tmin,
                    TS: tl.constexpr, C: tl.constexpr, CB: tl.constexpr):
    """One tile: front-to-back over its list. Writes ``out`` (C, Hp, Wp), the accumulated
    ``sum_i v_i alpha_i T_i``, and ``last`` (Hp, Wp) int32, the entries a pixel went through
    before it stopped."""
    s0, s1, cx, cy, pxl, pyl, pix = _tile(tile_start, tiles_x, wp, TS)
    ch = tl.arange(0, CB)
    T = tl.full((TS * TS,), 1.0, tl.float32)
    live = tl.full((TS * TS,), 1.0, tl.float32)
    cnt = tl.zeros((TS * TS,), tl.int32)
    acc = tl.zeros((TS * TS, CB), tl.float32)
    k = s0
    n_live = TS * TS
    while (k < s1) & (n_live > 0):
        r, l11, l21, l22, o, dx, dy, p1, p2, g = _falloff(rows, pos, geo, k, cx, cy, pxl, pyl)
        alpha = tl.minimum(o * g, amax)
        t_next = T * (1.0 - alpha)
        keep = (alpha >= amin) & (live > 0.0)
        stop = keep & (t_next < tmin)
        use = keep & (t_next >= tmin)
        w = tl.where(use, alpha * T, 0.0)
        T = tl.where(use, t_next, T)
        live = tl.where(stop, 0.0, live)
        alive = live > 0.0
        cnt += alive.to(tl.int32)
        v = tl.load(vals + r * C + ch, mask=ch < C, other=0.0)
        acc += w[:, None] * v[None, :]
        n_live = tl.sum(alive.to(tl.int32), axis=0)
        k += 1
    tl.store(out + ch[None, :] * (hp * wp) + pix[:, None], acc, mask=ch[None, :] < C)
    tl.store(last + pix, cnt)


def _backward_kernel(tile_start, rows, pos, geo, vals, out, last, g_out, d_isect, n_isect, tiles_x, hp, wp,
                     amin, amax, tmin, TS: tl.constexpr, C: tl.constexpr, CB: tl.constexpr,
                     WEIGHTS: tl.constexpr):
    """One tile's intersections' gradients ``d_isect`` (F, M): the centre x, y (pixels), l11,
    l21, l22, opacity, the C values and, with ``WEIGHTS``, the blending weight (the sum of the
    intersection's ``alpha T`` over the tile's pixels). Rows behind every pixel's stop stay as
    they were (zeros)."""
    s0, s1, cx, cy, pxl, pyl, pix = _tile(tile_start, tiles_x, wp, TS)
    ch = tl.arange(0, CB)
    cmask = ch[None, :] < C
    G = tl.load(g_out + ch[None, :] * (hp * wp) + pix[:, None], mask=cmask, other=0.0)
    total = tl.sum(G * tl.load(out + ch[None, :] * (hp * wp) + pix[:, None], mask=cmask, other=0.0), axis=1)
    lim = tl.load(last + pix)
    n_k = tl.minimum(tl.max(lim, axis=0).to(tl.int64), s1 - s0)
    T = tl.full((TS * TS,), 1.0, tl.float32)
    done = tl.zeros((TS * TS,), tl.float32)
    for j in range(0, n_k):
        k = s0 + j
        r, l11, l21, l22, o, dx, dy, p1, p2, g = _falloff(rows, pos, geo, k, cx, cy, pxl, pyl)
        v = tl.load(vals + r * C + ch, mask=ch < C, other=0.0)
        gv = tl.sum(G * v[None, :], axis=1)
        oa = o * g
        alpha = tl.minimum(oa, amax)
        om = 1.0 - alpha
        valid = (j < lim) & (alpha >= amin)
        w = tl.where(valid, alpha * T, 0.0)
        done += w * gv
        d_alpha = tl.where(valid, gv * T - (total - done) / om, 0.0)
        d_oa = tl.where(oa <= amax, d_alpha, 0.0)
        d_q = -0.5 * oa * d_oa
        e1 = d_q * p1
        e2 = d_q * p2
        a0 = tl.sum(e1, axis=0)
        a1 = tl.sum(e2, axis=0)
        tl.store(d_isect + k, -2.0 * l11 * a0)
        tl.store(d_isect + n_isect + k, -2.0 * (l21 * a0 + l22 * a1))
        tl.store(d_isect + 2 * n_isect + k, 2.0 * tl.sum(e1 * dx, axis=0))
        tl.store(d_isect + 3 * n_isect + k, 2.0 * tl.sum(e1 * dy, axis=0))
        tl.store(d_isect + 4 * n_isect + k, 2.0 * tl.sum(e2 * dy, axis=0))
        tl.store(d_isect + 5 * n_isect + k, tl.sum(g * d_oa, axis=0))
        dv = tl.sum(w[:, None] * G, axis=0)
        tl.store(d_isect + (6 + ch) * n_isect + k, dv, mask=ch < C)
        if WEIGHTS:
            tl.store(d_isect + (6 + C) * n_isect + k, tl.sum(w, axis=0))
        T = tl.where(valid, T * om, T)


class TritonKernels:
    """The two compiled (or interpreted) kernels and their launches."""

    def __init__(self, amin: float, amax: float, tmin: float):
        from . import _triton_project
        self._fwd = triton.jit(_forward_kernel)
        self._bwd = triton.jit(_backward_kernel)
        self._proj_fwd = _triton_project._forward_kernel
        self._proj_bwd = _triton_project._backward_kernel
        self._cull = _triton_project._cull_kernel
        self._bin = _triton_project._bin_kernel
        self.interpret = interpreting()
        self.amin, self.amax, self.tmin = float(amin), float(amax), float(tmin)
        self._constants: dict = {}

    def view_arrays(self, vm, K, campos, near: float) -> tuple:
        """The view's float64 arrays on the device the kernels read (viewmat, K, camera centre,
        SH constants, projection constants)."""
        dev = vm.device
        f64 = torch.float64
        key = (float(near), str(dev))
        if key not in self._constants:      # made once: no host-to-device copy a view
            self._constants[key] = (torch.tensor(SH_CONSTANTS, dtype=f64, device=dev),
                                    torch.tensor(kernel_constants(near), dtype=f64, device=dev))
        shc, cst = self._constants[key]
        return (vm.detach().to(f64).contiguous(), K.detach().to(f64).contiguous(),
                campos.detach().to(f64).contiguous(), shc, cst)

    def cull(self, params, view: tuple, width: int, height: int, antialiased: bool) -> torch.Tensor:
        """(N, 14) float64 culling and screen extent of every Gaussian (means, log_scales, quats,
        logits, float32 contiguous; the columns of projection.py's ``_cull_rows``)."""
        n, dev = params[0].shape[0], params[0].device
        info = torch.empty(n, 14, dtype=torch.float64, device=dev)
        if n:
            vm, kk, _campos, _shc, cst = view
            self._cull[(-(-n // _PROJECT_BLOCK),)](*params, vm, kk, cst, info, n, width, height,
                                                   AA=bool(antialiased), BLOCK=_PROJECT_BLOCK)
        return info

    def bin(self, info, ts: int, tiles_x: int, n_tiles: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The binning of the visible rows ``info`` (V, 14) (depth order, :meth:`cull`'s
        columns) into ts x ts tiles: (tile_start (n_tiles + 1,) int64, isect_rows (M,) int32),
        the intersections in (tile, depth) order as numba's binning has them."""
        v, dev = info.shape[0], info.device
        counts = torch.zeros(v, dtype=torch.int64, device=dev)
        grid = (max(1, -(-v // _PROJECT_BLOCK)),)
        none = torch.zeros(1, dtype=torch.int32, device=dev)
        if v:
            self._bin[grid](info, counts, none, none, v, tiles_x, COUNT=True, TS=ts, BLOCK=_PROJECT_BLOCK)
        ends = torch.cumsum(counts, 0)
        m = int(ends[-1]) if v else 0
        tile_of = torch.empty(m, dtype=torch.int32, device=dev)
        row_of = torch.empty(m, dtype=torch.int32, device=dev)
        if m:
            self._bin[grid](info, ends - counts, tile_of, row_of, v, tiles_x, COUNT=False, TS=ts,
                            BLOCK=_PROJECT_BLOCK)
        # rows come in depth order: a stable sort by tile keeps it inside each tile
        tile_sorted, perm = torch.sort(tile_of, stable=True)
        count = torch.bincount(tile_sorted, minlength=n_tiles)
        return torch.cat([count.new_zeros(1), torch.cumsum(count, 0)]), row_of.index_select(0, perm)

    def project_forward(self, rows, deg: int, view: tuple, width: int, height: int, antialiased: bool):
        """Projection and colour of the visible rows (means (V, 3), log_scales (V, 3), quats
        (V, 4), logits (V,), sh (V, K, 3), float32 contiguous): (pos (V, 2) float64, geo (V, 4)
        l11, l21, l22, opacity, depth (V,), colour (V, 3)) float32."""
        means, sh = rows[0], rows[4]
        v, dev = means.shape[0], means.device
        pos = torch.empty(v, 2, dtype=torch.float64, device=dev)
        geo = torch.empty(v, 4, dtype=torch.float32, device=dev)
        depth = torch.empty(v, dtype=torch.float32, device=dev)
        colour = torch.empty(v, 3, dtype=torch.float32, device=dev)
        if v:
            self._proj_fwd[(-(-v // _PROJECT_BLOCK),)](*rows, *view, pos, geo, depth, colour, v, width, height,
                                                       KS=sh.shape[1], DEG=int(deg), AA=bool(antialiased),
                                                       BLOCK=_PROJECT_BLOCK)
        return pos, geo, depth, colour

    def project_backward(self, rows, deg: int, view: tuple, width: int, height: int, antialiased: bool,
                         g_pos, g_geo, g_depth, g_colour):
        """Gradients of :meth:`project_forward`'s outputs back to the rows (float32, their shapes)."""
        means, sh = rows[0], rows[4]
        v = means.shape[0]
        grads = tuple(torch.zeros_like(x) for x in rows)
        if v:
            self._proj_bwd[(-(-v // _PROJECT_BLOCK),)](*rows, *view, g_pos, g_geo, g_depth, g_colour, *grads,
                                                       v, width, height, KS=sh.shape[1], DEG=int(deg),
                                                       AA=bool(antialiased), BLOCK=_PROJECT_BLOCK)
        return grads

    def forward(self, tile_start, rows, pos, geo, vals, ts: int, tiles_x: int, tiles_y: int):
        """(out (C, Hp, Wp) float32, last (Hp, Wp) int32) of every tile. ``pos`` (V, 2)
        float64, ``geo`` (V, 4) float32 (l11, l21, l22, opacity), ``vals`` (V, C) float32,
        ``rows`` (M,) int32 in (tile, depth) order, ``tile_start`` (tiles + 1,) int64."""
        c = vals.shape[1]
        hp, wp = tiles_y * ts, tiles_x * ts
        dev = vals.device
        out = torch.empty(c, hp, wp, dtype=torch.float32, device=dev)
        last = torch.empty(hp, wp, dtype=torch.int32, device=dev)
        self._fwd[(tiles_x * tiles_y,)](tile_start, rows, pos, geo, vals, out, last, tiles_x, hp, wp,
                                        self.amin, self.amax, self.tmin, TS=ts, C=c, CB=_block(c))
        return out, last

    def backward(self, tile_start, rows, pos, geo, vals, ts: int, tiles_x: int, tiles_y: int,
                 out, last, g_out, weights: bool = False):
        """(F, V) gradients per visible row, F = 6 + C (+ 1 with ``weights``): the sums over
        each row's intersections of :func:`_backward_kernel`'s."""
        c = vals.shape[1]
        hp, wp = tiles_y * ts, tiles_x * ts
        m = rows.shape[0]
        f = 6 + c + int(weights)
        d_isect = torch.zeros(f, m, dtype=torch.float32, device=vals.device)
        if m:
            self._bwd[(tiles_x * tiles_y,)](tile_start, rows, pos, geo, vals, out, last, g_out, d_isect, m,
                                            tiles_x, hp, wp, self.amin, self.amax, self.tmin, TS=ts, C=c,
                                            CB=_block(c), WEIGHTS=bool(weights))
        d_rows = torch.zeros(f, vals.shape[0], dtype=torch.float32, device=vals.device)
        d_rows.index_add_(1, rows.to(torch.int64), d_isect)
        return d_rows


def _block(c: int) -> int:
    if c > _MAX_VALUES:
        raise ValueError(f"at most {_MAX_VALUES} values a Gaussian, got {c}")
    return max(2, 1 << (c - 1).bit_length())


def interpreting() -> bool:
    """Whether Triton runs its kernels in its interpreter in this process: ``TRITON_INTERPRET=1``
    in the environment when Triton was first imported (Triton's own reductions are decorated
    then, so a process is one or the other)."""
    if triton is None:
        return False
    knobs = getattr(triton, "knobs", None)   # Triton >= 3.4; older ones read the variable
    if knobs is not None:
        return bool(knobs.runtime.interpret)
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def load(amin: float, amax: float, tmin: float, device: str = "cuda") -> Optional[TritonKernels]:
    """The kernels for tensors on ``device`` (compiled on first use for a CUDA device; CPU
    tensors only in Triton's interpreter, :func:`interpreting`), or None (:func:`error` says
    why: Triton missing, or CPU tensors in a process that compiles)."""
    key = (amin, amax, tmin)
    if triton is None:
        _STATE["error"] = _IMPORT_ERROR
        return None
    if str(device) == "cpu" and not interpreting():
        _STATE["error"] = RuntimeError("Triton's kernels run on CPU tensors only in its interpreter "
                                       "(TRITON_INTERPRET=1 before triton is imported)")
        return None
    if key not in _STATE:
        try:
            _STATE[key] = TritonKernels(amin, amax, tmin)
        except Exception as exc:  # noqa: BLE001 - an incompatible Triton: the eager path stays
            _STATE["error"] = exc
            return None
    return _STATE[key]


def available() -> bool:
    """Whether the GPU kernels can run here: Triton imports and torch sees a CUDA device."""
    return triton is not None and torch.cuda.is_available()


def error() -> Optional[BaseException]:
    """Why :func:`load` gave None (None if it did not)."""
    return _STATE.get("error", _IMPORT_ERROR if triton is None else None)
