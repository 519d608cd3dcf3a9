"""numba kernels over tiles: binning (each visible Gaussian's tiles, as a counting sort by
tile) and compositing (forward and backward), for :mod:`._numba_impl` (imported through it
only, after :mod:`.numba_kernels` has pointed numba's cache at RecGS's folder).

Compositing: inside a tile, the loop over the tile's pixels is the innermost one and has no
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


@numba.njit(inline="always", error_model="numpy")
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


@numba.njit(error_model="numpy")
def _pixel_offsets(ts):
    """Pixel centres of a tile relative to its centre (as tiles._pixel_offsets)."""
    n = ts * ts
    half = 0.5 * ts
    pxl = np.empty(n, np.float32)
    pyl = np.empty(n, np.float32)
    for p in range(n):
        pxl[p] = F32((p % ts) + 0.5 - half)
        pyl[p] = F32((p // ts) + 0.5 - half)
    return pxl, pyl


@numba.njit(cache=True, nogil=True, error_model="numpy")
def composite_forward(t_lo, t_hi, tile_start, rows, pos, geo, vals, ts, tiles_x, amin, amax, tmin,
                      out, last):
    """Front-to-back compositing of tiles t_lo..t_hi-1. Writes ``out`` (C, Hp, Wp), the accumulated
    ``sum_i v_i alpha_i T_i``, and ``last`` (Hp, Wp) int32, the number of entries of its tile's
    list a pixel went through before it stopped (all of them if it never stopped)."""
    n_c = vals.shape[1]
    n_p = ts * ts
    half = 0.5 * ts
    pxl, pyl = _pixel_offsets(ts)
    T = np.empty(n_p, np.float32)
    live = np.empty(n_p, np.float32)
    cnt = np.empty(n_p, np.int32)
    w = np.empty(n_p, np.float32)
    acc = np.empty((n_c, n_p), np.float32)
    for t in range(t_lo, t_hi):
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        cx = tx * ts + half
        cy = ty * ts + half
        T[:] = 1.0
        live[:] = 1.0
        cnt[:] = 0
        acc[:] = 0.0
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def composite_backward(t_lo, t_hi, tile_start, rows, pos, geo, vals, ts, tiles_x, amin, amax, tmin,
                       out, last, g_out, d_isect):
    """Gradients of the intersections of tiles t_lo..t_hi-1, ``d_isect`` (11, M): wrt the centre x, y (pixels),
    l11, l21, l22, opacity and the 5 values, from ``g_out`` (C, Hp, Wp), the gradient wrt
    ``out``; with a twelfth row, also each intersection's blending weight (the sum of its
    ``alpha T`` over the tile's pixels: its share of the pixels, no gradient). Replays each
    pixel's front-to-back pass with the forward's own operations (so it sees the forward's alphas, skips and transmittances bit for bit, up to ``last``) and uses
    ``dC/dalpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) / (1 - alpha_i)``, the sum behind
    being <g_out, out> less the running sum in front (as the eager kernels: total - cumsum)."""
    n_c = vals.shape[1]
    n_p = ts * ts
    half = 0.5 * ts
    pxl, pyl = _pixel_offsets(ts)
    G = np.empty((n_c, n_p), np.float32)
    total = np.empty(n_p, np.float32)
    lim = np.empty(n_p, np.int32)
    T = np.empty(n_p, np.float32)
    done = np.empty(n_p, np.float32)
    gv = np.empty(n_p, np.float32)
    with_weight = d_isect.shape[0] > 11
    for t in range(t_lo, t_hi):
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        if s1 == s0:
            continue
        ty = t // tiles_x
        tx = t - ty * tiles_x
        cx = tx * ts + half
        cy = ty * ts + half
        total[:] = 0.0
        n_k = 0
        for p in range(n_p):
            y = ty * ts + p // ts
            x = tx * ts + p % ts
            lim[p] = last[y, x]
            n_k = max(n_k, last[y, x])
            for c in range(n_c):
                G[c, p] = g_out[c, y, x]
                total[p] += g_out[c, y, x] * out[c, y, x]
        T[:] = 1.0
        done[:] = 0.0
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
            ws = F32(0.0)
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
                ws = _radd(ws, w)
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
            if with_weight:
                d_isect[11, k] = ws
        for k in range(s0 + n_k, s1):                # behind every pixel's stop
            for f in range(d_isect.shape[0]):
                d_isect[f, k] = F32(0.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def gather_rows(f_lo, f_hi, rows, d_isect, d_rows):
    """d_rows[f, rows[k]] += d_isect[f, k] for fields f_lo..f_hi-1, intersections in order (so
    the sums do not depend on how the fields are shared out)."""
    for f in range(f_lo, f_hi):
        for k in range(rows.shape[0]):
            d_rows[f, rows[k]] += d_isect[f, k]


# ----------------------------------------------------------------------------------------
# Binning (tiles.py's ``_tile_intersections`` + the stable sort by tile, as a counting
# sort: (tile, depth) order, deterministic)
# ----------------------------------------------------------------------------------------

@numba.njit(error_model="numpy")
def _row_span(trow, ts, x0, x1, y0, y1, u, v, A, B, C, D, ext):
    """First tile column and number of tiles of tile row ``trow`` that the ellipse
    d^T cov^-1 d <= ext reaches (exact per row; tiles._row_spans)."""
    lo = np.float64(max(trow * ts, y0)) + 0.5 - v
    hi = np.float64(min(trow * ts + ts - 1, y1)) + 0.5 - v
    ylim = np.sqrt(C * ext)
    empty = (lo > ylim) or (hi < -ylim)
    lo = max(min(lo, ylim), -ylim)
    hi = min(max(hi, -ylim), ylim)
    d_ext = B * np.sqrt(ext / A)
    dl = min(max(-d_ext, lo), hi)
    dr = min(max(d_ext, lo), hi)
    xl = (B * dl - np.sqrt(max(D * (C * ext - dl * dl), 0.0))) / C
    xr = (B * dr + np.sqrt(max(D * (C * ext - dr * dr), 0.0))) / C
    i0 = max(np.int64(np.ceil(u + xl - 0.5)), x0)
    i1 = min(np.int64(np.floor(u + xr - 0.5)), x1)
    tx0 = i0 // ts
    if empty or i0 > i1:
        return tx0, 0
    return tx0, i1 // ts - tx0 + 1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def bin_count(lo, hi, info, ids, ts, tiles_x, counts):
    """Intersections per tile of the visible Gaussians ids[lo:hi] (depth order), added to
    ``counts`` (n_tiles,) (the rows of ``info`` are :func:`._numba_project.cull`'s)."""
    for r in range(lo, hi):
        i = ids[r]
        x0 = np.int64(info[i, 9])
        x1 = np.int64(info[i, 10])
        y0 = np.int64(info[i, 11])
        y1 = np.int64(info[i, 12])
        for trow in range(y0 // ts, y1 // ts + 1):
            tx0, ntx = _row_span(trow, ts, x0, x1, y0, y1, info[i, 2], info[i, 3], info[i, 4],
                                 info[i, 5], info[i, 6], info[i, 7], info[i, 8])
            for j in range(ntx):
                counts[trow * tiles_x + tx0 + j] += 1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def bin_offsets(counts, tile_start):
    """Turn per-part counts (n_parts, n_tiles) into each part's first slot in every tile
    (tile-major, then part: the parts are consecutive runs of the depth order) and fill
    ``tile_start`` (n_tiles + 1,)."""
    n_parts, n_tiles = counts.shape
    tile_start[0] = 0
    for t in range(n_tiles):
        s = tile_start[t]
        for part in range(n_parts):
            c = counts[part, t]
            counts[part, t] = s
            s += c
        tile_start[t + 1] = s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def bin_fill(lo, hi, info, ids, ts, tiles_x, slots, rows):
    """Write r into ``rows`` at the next free slot of each tile that visible Gaussian ids[r]
    reaches, r = lo..hi-1 in depth order (``slots``: this part's row of :func:`bin_offsets`):
    a counting sort, stable, so each tile's list is in depth order."""
    for r in range(lo, hi):
        i = ids[r]
        x0 = np.int64(info[i, 9])
        x1 = np.int64(info[i, 10])
        y0 = np.int64(info[i, 11])
        y1 = np.int64(info[i, 12])
        for trow in range(y0 // ts, y1 // ts + 1):
            tx0, ntx = _row_span(trow, ts, x0, x1, y0, y1, info[i, 2], info[i, 3], info[i, 4],
                                 info[i, 5], info[i, 6], info[i, 7], info[i, 8])
            for j in range(ntx):
                t = trow * tiles_x + tx0 + j
                rows[slots[t]] = r
                slots[t] += 1
