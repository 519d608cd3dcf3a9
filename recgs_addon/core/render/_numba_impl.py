"""numba kernels of the compositing step (imported by :mod:`.numba_kernels` only, after it has
pointed numba's cache at RecGS's folder: the cache location is fixed when these decorators run).

One call composites every tile of a view (tiles in parallel, ``prange``), one call computes
every gradient. Inside a tile, the loop over the tile's pixels is the innermost one and has no
branches, so LLVM turns it into SIMD code (16 pixels of a 4x4 tile = one AVX-512 register, two
AVX2 ones); ``_exp`` is written out for the same reason (a call to libm's ``expf`` cannot be
vectorised, and numba only vectorises it where Intel's SVML happens to be installed).

Layout: a view's (tile, Gaussian) intersections sorted by tile, in depth order inside a tile
(``tile_start`` (n_tiles + 1,) offsets into ``rows`` (M,), the visible row of each), per visible
row ``pos`` (V, 2) float64 pixel centres, ``geo`` (V, 4) float32 (l11, l21, l22, opacity) and
``vals`` (V, C) float32 (C = 5 in the backward: rgb, depth, 1); images are planar (C, Hp, Wp)
with Hp, Wp the tile-padded size.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import prange

F32 = np.float32
_LOG2E = F32(1.4426950408889634)
_LN2_HI = F32(0.693359375)         # ln 2 = _LN2_HI + _LN2_LO, _LN2_HI exact in 9 bits
_LN2_LO = F32(-2.12194440e-4)
# Cephes' expf polynomial for exp(r) - 1 - r on [-ln2/2, ln2/2]
_P0 = F32(1.9875691500e-4)
_P1 = F32(1.3981999507e-3)
_P2 = F32(8.3334519073e-3)
_P3 = F32(4.1665795894e-2)
_P4 = F32(1.6666665459e-1)
_P5 = F32(5.0000001201e-1)


@numba.njit(inline="always")
def _exp(x):
    """exp(x) for float32 x <= 0, within 1 ulp (x < -87 gives exp(-87), which is < 1/255 like
    the true value; the rasterizer only asks for x = -q/2 <= 0). Branch-free: vectorisable."""
    x = max(x, F32(-87.0))
    z = np.floor(x * _LOG2E + F32(0.5))
    r = (x - z * _LN2_HI) - z * _LN2_LO
    p = ((((_P0 * r + _P1) * r + _P2) * r + _P3) * r + _P4) * r + _P5
    y = (p * r) * r + r + F32(1.0)
    return y * np.int32((np.int32(z) + np.int32(127)) << 23).view(np.float32)


@numba.njit(fastmath={"reassoc", "nsz"})
def _radd(s, x):
    """s + x, the one operation LLVM may reorder: a sum over a tile's pixels written with it is
    vectorised (one accumulator per SIMD lane, added up at the end). Not inlined by numba, so
    that the flags stay on this addition alone (LLVM inlines it and keeps them)."""
    return s + x


@numba.njit(inline="always")
def _pixel_offsets(ts):
    """Pixel centres of a tile relative to its centre (as rasterizer._pixel_offsets)."""
    n = ts * ts
    half = 0.5 * ts
    pxl = np.empty(n, np.float32)
    pyl = np.empty(n, np.float32)
    for p in range(n):
        pxl[p] = F32((p % ts) + 0.5 - half)
        pyl[p] = F32((p // ts) + 0.5 - half)
    return pxl, pyl


@numba.njit(parallel=True, cache=True, nogil=True)
def composite_forward(tile_start, rows, pos, geo, vals, ts, tiles_x, amin, amax, tmin, out, last):
    """Front-to-back compositing of every tile. Writes ``out`` (C, Hp, Wp), the accumulated
    ``sum_i v_i alpha_i T_i``, and ``last`` (Hp, Wp) int32, the number of entries of its tile's
    list a pixel went through before it stopped (all of them if it never stopped)."""
    n_tiles = tile_start.shape[0] - 1
    n_c = vals.shape[1]
    n_p = ts * ts
    half = 0.5 * ts
    pxl, pyl = _pixel_offsets(ts)
    for t in prange(n_tiles):
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        cx = tx * ts + half
        cy = ty * ts + half
        T = np.ones(n_p, np.float32)
        live = np.ones(n_p, np.float32)
        cnt = np.zeros(n_p, np.int32)
        w = np.empty(n_p, np.float32)
        acc = np.zeros((n_c, n_p), np.float32)
        for k in range(s0, s1):
            r = rows[k]
            # centre relative to the tile centre: subtracted in float64, then rounded
            mx = F32(pos[r, 0] - cx)
            my = F32(pos[r, 1] - cy)
            l11 = geo[r, 0]
            l21 = geo[r, 1]
            l22 = geo[r, 2]
            o = geo[r, 3]
            n_live = 0
            for p in range(n_p):
                dx = pxl[p] - mx
                dy = pyl[p] - my
                p1 = l11 * dx + l21 * dy
                p2 = l22 * dy
                g = _exp(F32(-0.5) * (p1 * p1 + p2 * p2))
                alpha = min(o * g, amax)
                t_p = T[p]
                t_next = t_p * (F32(1.0) - alpha)
                keep = (alpha >= amin) & (live[p] > F32(0.0))
                # the stop: T would fall below tmin; this Gaussian is not added
                stop = keep & (t_next < tmin)
                use = keep & (t_next >= tmin)
                w[p] = alpha * t_p if use else F32(0.0)
                T[p] = t_next if use else t_p
                lv = F32(0.0) if stop else live[p]
                live[p] = lv
                cnt[p] += np.int32(lv > F32(0.0))
                n_live += np.int32(lv > F32(0.0))
            for c in range(n_c):
                v = vals[r, c]
                for p in range(n_p):
                    acc[c, p] += w[p] * v
            if n_live == 0:
                break
        for p in range(n_p):
            y = ty * ts + p // ts
            x = tx * ts + p % ts
            for c in range(n_c):
                out[c, y, x] = acc[c, p]
            last[y, x] = cnt[p]


@numba.njit(parallel=True, cache=True, nogil=True)
def composite_backward(tile_start, rows, pos, geo, vals, ts, tiles_x, amin, amax, tmin, out, last,
                       g_out, d_isect):
    """Gradients of every intersection, ``d_isect`` (11, M): wrt the centre x, y (pixels),
    l11, l21, l22, opacity and the 5 values, from ``g_out`` (C, Hp, Wp), the gradient wrt
    ``out``. Replays each pixel's front-to-back pass with the forward's own operations (so it
    sees the forward's alphas, skips and transmittances bit for bit, up to ``last``) and uses
    ``dC/dalpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) / (1 - alpha_i)``, the sum behind
    being <g_out, out> less the running sum in front (as the eager kernels: total - cumsum)."""
    n_tiles = tile_start.shape[0] - 1
    n_c = vals.shape[1]
    n_p = ts * ts
    half = 0.5 * ts
    pxl, pyl = _pixel_offsets(ts)
    for t in prange(n_tiles):
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        if s1 == s0:
            continue
        ty = t // tiles_x
        tx = t - ty * tiles_x
        cx = tx * ts + half
        cy = ty * ts + half
        G = np.empty((n_c, n_p), np.float32)
        total = np.zeros(n_p, np.float32)
        lim = np.empty(n_p, np.int32)
        n_k = 0
        for p in range(n_p):
            y = ty * ts + p // ts
            x = tx * ts + p % ts
            lim[p] = last[y, x]
            n_k = max(n_k, last[y, x])
            for c in range(n_c):
                G[c, p] = g_out[c, y, x]
                total[p] += g_out[c, y, x] * out[c, y, x]
        T = np.ones(n_p, np.float32)
        done = np.zeros(n_p, np.float32)
        gv = np.empty(n_p, np.float32)
        for j in range(n_k):
            k = s0 + j
            r = rows[k]
            mx = F32(pos[r, 0] - cx)
            my = F32(pos[r, 1] - cy)
            l11 = geo[r, 0]
            l21 = geo[r, 1]
            l22 = geo[r, 2]
            o = geo[r, 3]
            for p in range(n_p):                     # <dL/dout_p, v_i>
                gv[p] = F32(0.0)
            for c in range(n_c):
                v = vals[r, c]
                for p in range(n_p):
                    gv[p] += v * G[c, p]
            # sums over the tile's pixels: geometry (a0..a5) and the 5 values (c0..c4)
            a0 = a1 = a2 = a3 = a4 = a5 = F32(0.0)
            c0 = c1 = c2 = c3 = c4 = F32(0.0)
            for p in range(n_p):
                dx = pxl[p] - mx
                dy = pyl[p] - my
                p1 = l11 * dx + l21 * dy
                p2 = l22 * dy
                g = _exp(F32(-0.5) * (p1 * p1 + p2 * p2))
                oa = o * g
                alpha = min(oa, amax)
                om = F32(1.0) - alpha                # >= 0.01
                valid = (j < lim[p]) & (alpha >= amin)
                t_p = T[p]
                w = alpha * t_p if valid else F32(0.0)
                dn = done[p] + w * gv[p]
                done[p] = dn
                d_alpha = gv[p] * t_p - (total[p] - dn) / om if valid else F32(0.0)
                # alpha = min(amax, o g): no gradient to o or g where the clamp is active
                d_oa = d_alpha if oa <= amax else F32(0.0)
                d_q = F32(-0.5) * oa * d_oa          # q = p1^2 + p2^2, g = exp(-q/2)
                e1 = d_q * p1
                e2 = d_q * p2
                a0 = _radd(a0, e1)
                a1 = _radd(a1, e2)
                a2 = _radd(a2, e1 * dx)
                a3 = _radd(a3, e1 * dy)
                a4 = _radd(a4, e2 * dy)
                a5 = _radd(a5, g * d_oa)
                c0 = _radd(c0, w * G[0, p])
                c1 = _radd(c1, w * G[1, p])
                c2 = _radd(c2, w * G[2, p])
                c3 = _radd(c3, w * G[3, p])
                c4 = _radd(c4, w * G[4, p])
                T[p] = t_p * om if valid else t_p
            d_isect[0, k] = F32(-2.0) * l11 * a0                  # centre x (dx = px - mx)
            d_isect[1, k] = F32(-2.0) * (l21 * a0 + l22 * a1)    # centre y
            d_isect[2, k] = F32(2.0) * a2                         # l11
            d_isect[3, k] = F32(2.0) * a3                         # l21
            d_isect[4, k] = F32(2.0) * a4                         # l22
            d_isect[5, k] = a5                                    # opacity
            d_isect[6, k] = c0
            d_isect[7, k] = c1
            d_isect[8, k] = c2
            d_isect[9, k] = c3
            d_isect[10, k] = c4
        for k in range(s0 + n_k, s1):                # behind every pixel's stop
            for f in range(d_isect.shape[0]):
                d_isect[f, k] = F32(0.0)


@numba.njit(parallel=True, cache=True, nogil=True)
def gather_rows(rows, d_isect, d_rows):
    """d_rows[f, rows[k]] += d_isect[f, k]: fields in parallel, intersections in order (so the
    sums do not depend on the thread count)."""
    for f in prange(d_isect.shape[0]):
        for k in range(rows.shape[0]):
            d_rows[f, rows[k]] += d_isect[f, k]
