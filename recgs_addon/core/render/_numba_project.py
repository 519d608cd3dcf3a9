"""numba kernels per Gaussian: culling and depth order, projection and SH colour (forward and
backward), for :mod:`._numba_impl` (imported through it only, after :mod:`.numba_kernels` has
pointed numba's cache at RecGS's folder)."""
from __future__ import annotations

import numba
import numpy as np

F32 = np.float32


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
