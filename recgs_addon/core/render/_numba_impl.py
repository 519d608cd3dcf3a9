"""numba kernels of the rasterizer (imported by :mod:`.numba_kernels` only, after it has
pointed numba's cache at RecGS's folder: the cache location is fixed when these decorators run).

Every kernel is serial and works on a range of its items (tiles, Gaussians, gradient fields):
:mod:`.numba_kernels` runs the ranges on threads of its own (``nogil``). numba's ``parallel``
mode would do the same with its own pool, but compiles ~2.5x slower (41 against 14 s measured
for all kernels, cold cache), and its OpenMP pool is a second one beside torch's.

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
    """Pixel centres of a tile relative to its centre (as rasterizer._pixel_offsets)."""
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
    ``out``. Replays each pixel's front-to-back pass with the forward's own operations (so it
    sees the forward's alphas, skips and transmittances bit for bit, up to ``last``) and uses
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def gather_rows(f_lo, f_hi, rows, d_isect, d_rows):
    """d_rows[f, rows[k]] += d_isect[f, k] for fields f_lo..f_hi-1, intersections in order (so
    the sums do not depend on how the fields are shared out)."""
    for f in range(f_lo, f_hi):
        for k in range(rows.shape[0]):
            d_rows[f, rows[k]] += d_isect[f, k]


# ----------------------------------------------------------------------------------------
# Per Gaussian: culling, projection, colour (the eager twins are in projection.py and
# model/sh.py; same float64 formulas, written out). Constants come in ``cst`` (float64):
# near, dilation, frustum clamp, alpha_min, quaternion eps^2, AA ratio floor, binning margins
# (relative, absolute), max radius: passed, not frozen, so that a cached kernel can never
# hold stale values of constants defined elsewhere.
# ----------------------------------------------------------------------------------------

_C_NEAR, _C_DIL, _C_CLAMP, _C_AMIN, _C_QEPS2, _C_AAEPS, _C_MREL, _C_MABS, _C_MAXR = range(9)


@numba.njit(error_model="numpy")
def _camera(m0, m1, m2, vm):
    """Camera-space position (the rows of ``means @ Rw.T + tw``)."""
    x = m0 * vm[0, 0] + m1 * vm[0, 1] + m2 * vm[0, 2] + vm[0, 3]
    y = m0 * vm[1, 0] + m1 * vm[1, 1] + m2 * vm[1, 2] + vm[1, 3]
    z = m0 * vm[2, 0] + m1 * vm[2, 1] + m2 * vm[2, 2] + vm[2, 3]
    return x, y, z


@numba.njit(error_model="numpy")
def _rotation(q, qeps2):
    """Rotation matrix of the quaternion (w, x, y, z) normalised by sqrt(|q|^2 + eps^2), and
    that normalised quaternion and the factor."""
    w0 = np.float64(q[0])
    x0 = np.float64(q[1])
    y0 = np.float64(q[2])
    z0 = np.float64(q[3])
    rn = 1.0 / np.sqrt(w0 * w0 + x0 * x0 + y0 * y0 + z0 * z0 + qeps2)
    w = w0 * rn
    x = x0 * rn
    y = y0 * rn
    z = z0 * rn
    R = np.empty((3, 3))
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    return R, w, x, y, z, rn


@numba.njit(error_model="numpy")
def _cov2d(i, means, log_scales, quats, vm, K, width, height, cst, a, b):
    """EWA projection of Gaussian i: fills the rows a = T M, b (T = J Rw, M = R S) and returns
    (x, y, z, u, v, xz_raw, yz_raw, R, s0, s1, s2, w, qx, qy, qz, rn)."""
    fx = K[0, 0]
    fy = K[1, 1]
    x, y, z = _camera(np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2]), vm)
    inv_z = 1.0 / z
    u = fx * x * inv_z + K[0, 2]
    v = fy * y * inv_z + K[1, 2]
    limx = cst[_C_CLAMP] * 0.5 * width / fx
    limy = cst[_C_CLAMP] * 0.5 * height / fy
    xr = x * inv_z
    yr = y * inv_z
    xz = min(max(xr, -limx), limx)
    yz = min(max(yr, -limy), limy)
    R, w, qx, qy, qz, rn = _rotation(quats[i], cst[_C_QEPS2])
    s0 = np.exp(np.float64(log_scales[i, 0]))
    s1 = np.exp(np.float64(log_scales[i, 1]))
    s2 = np.exp(np.float64(log_scales[i, 2]))
    for j in range(3):
        sj = s0 if j == 0 else (s1 if j == 1 else s2)
        aj = 0.0
        bj = 0.0
        for k in range(3):
            t0k = (fx * inv_z) * (vm[0, k] - xz * vm[2, k])
            t1k = (fy * inv_z) * (vm[1, k] - yz * vm[2, k])
            mkj = R[k, j] * sj
            aj += t0k * mkj
            bj += t1k * mkj
        a[j] = aj
        b[j] = bj
    return x, y, z, u, v, xr, yr, R, s0, s1, s2, w, qx, qy, qz, rn


@numba.njit(error_model="numpy")
def _conic(a, b, dil):
    A = a[0] * a[0] + a[1] * a[1] + a[2] * a[2]
    B = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    C = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]
    c0 = a[1] * b[2] - a[2] * b[1]
    c1 = a[2] * b[0] - a[0] * b[2]
    c2 = a[0] * b[1] - a[1] * b[0]
    det0 = c0 * c0 + c1 * c1 + c2 * c2           # |a x b|^2: no A C - B^2 cancellation
    det = det0 + dil * (A + C) + dil * dil
    return A, B, C, det0, det


@numba.njit(error_model="numpy")
def _opacity(logit, det0, det, antialiased, aaeps):
    o = 1.0 / (1.0 + np.exp(-np.float64(logit)))
    if antialiased:
        return o, o * np.sqrt(max(det0 / det, aaeps))
    return o, o


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cull(lo, hi, means, log_scales, quats, logits, vm, K, width, height, antialiased, cst, info):
    """No-grad pass over Gaussians lo..hi-1 (projection.py's ``_candidates`` + ``_cull_rows``).
    Fills ``info`` (N, 14) float64 with ok (1 = drawn), z, u, v, A, B, C (dilated 2D
    covariance), D (its determinant), extent, x0, x1, y0, y1 (inclusive pixel range in the
    image), radius; only column 0 is meaningful where it is 0."""
    fx = K[0, 0]
    fy = K[1, 1]
    near = cst[_C_NEAR]
    dil = cst[_C_DIL]
    amin = cst[_C_AMIN]
    limx = cst[_C_CLAMP] * 0.5 * width / fx
    limy = cst[_C_CLAMP] * 0.5 * height / fy
    jac2 = fx * fx * (1 + limx * limx) + fy * fy * (1 + limy * limy)
    a = np.empty(3)
    b = np.empty(3)
    for i in range(lo, hi):
        info[i, 0] = 0.0
        x, y, z = _camera(np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2]), vm)
        if not z > near:
            continue
        # cheap conservative test first (bound on the largest eigenvalue of cov2d: |J|_F^2
        # max(scale)^2 + dilation, widened by 1 % and a pixel): most of a large model is out
        # of any one view
        smax = max(log_scales[i, 0], max(log_scales[i, 1], log_scales[i, 2]))
        lam = 1.01 * (jac2 / (z * z) * np.exp(2.0 * np.float64(smax)) + dil)
        o = 1.0 / (1.0 + np.exp(-np.float64(logits[i])))
        if not o >= amin * (1 - 1e-9):
            continue
        lt = max(np.log(max(o, amin) / amin), 0.0)
        ext = (2.0 * lt) * (1.0 + 2.0 * cst[_C_MREL]) + cst[_C_MABS]
        rb = np.sqrt(ext * lam) + 1.0
        u = fx * x / z + K[0, 2]
        v = fy * y / z + K[1, 2]
        if u + rb < 0 or u - rb > width or v + rb < 0 or v - rb > height:
            if np.isfinite(u) and np.isfinite(v) and np.isfinite(rb):
                continue
        x, y, z, u, v, xr, yr, R, s0, s1, s2, w, qx, qy, qz, rn = _cov2d(
            i, means, log_scales, quats, vm, K, width, height, cst, a, b)
        A, B, C, det0, det = _conic(a, b, dil)
        o, o_aa = _opacity(logits[i], det0, det, antialiased, cst[_C_AAEPS])
        Ad = A + dil
        Cd = C + dil
        lt = max(np.log(max(o_aa, amin) / amin), 0.0)
        ext = (2.0 * lt) * (1.0 + 2.0 * cst[_C_MREL]) + cst[_C_MABS]
        half_diff = 0.5 * (Ad - Cd)
        lam_max = 0.5 * (Ad + Cd) + np.sqrt(half_diff * half_diff + B * B)
        r = np.sqrt(2.0 * lt) * np.sqrt(lam_max)
        rb = np.sqrt(ext * lam_max)
        x0 = np.ceil(u - rb - 0.5)
        x1 = np.floor(u + rb - 0.5)
        y0 = np.ceil(v - rb - 0.5)
        y1 = np.floor(v + rb - 0.5)
        ok = (o_aa >= amin) and x1 >= 0 and x0 <= width - 1 and y1 >= 0 and y0 <= height - 1
        ok = ok and np.isfinite(u) and np.isfinite(v) and np.isfinite(r)
        if not ok:
            continue
        info[i, 0] = 1.0
        info[i, 1] = z
        info[i, 2] = u
        info[i, 3] = v
        info[i, 4] = Ad
        info[i, 5] = B
        info[i, 6] = Cd
        info[i, 7] = det
        info[i, 8] = ext
        info[i, 9] = min(max(x0, 0.0), width - 1.0)
        info[i, 10] = min(max(x1, 0.0), width - 1.0)
        info[i, 11] = min(max(y0, 0.0), height - 1.0)
        info[i, 12] = min(max(y1, 0.0), height - 1.0)
        info[i, 13] = min(max(r, 0.0), cst[_C_MAXR])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def visible_in_depth_order(info):
    """Indices of the drawn Gaussians sorted by depth (stable: ties by index)."""
    n = info.shape[0]
    cnt = 0
    for i in range(n):
        if info[i, 0] > 0:
            cnt += 1
    ids = np.empty(cnt, np.int64)
    z = np.empty(cnt)
    j = 0
    for i in range(n):
        if info[i, 0] > 0:
            ids[j] = i
            z[j] = info[i, 1]
            j += 1
    return ids[np.argsort(z, kind="mergesort")]


@numba.njit(error_model="numpy")
def _sh_basis(deg, x, y, z, shc, out):
    """INRIA's real SH basis, float32 (as model/sh.py evaluates it); shc = C0, C1, C2[5], C3[7]."""
    out[0] = F32(shc[0])
    if deg > 0:
        out[1] = F32(-shc[1]) * y
        out[2] = F32(shc[1]) * z
        out[3] = F32(-shc[1]) * x
        if deg > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            xy = x * y
            yz = y * z
            xz = x * z
            out[4] = F32(shc[2]) * xy
            out[5] = F32(shc[3]) * yz
            out[6] = F32(shc[4]) * (F32(2.0) * zz - xx - yy)
            out[7] = F32(shc[5]) * xz
            out[8] = F32(shc[6]) * (xx - yy)
            if deg > 2:
                out[9] = F32(shc[7]) * y * (F32(3.0) * xx - yy)
                out[10] = F32(shc[8]) * xy * z
                out[11] = F32(shc[9]) * y * (F32(4.0) * zz - xx - yy)
                out[12] = F32(shc[10]) * z * (F32(2.0) * zz - F32(3.0) * xx - F32(3.0) * yy)
                out[13] = F32(shc[11]) * x * (F32(4.0) * zz - xx - yy)
                out[14] = F32(shc[12]) * z * (xx - yy)
                out[15] = F32(shc[13]) * x * (xx - F32(3.0) * yy)


@numba.njit(error_model="numpy")
def _sh_basis_grad(deg, x, y, z, shc, gb):
    """sum_k gb[k] grad Y_k(x, y, z) (float64)."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    if deg > 0:
        c1 = shc[1]
        gy -= c1 * gb[1]
        gz += c1 * gb[2]
        gx -= c1 * gb[3]
        if deg > 1:
            gx += shc[2] * y * gb[4]
            gy += shc[2] * x * gb[4]
            gy += shc[3] * z * gb[5]
            gz += shc[3] * y * gb[5]
            gx += shc[4] * -2.0 * x * gb[6]
            gy += shc[4] * -2.0 * y * gb[6]
            gz += shc[4] * 4.0 * z * gb[6]
            gx += shc[5] * z * gb[7]
            gz += shc[5] * x * gb[7]
            gx += shc[6] * 2.0 * x * gb[8]
            gy += shc[6] * -2.0 * y * gb[8]
            if deg > 2:
                xx = x * x
                yy = y * y
                zz = z * z
                gx += shc[7] * 6.0 * x * y * gb[9]
                gy += shc[7] * (3.0 * xx - 3.0 * yy) * gb[9]
                gx += shc[8] * y * z * gb[10]
                gy += shc[8] * x * z * gb[10]
                gz += shc[8] * x * y * gb[10]
                gx += shc[9] * -2.0 * x * y * gb[11]
                gy += shc[9] * (4.0 * zz - xx - 3.0 * yy) * gb[11]
                gz += shc[9] * 8.0 * y * z * gb[11]
                gx += shc[10] * -6.0 * x * z * gb[12]
                gy += shc[10] * -6.0 * y * z * gb[12]
                gz += shc[10] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * gb[12]
                gx += shc[11] * (4.0 * zz - 3.0 * xx - yy) * gb[13]
                gy += shc[11] * -2.0 * x * y * gb[13]
                gz += shc[11] * 8.0 * x * z * gb[13]
                gx += shc[12] * 2.0 * x * z * gb[14]
                gy += shc[12] * -2.0 * y * z * gb[14]
                gz += shc[12] * (xx - yy) * gb[14]
                gx += shc[13] * (3.0 * xx - 3.0 * yy) * gb[15]
                gy += shc[13] * -6.0 * x * y * gb[15]
    return gx, gy, gz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def project_forward(lo, hi, means, log_scales, quats, logits, sh, deg, vm, K, campos, width,
                    height, antialiased, cst, shc, pos, geo, depth, colour):
    """The differentiable pass on rows lo..hi-1 of the V visible ones (gathered, depth order): ``pos`` (V, 2)
    float64 pixel centres; float32 ``geo`` (V, 4) l11, l21, l22, opacity; ``depth`` (V,);
    ``colour`` (V, 3) = max(0, SH(dir) + 0.5), dir = unit (mean - camera centre)."""
    nk = (deg + 1) * (deg + 1)
    dil = cst[_C_DIL]
    a = np.empty(3)
    b = np.empty(3)
    basis = np.empty(16, np.float32)
    for i in range(lo, hi):
        x, y, z, u, v, xr, yr, R, s0, s1, s2, w, qx, qy, qz, rn = _cov2d(
            i, means, log_scales, quats, vm, K, width, height, cst, a, b)
        A, B, C, det0, det = _conic(a, b, dil)
        o, o_aa = _opacity(logits[i], det0, det, antialiased, cst[_C_AAEPS])
        sqrt_cd = np.sqrt(C + dil)
        sqrt_det = np.sqrt(det)
        pos[i, 0] = u
        pos[i, 1] = v
        geo[i, 0] = F32(sqrt_cd / sqrt_det)
        geo[i, 1] = F32(-B / (sqrt_cd * sqrt_det))
        geo[i, 2] = F32(1.0 / sqrt_cd)
        geo[i, 3] = F32(o_aa)
        depth[i] = F32(z)
        d0 = np.float64(means[i, 0]) - campos[0]
        d1 = np.float64(means[i, 1]) - campos[1]
        d2 = np.float64(means[i, 2]) - campos[2]
        dn = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        _sh_basis(deg, F32(d0 / dn), F32(d1 / dn), F32(d2 / dn), shc, basis)
        for c in range(3):
            raw = basis[0] * sh[i, 0, c]
            for k in range(1, nk):
                raw = raw + basis[k] * sh[i, k, c]
            colour[i, c] = max(raw + F32(0.5), F32(0.0))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def project_backward(lo, hi, means, log_scales, quats, logits, sh, deg, vm, K, campos, width,
                     height, antialiased, cst, shc, g_pos, g_geo, g_depth, g_colour,
                     d_means, d_log_scales, d_quats, d_logits, d_sh):
    """Gradients of :func:`project_forward`'s outputs back to the rows' parameters (the chain
    rule of projection.py's ``_project_rows`` and model/sh.py, written out in float64;
    ``d_sh`` must come in zeroed)."""
    nk = (deg + 1) * (deg + 1)
    dil = cst[_C_DIL]
    fx = K[0, 0]
    fy = K[1, 1]
    limx = cst[_C_CLAMP] * 0.5 * width / fx
    limy = cst[_C_CLAMP] * 0.5 * height / fy
    a = np.empty(3)
    b = np.empty(3)
    ga = np.empty(3)
    gb = np.empty(3)
    gR = np.empty((3, 3))
    basis = np.empty(16, np.float32)
    g_raw = np.empty(3, np.float32)
    g_basis = np.empty(16)
    for i in range(lo, hi):
        x, y, z, u, v, xr, yr, R, s0, s1, s2, w, qx, qy, qz, rn = _cov2d(
            i, means, log_scales, quats, vm, K, width, height, cst, a, b)
        A, B, C, det0, det = _conic(a, b, dil)
        o, o_aa = _opacity(logits[i], det0, det, antialiased, cst[_C_AAEPS])
        inv_z = 1.0 / z
        Cd = C + dil
        sqrt_cd = np.sqrt(Cd)
        sqrt_det = np.sqrt(det)
        g11 = np.float64(g_geo[i, 0])
        g21 = np.float64(g_geo[i, 1])
        g22 = np.float64(g_geo[i, 2])
        go = np.float64(g_geo[i, 3])
        # l11 = sqrt_cd / sqrt_det, l21 = -B / (sqrt_cd sqrt_det), l22 = 1 / sqrt_cd
        P = sqrt_cd * sqrt_det
        gB = -g21 / P
        gP = g21 * B / (P * P)
        g_scd = g11 / sqrt_det + gP * sqrt_det - g22 / (sqrt_cd * sqrt_cd)
        g_sdet = -g11 * sqrt_cd / (sqrt_det * sqrt_det) + gP * sqrt_cd
        gC = g_scd * 0.5 / sqrt_cd
        g_det = g_sdet * 0.5 / sqrt_det
        g_det0 = 0.0
        # opacity (sigmoid, times sqrt(max(det0 / det, eps)) when antialiased)
        if antialiased:
            ratio = det0 / det
            rc = max(ratio, cst[_C_AAEPS])
            g_sig = go * np.sqrt(rc)
            if ratio >= cst[_C_AAEPS]:
                g_ratio = go * o * 0.5 / np.sqrt(rc)
                g_det0 += g_ratio / det
                g_det -= g_ratio * det0 / (det * det)
        else:
            g_sig = go
        d_logits[i] = F32(g_sig * o * (1.0 - o))
        # det = det0 + dil (A + C) + dil^2
        g_det0 += g_det
        gA = dil * g_det
        gC += dil * g_det
        # A = a.a, B = a.b, C = b.b, det0 = |a x b|^2
        c0 = a[1] * b[2] - a[2] * b[1]
        c1 = a[2] * b[0] - a[0] * b[2]
        c2 = a[0] * b[1] - a[1] * b[0]
        gc0 = 2.0 * g_det0 * c0
        gc1 = 2.0 * g_det0 * c1
        gc2 = 2.0 * g_det0 * c2
        for j in range(3):
            ga[j] = 2.0 * gA * a[j] + gB * b[j]
            gb[j] = gB * a[j] + 2.0 * gC * b[j]
        ga[0] += b[1] * gc2 - b[2] * gc1          # b x gc
        ga[1] += b[2] * gc0 - b[0] * gc2
        ga[2] += b[0] * gc1 - b[1] * gc0
        gb[0] += gc1 * a[2] - gc2 * a[1]          # gc x a
        gb[1] += gc2 * a[0] - gc0 * a[2]
        gb[2] += gc0 * a[1] - gc1 * a[0]
        # a_j = sum_k t0_k M_kj, b_j = sum_k t1_k M_kj, M = R diag(s)
        xz = min(max(xr, -limx), limx)
        yz = min(max(yr, -limy), limy)
        g_fi0 = 0.0                               # wrt fx inv_z and fy inv_z
        g_fi1 = 0.0
        g_xz = 0.0
        g_yz = 0.0
        gs0 = 0.0
        gs1 = 0.0
        gs2 = 0.0
        for k in range(3):
            e0 = vm[0, k] - xz * vm[2, k]
            e1 = vm[1, k] - yz * vm[2, k]
            t0k = (fx * inv_z) * e0
            t1k = (fy * inv_z) * e1
            gt0 = 0.0
            gt1 = 0.0
            for j in range(3):
                sj = s0 if j == 0 else (s1 if j == 1 else s2)
                mkj = R[k, j] * sj
                gt0 += ga[j] * mkj
                gt1 += gb[j] * mkj
                gm = t0k * ga[j] + t1k * gb[j]
                gR[k, j] = gm * sj
                if j == 0:
                    gs0 += gm * R[k, j]
                elif j == 1:
                    gs1 += gm * R[k, j]
                else:
                    gs2 += gm * R[k, j]
            g_fi0 += gt0 * e0
            g_fi1 += gt1 * e1
            g_xz -= gt0 * (fx * inv_z) * vm[2, k]
            g_yz -= gt1 * (fy * inv_z) * vm[2, k]
        d_log_scales[i, 0] = F32(gs0 * s0)
        d_log_scales[i, 1] = F32(gs1 * s1)
        d_log_scales[i, 2] = F32(gs2 * s2)
        # rotation from the normalised quaternion (w, qx, qy, qz), then the normalisation
        gw = 2.0 * (-qz * gR[0, 1] + qy * gR[0, 2] + qz * gR[1, 0] - qx * gR[1, 2]
                    - qy * gR[2, 0] + qx * gR[2, 1])
        gx_ = 2.0 * (qy * gR[0, 1] + qz * gR[0, 2] + qy * gR[1, 0] - 2.0 * qx * gR[1, 1]
                     - w * gR[1, 2] + qz * gR[2, 0] + w * gR[2, 1] - 2.0 * qx * gR[2, 2])
        gy_ = 2.0 * (-2.0 * qy * gR[0, 0] + qx * gR[0, 1] + w * gR[0, 2] + qx * gR[1, 0]
                     + qz * gR[1, 2] - w * gR[2, 0] + qz * gR[2, 1] - 2.0 * qy * gR[2, 2])
        gz_ = 2.0 * (-2.0 * qz * gR[0, 0] - w * gR[0, 1] + qx * gR[0, 2] + w * gR[1, 0]
                     - 2.0 * qz * gR[1, 1] + qy * gR[1, 2] + qx * gR[2, 0] + qy * gR[2, 1])
        # q_n = q rn, rn = (|q|^2 + eps^2)^(-1/2): dq = rn (dq_n - q_n (q_n . dq_n))
        dot = w * gw + qx * gx_ + qy * gy_ + qz * gz_
        d_quats[i, 0] = F32(rn * (gw - w * dot))
        d_quats[i, 1] = F32(rn * (gx_ - qx * dot))
        d_quats[i, 2] = F32(rn * (gy_ - qy * dot))
        d_quats[i, 3] = F32(rn * (gz_ - qz * dot))
        # screen position, frustum clamp (zero gradient outside), 1/z
        gu = np.float64(g_pos[i, 0])
        gv = np.float64(g_pos[i, 1])
        g_inv = fx * g_fi0 + fy * g_fi1 + gu * fx * x + gv * fy * y
        gx = gu * fx * inv_z
        gy = gv * fy * inv_z
        if -limx <= xr <= limx:
            gx += g_xz * inv_z
            g_inv += g_xz * x
        if -limy <= yr <= limy:
            gy += g_yz * inv_z
            g_inv += g_yz * y
        gz = np.float64(g_depth[i]) - g_inv * inv_z * inv_z
        gm0 = gx * vm[0, 0] + gy * vm[1, 0] + gz * vm[2, 0]
        gm1 = gx * vm[0, 1] + gy * vm[1, 1] + gz * vm[2, 1]
        gm2 = gx * vm[0, 2] + gy * vm[1, 2] + gz * vm[2, 2]
        # colour: clamp at 0, SH coefficients, then the direction back to the mean
        d0 = np.float64(means[i, 0]) - campos[0]
        d1 = np.float64(means[i, 1]) - campos[1]
        d2 = np.float64(means[i, 2]) - campos[2]
        dn = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        ux = d0 / dn
        uy = d1 / dn
        uz = d2 / dn
        _sh_basis(deg, F32(ux), F32(uy), F32(uz), shc, basis)
        g_raw[:] = 0.0
        for c in range(3):
            raw = basis[0] * sh[i, 0, c]
            for k in range(1, nk):
                raw = raw + basis[k] * sh[i, k, c]
            if raw + F32(0.5) >= F32(0.0):
                g_raw[c] = g_colour[i, c]
        for k in range(nk):
            gbk = 0.0
            for c in range(3):
                d_sh[i, k, c] = basis[k] * g_raw[c]
                gbk += np.float64(g_raw[c]) * np.float64(sh[i, k, c])
            g_basis[k] = gbk
        gdx, gdy, gdz = _sh_basis_grad(deg, np.float64(F32(ux)), np.float64(F32(uy)),
                                       np.float64(F32(uz)), shc, g_basis)
        dot = ux * gdx + uy * gdy + uz * gdz
        gm0 += (gdx - ux * dot) / dn
        gm1 += (gdy - uy * dot) / dn
        gm2 += (gdz - uz * dot) / dn
        d_means[i, 0] = F32(gm0)
        d_means[i, 1] = F32(gm1)
        d_means[i, 2] = F32(gm2)


# ----------------------------------------------------------------------------------------
# Binning (rasterizer.py's ``_tile_intersections`` + the stable sort by tile, as a counting
# sort: (tile, depth) order, deterministic)
# ----------------------------------------------------------------------------------------

@numba.njit(error_model="numpy")
def _row_span(trow, ts, x0, x1, y0, y1, u, v, A, B, C, D, ext):
    """First tile column and number of tiles of tile row ``trow`` that the ellipse
    d^T cov^-1 d <= ext reaches (exact per row; rasterizer._row_spans)."""
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
    ``counts`` (n_tiles,) (the rows of ``info`` are :func:`cull`'s)."""
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
