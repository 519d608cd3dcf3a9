"""Triton kernels per Gaussian for the GPU path: culling, binning, and projection and SH colour
of the visible rows forward and backward, the twins of numba's (:mod:`._numba_project`: the
same float64 formulas, the SH basis in float32 as model/sh.py evaluates it). One program takes
``BLOCK`` Gaussians; each Gaussian is a lane, so there is nothing to reduce and no atomics.
Used through :class:`.triton_kernels.TritonKernels`; Triton is imported here, once.

Constants come in ``cst`` (float64, ``projection.kernel_constants``: near, dilation, frustum
clamp, alpha_min, quaternion eps^2, AA ratio floor, ...), the viewmat (16), intrinsics (9),
camera centre (3) and SH constants (14: C0, C1, C2[5], C3[7]) as float64 arrays on the device.
"""
from __future__ import annotations

import os

# fused multiply-adds in the kernels (Triton's default so far; saying so silences its warning)
os.environ.setdefault("TRITON_DEFAULT_FP_FUSION", "1")
try:  # Triton: with CUDA builds of torch; on a CPU-only machine only for its interpreter
    import triton
    import triton.language as tl
except Exception as _exc:  # noqa: BLE001 - missing or broken: the eager path stays
    triton, tl, _IMPORT_ERROR = None, None, _exc
else:
    _IMPORT_ERROR = None


def _jit(fn):
    return triton.jit(fn) if triton is not None else fn


@_jit
def _f64(ptr, i, m):
    return tl.load(ptr + i, mask=m, other=0.0).to(tl.float64)


@_jit
def _setup(vm, kk, cst, width, height):
    """The view's numbers as scalars: the viewmat's rows, fx, fy, cx, cy, the frustum limits."""
    v00 = tl.load(vm + 0)
    v01 = tl.load(vm + 1)
    v02 = tl.load(vm + 2)
    v03 = tl.load(vm + 3)
    v10 = tl.load(vm + 4)
    v11 = tl.load(vm + 5)
    v12 = tl.load(vm + 6)
    v13 = tl.load(vm + 7)
    v20 = tl.load(vm + 8)
    v21 = tl.load(vm + 9)
    v22 = tl.load(vm + 10)
    v23 = tl.load(vm + 11)
    fx = tl.load(kk + 0)
    cx = tl.load(kk + 2)
    fy = tl.load(kk + 4)
    cy = tl.load(kk + 5)
    clamp = tl.load(cst + 2)
    limx = clamp * 0.5 * width / fx
    limy = clamp * 0.5 * height / fy
    return v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, fx, fy, cx, cy, limx, limy


@_jit
def _rotation(quats, i, m, qeps2):
    """Rotation matrix (row major) of the quaternion (w, x, y, z) normalised by
    sqrt(|q|^2 + eps^2), the normalised quaternion and the factor."""
    w0 = _f64(quats, 4 * i, m)
    x0 = _f64(quats, 4 * i + 1, m)
    y0 = _f64(quats, 4 * i + 2, m)
    z0 = _f64(quats, 4 * i + 3, m)
    rn = 1.0 / tl.sqrt(w0 * w0 + x0 * x0 + y0 * y0 + z0 * z0 + qeps2)
    w = w0 * rn
    x = x0 * rn
    y = y0 * rn
    z = z0 * rn
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    return r00, r01, r02, r10, r11, r12, r20, r21, r22, w, x, y, z, rn


@_jit
def _sh_basis(x, y, z, shc, DEG: tl.constexpr):
    """INRIA's real SH basis at the float32 direction (x, y, z), as 16 float32 values (those
    beyond ``DEG`` are 0)."""
    zero = tl.zeros_like(x)
    c0 = tl.load(shc + 0).to(tl.float32)
    b0 = zero + c0
    b1 = zero
    b2 = zero
    b3 = zero
    b4 = zero
    b5 = zero
    b6 = zero
    b7 = zero
    b8 = zero
    b9 = zero
    b10 = zero
    b11 = zero
    b12 = zero
    b13 = zero
    b14 = zero
    b15 = zero
    if DEG > 0:
        c1 = tl.load(shc + 1).to(tl.float32)
        b1 = -c1 * y
        b2 = c1 * z
        b3 = -c1 * x
        if DEG > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            b4 = tl.load(shc + 2).to(tl.float32) * (x * y)
            b5 = tl.load(shc + 3).to(tl.float32) * (y * z)
            b6 = tl.load(shc + 4).to(tl.float32) * (2.0 * zz - xx - yy)
            b7 = tl.load(shc + 5).to(tl.float32) * (x * z)
            b8 = tl.load(shc + 6).to(tl.float32) * (xx - yy)
            if DEG > 2:
                b9 = tl.load(shc + 7).to(tl.float32) * y * (3.0 * xx - yy)
                b10 = tl.load(shc + 8).to(tl.float32) * (x * y) * z
                b11 = tl.load(shc + 9).to(tl.float32) * y * (4.0 * zz - xx - yy)
                b12 = tl.load(shc + 10).to(tl.float32) * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                b13 = tl.load(shc + 11).to(tl.float32) * x * (4.0 * zz - xx - yy)
                b14 = tl.load(shc + 12).to(tl.float32) * z * (xx - yy)
                b15 = tl.load(shc + 13).to(tl.float32) * x * (xx - 3.0 * yy)
    return b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15


@_jit
def _direction(means, campos, i, m):
    """The unit direction from the camera centre to the mean (float64) and its length."""
    d0 = _f64(means, 3 * i, m) - tl.load(campos + 0)
    d1 = _f64(means, 3 * i + 1, m) - tl.load(campos + 1)
    d2 = _f64(means, 3 * i + 2, m) - tl.load(campos + 2)
    dn = tl.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    dn = tl.where(m, dn, 1.0)
    return d0 / dn, d1 / dn, d2 / dn, dn


@_jit
def _camera(means, i, m, v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23):
    """Camera-space position of the means (the rows of ``means @ Rw.T + tw``, float64)."""
    m0 = _f64(means, 3 * i, m)
    m1 = _f64(means, 3 * i + 1, m)
    m2 = _f64(means, 3 * i + 2, m)
    x = m0 * v00 + m1 * v01 + m2 * v02 + v03
    y = m0 * v10 + m1 * v11 + m2 * v12 + v13
    z = m0 * v20 + m1 * v21 + m2 * v22 + v23
    return x, y, z


@_jit
def _scales(log_scales, i, m):
    s0 = tl.exp(_f64(log_scales, 3 * i, m))
    s1 = tl.exp(_f64(log_scales, 3 * i + 1, m))
    s2 = tl.exp(_f64(log_scales, 3 * i + 2, m))
    return s0, s1, s2


@_jit
def _ewa(fi0, fi1, xz, yz, v00, v01, v02, v10, v11, v12, v20, v21, v22,
         r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2):
    """EWA projection: e (the rows of J Rw without fx / z, fy / z: e0_k = vm[0, k] - xz
    vm[2, k], e1_k likewise with yz) and the rows a = T M, b (T = J Rw, M = R diag(s))."""
    e00 = v00 - xz * v20
    e01 = v01 - xz * v21
    e02 = v02 - xz * v22
    e10 = v10 - yz * v20
    e11 = v11 - yz * v21
    e12 = v12 - yz * v22
    t00 = fi0 * e00
    t01 = fi0 * e01
    t02 = fi0 * e02
    t10 = fi1 * e10
    t11 = fi1 * e11
    t12 = fi1 * e12
    a0 = (t00 * r00 + t01 * r10 + t02 * r20) * s0
    a1 = (t00 * r01 + t01 * r11 + t02 * r21) * s1
    a2 = (t00 * r02 + t01 * r12 + t02 * r22) * s2
    b0 = (t10 * r00 + t11 * r10 + t12 * r20) * s0
    b1 = (t10 * r01 + t11 * r11 + t12 * r21) * s1
    b2 = (t10 * r02 + t11 * r12 + t12 * r22) * s2
    return e00, e01, e02, e10, e11, e12, a0, a1, a2, b0, b1, b2


@_jit
def _conic(a0, a1, a2, b0, b1, b2, dil):
    """A = a.a, B = a.b, C = b.b, a x b, det0 = |a x b|^2 (no A C - B^2 cancellation) and the
    dilated determinant."""
    A = a0 * a0 + a1 * a1 + a2 * a2
    B = a0 * b0 + a1 * b1 + a2 * b2
    C = b0 * b0 + b1 * b1 + b2 * b2
    c0 = a1 * b2 - a2 * b1
    c1 = a2 * b0 - a0 * b2
    c2 = a0 * b1 - a1 * b0
    det0 = c0 * c0 + c1 * c1 + c2 * c2
    det = det0 + dil * (A + C) + dil * dil
    return A, B, C, c0, c1, c2, det0, det


@_jit
def _sh_raw(row, m, k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13, k14, k15,
            DEG: tl.constexpr):
    """One channel's SH sum (float32, coefficient by coefficient as numba's): ``row`` points at
    the channel's coefficient 0 of each Gaussian (stride 3 between coefficients)."""
    raw = k0 * tl.load(row, mask=m, other=0.0)
    if DEG > 0:
        raw = raw + k1 * tl.load(row + 3, mask=m, other=0.0)
        raw = raw + k2 * tl.load(row + 6, mask=m, other=0.0)
        raw = raw + k3 * tl.load(row + 9, mask=m, other=0.0)
    if DEG > 1:
        raw = raw + k4 * tl.load(row + 12, mask=m, other=0.0)
        raw = raw + k5 * tl.load(row + 15, mask=m, other=0.0)
        raw = raw + k6 * tl.load(row + 18, mask=m, other=0.0)
        raw = raw + k7 * tl.load(row + 21, mask=m, other=0.0)
        raw = raw + k8 * tl.load(row + 24, mask=m, other=0.0)
    if DEG > 2:
        raw = raw + k9 * tl.load(row + 27, mask=m, other=0.0)
        raw = raw + k10 * tl.load(row + 30, mask=m, other=0.0)
        raw = raw + k11 * tl.load(row + 33, mask=m, other=0.0)
        raw = raw + k12 * tl.load(row + 36, mask=m, other=0.0)
        raw = raw + k13 * tl.load(row + 39, mask=m, other=0.0)
        raw = raw + k14 * tl.load(row + 42, mask=m, other=0.0)
        raw = raw + k15 * tl.load(row + 45, mask=m, other=0.0)
    return raw


@_jit
def _forward_kernel(means, log_scales, quats, logits, sh, vm, kk, campos, shc, cst, pos, geo, depth, colour,
                    V, width, height, KS: tl.constexpr, DEG: tl.constexpr, AA: tl.constexpr,
                    BLOCK: tl.constexpr):
    """Rows of the V visible Gaussians: ``pos`` (V, 2) float64 pixel centres; ``geo`` (V, 4)
    float32 l11, l21, l22, opacity; ``depth`` (V,); ``colour`` (V, 3) = max(0, SH(dir) + 0.5).
    ``sh`` (V, KS, 3) float32."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < V
    v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, fx, fy, cx, cy, limx, limy = _setup(
        vm, kk, cst, width, height)
    dil = tl.load(cst + 1)
    x, y, z = _camera(means, i, m, v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23)
    z = tl.where(m, z, 1.0)
    inv_z = 1.0 / z
    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    xz = tl.minimum(tl.maximum(x * inv_z, -limx), limx)
    yz = tl.minimum(tl.maximum(y * inv_z, -limy), limy)
    r00, r01, r02, r10, r11, r12, r20, r21, r22, qw, qx, qy, qz, rn = _rotation(quats, i, m, tl.load(cst + 4))
    s0, s1, s2 = _scales(log_scales, i, m)
    fi0 = fx * inv_z
    fi1 = fy * inv_z
    e00, e01, e02, e10, e11, e12, a0, a1, a2, b0, b1, b2 = _ewa(
        fi0, fi1, xz, yz, v00, v01, v02, v10, v11, v12, v20, v21, v22,
        r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2)
    A, B, C, c0, c1, c2, det0, det = _conic(a0, a1, a2, b0, b1, b2, dil)
    o = 1.0 / (1.0 + tl.exp(-_f64(logits, i, m)))
    if AA:
        o = o * tl.sqrt(tl.maximum(det0 / det, tl.load(cst + 5)))
    sqrt_cd = tl.sqrt(C + dil)
    sqrt_det = tl.sqrt(det)
    tl.store(pos + 2 * i, u, mask=m)
    tl.store(pos + 2 * i + 1, v, mask=m)
    tl.store(geo + 4 * i, (sqrt_cd / sqrt_det).to(tl.float32), mask=m)
    tl.store(geo + 4 * i + 1, (-B / (sqrt_cd * sqrt_det)).to(tl.float32), mask=m)
    tl.store(geo + 4 * i + 2, (1.0 / sqrt_cd).to(tl.float32), mask=m)
    tl.store(geo + 4 * i + 3, o.to(tl.float32), mask=m)
    tl.store(depth + i, z.to(tl.float32), mask=m)
    ux, uy, uz, dn = _direction(means, campos, i, m)
    k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13, k14, k15 = _sh_basis(
        ux.to(tl.float32), uy.to(tl.float32), uz.to(tl.float32), shc, DEG)
    for c in tl.static_range(3):
        raw = _sh_raw(sh + i * (3 * KS) + c, m, k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13,
                      k14, k15, DEG)
        tl.store(colour + 3 * i + c, tl.maximum(raw + 0.5, 0.0), mask=m)


@_jit
def _sh_channel(sh, i, m, c, gr, d_sh, bk, k: tl.constexpr, KS: tl.constexpr):
    """Coefficient k of channel c: its gradient (basis times the raw colour's) stored, and its
    share of the basis' gradient (float64) returned."""
    addr = i * (3 * KS) + 3 * k + c
    tl.store(d_sh + addr, bk * gr, mask=m)
    return gr.to(tl.float64) * tl.load(sh + addr, mask=m, other=0.0).to(tl.float64)


@_jit
def _backward_kernel(means, log_scales, quats, logits, sh, vm, kk, campos, shc, cst,
                     g_pos, g_geo, g_depth, g_colour, d_means, d_log_scales, d_quats, d_logits, d_sh,
                     V, width, height, KS: tl.constexpr, DEG: tl.constexpr, AA: tl.constexpr,
                     BLOCK: tl.constexpr):
    """Gradients of :func:`_forward_kernel`'s outputs back to the rows' parameters (the chain rule
    of projection.py's ``_project_rows`` and model/sh.py written out in float64, as numba's
    ``project_backward``); ``d_sh`` (V, KS, 3) must come in zeroed."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < V
    v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, fx, fy, cx, cy, limx, limy = _setup(
        vm, kk, cst, width, height)
    dil = tl.load(cst + 1)
    aaeps = tl.load(cst + 5)
    x, y, z = _camera(means, i, m, v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23)
    z = tl.where(m, z, 1.0)
    inv_z = 1.0 / z
    xr = x * inv_z
    yr = y * inv_z
    xz = tl.minimum(tl.maximum(xr, -limx), limx)
    yz = tl.minimum(tl.maximum(yr, -limy), limy)
    r00, r01, r02, r10, r11, r12, r20, r21, r22, qw, qx, qy, qz, rn = _rotation(quats, i, m, tl.load(cst + 4))
    s0, s1, s2 = _scales(log_scales, i, m)
    fi0 = fx * inv_z
    fi1 = fy * inv_z
    e00, e01, e02, e10, e11, e12, a0, a1, a2, b0, b1, b2 = _ewa(
        fi0, fi1, xz, yz, v00, v01, v02, v10, v11, v12, v20, v21, v22,
        r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2)
    t00 = fi0 * e00
    t01 = fi0 * e01
    t02 = fi0 * e02
    t10 = fi1 * e10
    t11 = fi1 * e11
    t12 = fi1 * e12
    A, B, C, c0, c1, c2, det0, det = _conic(a0, a1, a2, b0, b1, b2, dil)
    o = 1.0 / (1.0 + tl.exp(-_f64(logits, i, m)))
    sqrt_cd = tl.sqrt(C + dil)
    sqrt_det = tl.sqrt(det)
    g11 = _f64(g_geo, 4 * i, m)
    g21 = _f64(g_geo, 4 * i + 1, m)
    g22 = _f64(g_geo, 4 * i + 2, m)
    go = _f64(g_geo, 4 * i + 3, m)
    # l11 = sqrt_cd / sqrt_det, l21 = -B / (sqrt_cd sqrt_det), l22 = 1 / sqrt_cd
    P = sqrt_cd * sqrt_det
    gB = -g21 / P
    gP = g21 * B / (P * P)
    g_scd = g11 / sqrt_det + gP * sqrt_det - g22 / (sqrt_cd * sqrt_cd)
    g_sdet = -g11 * sqrt_cd / (sqrt_det * sqrt_det) + gP * sqrt_cd
    gC = g_scd * 0.5 / sqrt_cd
    g_det = g_sdet * 0.5 / sqrt_det
    g_det0 = tl.zeros_like(g_det)
    # opacity (sigmoid, times sqrt(max(det0 / det, eps)) when antialiased)
    if AA:
        ratio = det0 / det
        rc = tl.maximum(ratio, aaeps)
        g_sig = go * tl.sqrt(rc)
        g_ratio = tl.where(ratio >= aaeps, go * o * 0.5 / tl.sqrt(rc), 0.0)
        g_det0 = g_det0 + g_ratio / det
        g_det = g_det - g_ratio * det0 / (det * det)
    else:
        g_sig = go
    tl.store(d_logits + i, (g_sig * o * (1.0 - o)).to(tl.float32), mask=m)
    # det = det0 + dil (A + C) + dil^2
    g_det0 = g_det0 + g_det
    gA = dil * g_det
    gC = gC + dil * g_det
    # A = a.a, B = a.b, C = b.b, det0 = |a x b|^2
    gc0 = 2.0 * g_det0 * c0
    gc1 = 2.0 * g_det0 * c1
    gc2 = 2.0 * g_det0 * c2
    ga0 = 2.0 * gA * a0 + gB * b0 + (b1 * gc2 - b2 * gc1)       # ... + b x gc
    ga1 = 2.0 * gA * a1 + gB * b1 + (b2 * gc0 - b0 * gc2)
    ga2 = 2.0 * gA * a2 + gB * b2 + (b0 * gc1 - b1 * gc0)
    gb0 = gB * a0 + 2.0 * gC * b0 + (gc1 * a2 - gc2 * a1)       # ... + gc x a
    gb1 = gB * a1 + 2.0 * gC * b1 + (gc2 * a0 - gc0 * a2)
    gb2 = gB * a2 + 2.0 * gC * b2 + (gc0 * a1 - gc1 * a0)
    # a_j = sum_k t0_k M_kj, b_j = sum_k t1_k M_kj, M = R diag(s)
    # gradient wrt t0_k, t1_k
    gt00 = ga0 * r00 * s0 + ga1 * r01 * s1 + ga2 * r02 * s2
    gt01 = ga0 * r10 * s0 + ga1 * r11 * s1 + ga2 * r12 * s2
    gt02 = ga0 * r20 * s0 + ga1 * r21 * s1 + ga2 * r22 * s2
    gt10 = gb0 * r00 * s0 + gb1 * r01 * s1 + gb2 * r02 * s2
    gt11 = gb0 * r10 * s0 + gb1 * r11 * s1 + gb2 * r12 * s2
    gt12 = gb0 * r20 * s0 + gb1 * r21 * s1 + gb2 * r22 * s2
    # gradient wrt M_kj: t0_k ga_j + t1_k gb_j
    gm00 = t00 * ga0 + t10 * gb0
    gm01 = t00 * ga1 + t10 * gb1
    gm02 = t00 * ga2 + t10 * gb2
    gm10 = t01 * ga0 + t11 * gb0
    gm11 = t01 * ga1 + t11 * gb1
    gm12 = t01 * ga2 + t11 * gb2
    gm20 = t02 * ga0 + t12 * gb0
    gm21 = t02 * ga1 + t12 * gb1
    gm22 = t02 * ga2 + t12 * gb2
    gs0 = gm00 * r00 + gm10 * r10 + gm20 * r20
    gs1 = gm01 * r01 + gm11 * r11 + gm21 * r21
    gs2 = gm02 * r02 + gm12 * r12 + gm22 * r22
    tl.store(d_log_scales + 3 * i, (gs0 * s0).to(tl.float32), mask=m)
    tl.store(d_log_scales + 3 * i + 1, (gs1 * s1).to(tl.float32), mask=m)
    tl.store(d_log_scales + 3 * i + 2, (gs2 * s2).to(tl.float32), mask=m)
    gR00 = gm00 * s0
    gR01 = gm01 * s1
    gR02 = gm02 * s2
    gR10 = gm10 * s0
    gR11 = gm11 * s1
    gR12 = gm12 * s2
    gR20 = gm20 * s0
    gR21 = gm21 * s1
    gR22 = gm22 * s2
    # rotation from the normalised quaternion (qw, qx, qy, qz), then the normalisation
    gw = 2.0 * (-qz * gR01 + qy * gR02 + qz * gR10 - qx * gR12 - qy * gR20 + qx * gR21)
    gx_ = 2.0 * (qy * gR01 + qz * gR02 + qy * gR10 - 2.0 * qx * gR11 - qw * gR12 + qz * gR20 + qw * gR21
                 - 2.0 * qx * gR22)
    gy_ = 2.0 * (-2.0 * qy * gR00 + qx * gR01 + qw * gR02 + qx * gR10 + qz * gR12 - qw * gR20 + qz * gR21
                 - 2.0 * qy * gR22)
    gz_ = 2.0 * (-2.0 * qz * gR00 - qw * gR01 + qx * gR02 + qw * gR10 - 2.0 * qz * gR11 + qy * gR12
                 + qx * gR20 + qy * gR21)
    # q_n = q rn, rn = (|q|^2 + eps^2)^(-1/2): dq = rn (dq_n - q_n (q_n . dq_n))
    dot = qw * gw + qx * gx_ + qy * gy_ + qz * gz_
    tl.store(d_quats + 4 * i, (rn * (gw - qw * dot)).to(tl.float32), mask=m)
    tl.store(d_quats + 4 * i + 1, (rn * (gx_ - qx * dot)).to(tl.float32), mask=m)
    tl.store(d_quats + 4 * i + 2, (rn * (gy_ - qy * dot)).to(tl.float32), mask=m)
    tl.store(d_quats + 4 * i + 3, (rn * (gz_ - qz * dot)).to(tl.float32), mask=m)
    # t0_k = (fx inv_z) e0_k, e0_k = vm[0, k] - xz vm[2, k] (and t1 with fy, yz)
    g_fi0 = gt00 * e00 + gt01 * e01 + gt02 * e02
    g_fi1 = gt10 * e10 + gt11 * e11 + gt12 * e12
    g_xz = -(gt00 * fi0 * v20 + gt01 * fi0 * v21 + gt02 * fi0 * v22)
    g_yz = -(gt10 * fi1 * v20 + gt11 * fi1 * v21 + gt12 * fi1 * v22)
    # screen position, frustum clamp (zero gradient outside), 1/z
    gu = _f64(g_pos, 2 * i, m)
    gv = _f64(g_pos, 2 * i + 1, m)
    g_inv = fx * g_fi0 + fy * g_fi1 + gu * fx * x + gv * fy * y
    gx = gu * fx * inv_z
    gy = gv * fy * inv_z
    inx = (xr >= -limx) & (xr <= limx)
    iny = (yr >= -limy) & (yr <= limy)
    gx = gx + tl.where(inx, g_xz * inv_z, 0.0)
    g_inv = g_inv + tl.where(inx, g_xz * x, 0.0)
    gy = gy + tl.where(iny, g_yz * inv_z, 0.0)
    g_inv = g_inv + tl.where(iny, g_yz * y, 0.0)
    gz = _f64(g_depth, i, m) - g_inv * inv_z * inv_z
    gm0 = gx * v00 + gy * v10 + gz * v20
    gm1 = gx * v01 + gy * v11 + gz * v21
    gm2 = gx * v02 + gy * v12 + gz * v22
    # colour: the clamp at 0, the SH coefficients, then the direction back to the mean
    ux, uy, uz, dn = _direction(means, campos, i, m)
    fxu = ux.to(tl.float32)
    fyu = uy.to(tl.float32)
    fzu = uz.to(tl.float32)
    k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13, k14, k15 = _sh_basis(fxu, fyu, fzu, shc, DEG)
    gb_0 = tl.zeros_like(ux)
    gb_1 = tl.zeros_like(ux)
    gb_2 = tl.zeros_like(ux)
    gb_3 = tl.zeros_like(ux)
    gb_4 = tl.zeros_like(ux)
    gb_5 = tl.zeros_like(ux)
    gb_6 = tl.zeros_like(ux)
    gb_7 = tl.zeros_like(ux)
    gb_8 = tl.zeros_like(ux)
    gb_9 = tl.zeros_like(ux)
    gb_10 = tl.zeros_like(ux)
    gb_11 = tl.zeros_like(ux)
    gb_12 = tl.zeros_like(ux)
    gb_13 = tl.zeros_like(ux)
    gb_14 = tl.zeros_like(ux)
    gb_15 = tl.zeros_like(ux)
    for c in tl.static_range(3):
        raw = _sh_raw(sh + i * (3 * KS) + c, m, k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13,
                      k14, k15, DEG)
        gc = tl.load(g_colour + 3 * i + c, mask=m, other=0.0).to(tl.float32)
        gr = tl.where(raw + 0.5 >= 0.0, gc, 0.0)
        gb_0 = gb_0 + _sh_channel(sh, i, m, c, gr, d_sh, k0, 0, KS)
        if DEG > 0:
            gb_1 = gb_1 + _sh_channel(sh, i, m, c, gr, d_sh, k1, 1, KS)
            gb_2 = gb_2 + _sh_channel(sh, i, m, c, gr, d_sh, k2, 2, KS)
            gb_3 = gb_3 + _sh_channel(sh, i, m, c, gr, d_sh, k3, 3, KS)
        if DEG > 1:
            gb_4 = gb_4 + _sh_channel(sh, i, m, c, gr, d_sh, k4, 4, KS)
            gb_5 = gb_5 + _sh_channel(sh, i, m, c, gr, d_sh, k5, 5, KS)
            gb_6 = gb_6 + _sh_channel(sh, i, m, c, gr, d_sh, k6, 6, KS)
            gb_7 = gb_7 + _sh_channel(sh, i, m, c, gr, d_sh, k7, 7, KS)
            gb_8 = gb_8 + _sh_channel(sh, i, m, c, gr, d_sh, k8, 8, KS)
        if DEG > 2:
            gb_9 = gb_9 + _sh_channel(sh, i, m, c, gr, d_sh, k9, 9, KS)
            gb_10 = gb_10 + _sh_channel(sh, i, m, c, gr, d_sh, k10, 10, KS)
            gb_11 = gb_11 + _sh_channel(sh, i, m, c, gr, d_sh, k11, 11, KS)
            gb_12 = gb_12 + _sh_channel(sh, i, m, c, gr, d_sh, k12, 12, KS)
            gb_13 = gb_13 + _sh_channel(sh, i, m, c, gr, d_sh, k13, 13, KS)
            gb_14 = gb_14 + _sh_channel(sh, i, m, c, gr, d_sh, k14, 14, KS)
            gb_15 = gb_15 + _sh_channel(sh, i, m, c, gr, d_sh, k15, 15, KS)
    # sum_k g_basis[k] grad Y_k at the float32 direction (float64 maths)
    xs = fxu.to(tl.float64)
    ys = fyu.to(tl.float64)
    zs = fzu.to(tl.float64)
    gdx = tl.zeros_like(ux)
    gdy = tl.zeros_like(ux)
    gdz = tl.zeros_like(ux)
    if DEG > 0:
        q1 = tl.load(shc + 1)
        gdy = gdy - q1 * gb_1
        gdz = gdz + q1 * gb_2
        gdx = gdx - q1 * gb_3
    if DEG > 1:
        q2 = tl.load(shc + 2)
        q3 = tl.load(shc + 3)
        q4 = tl.load(shc + 4)
        q5 = tl.load(shc + 5)
        q6 = tl.load(shc + 6)
        gdx = gdx + q2 * ys * gb_4
        gdy = gdy + q2 * xs * gb_4
        gdy = gdy + q3 * zs * gb_5
        gdz = gdz + q3 * ys * gb_5
        gdx = gdx + q4 * -2.0 * xs * gb_6
        gdy = gdy + q4 * -2.0 * ys * gb_6
        gdz = gdz + q4 * 4.0 * zs * gb_6
        gdx = gdx + q5 * zs * gb_7
        gdz = gdz + q5 * xs * gb_7
        gdx = gdx + q6 * 2.0 * xs * gb_8
        gdy = gdy + q6 * -2.0 * ys * gb_8
    if DEG > 2:
        q7 = tl.load(shc + 7)
        q8 = tl.load(shc + 8)
        q9 = tl.load(shc + 9)
        q10 = tl.load(shc + 10)
        q11 = tl.load(shc + 11)
        q12 = tl.load(shc + 12)
        q13 = tl.load(shc + 13)
        xx = xs * xs
        yy = ys * ys
        zz = zs * zs
        gdx = gdx + q7 * 6.0 * xs * ys * gb_9
        gdy = gdy + q7 * (3.0 * xx - 3.0 * yy) * gb_9
        gdx = gdx + q8 * ys * zs * gb_10
        gdy = gdy + q8 * xs * zs * gb_10
        gdz = gdz + q8 * xs * ys * gb_10
        gdx = gdx + q9 * -2.0 * xs * ys * gb_11
        gdy = gdy + q9 * (4.0 * zz - xx - 3.0 * yy) * gb_11
        gdz = gdz + q9 * 8.0 * ys * zs * gb_11
        gdx = gdx + q10 * -6.0 * xs * zs * gb_12
        gdy = gdy + q10 * -6.0 * ys * zs * gb_12
        gdz = gdz + q10 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * gb_12
        gdx = gdx + q11 * (4.0 * zz - 3.0 * xx - yy) * gb_13
        gdy = gdy + q11 * -2.0 * xs * ys * gb_13
        gdz = gdz + q11 * 8.0 * xs * zs * gb_13
        gdx = gdx + q12 * 2.0 * xs * zs * gb_14
        gdy = gdy + q12 * -2.0 * ys * zs * gb_14
        gdz = gdz + q12 * (xx - yy) * gb_14
        gdx = gdx + q13 * (3.0 * xx - 3.0 * yy) * gb_15
        gdy = gdy + q13 * -6.0 * xs * ys * gb_15
    dd = ux * gdx + uy * gdy + uz * gdz
    gm0 = gm0 + (gdx - ux * dd) / dn
    gm1 = gm1 + (gdy - uy * dd) / dn
    gm2 = gm2 + (gdz - uz * dd) / dn
    tl.store(d_means + 3 * i, gm0.to(tl.float32), mask=m)
    tl.store(d_means + 3 * i + 1, gm1.to(tl.float32), mask=m)
    tl.store(d_means + 3 * i + 2, gm2.to(tl.float32), mask=m)


@_jit
def _cull_kernel(means, log_scales, quats, logits, vm, kk, cst, info, N, width, height,
                 AA: tl.constexpr, BLOCK: tl.constexpr):
    """No-grad pass over every Gaussian (projection.py's ``_candidates`` + ``_cull_rows``, as
    numba's ``cull``): ``info`` (N, 14) float64 ok (1 = drawn), z, u, v, A, B, C (dilated 2D
    covariance), D (its determinant), extent, x0, x1, y0, y1 (inclusive pixel range in the
    image), radius; only column 0 is meaningful where it is 0."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < N
    v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, fx, fy, cx, cy, limx, limy = _setup(
        vm, kk, cst, width, height)
    near = tl.load(cst + 0)
    dil = tl.load(cst + 1)
    amin = tl.load(cst + 3)
    mrel = tl.load(cst + 6)
    mabs = tl.load(cst + 7)
    maxr = tl.load(cst + 8)
    x, y, z = _camera(means, i, m, v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23)
    front = m & (z > near)
    z = tl.where(front, z, 1.0)
    inv_z = 1.0 / z
    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    xz = tl.minimum(tl.maximum(x * inv_z, -limx), limx)
    yz = tl.minimum(tl.maximum(y * inv_z, -limy), limy)
    r00, r01, r02, r10, r11, r12, r20, r21, r22, qw, qx, qy, qz, rn = _rotation(quats, i, m, tl.load(cst + 4))
    s0, s1, s2 = _scales(log_scales, i, m)
    fi0 = fx * inv_z
    fi1 = fy * inv_z
    e00, e01, e02, e10, e11, e12, a0, a1, a2, b0, b1, b2 = _ewa(
        fi0, fi1, xz, yz, v00, v01, v02, v10, v11, v12, v20, v21, v22,
        r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2)
    A, B, C, c0, c1, c2, det0, det = _conic(a0, a1, a2, b0, b1, b2, dil)
    o = 1.0 / (1.0 + tl.exp(-_f64(logits, i, m)))
    if AA:
        o = o * tl.sqrt(tl.maximum(det0 / det, tl.load(cst + 5)))
    Ad = A + dil
    Cd = C + dil
    lt = tl.maximum(tl.log(tl.maximum(o, amin) / amin), 0.0)
    ext = (2.0 * lt) * (1.0 + 2.0 * mrel) + mabs
    half_diff = 0.5 * (Ad - Cd)
    lam_max = 0.5 * (Ad + Cd) + tl.sqrt(half_diff * half_diff + B * B)
    r = tl.sqrt(2.0 * lt) * tl.sqrt(lam_max)
    rb = tl.sqrt(ext * lam_max)
    x0 = tl.math.ceil(u - rb - 0.5)
    x1 = tl.math.floor(u + rb - 0.5)
    y0 = tl.math.ceil(v - rb - 0.5)
    y1 = tl.math.floor(v + rb - 0.5)
    w1 = width - 1.0
    h1 = height - 1.0
    ok = front & (o >= amin) & (x1 >= 0) & (x0 <= w1) & (y1 >= 0) & (y0 <= h1)
    ok = ok & (tl.abs(u) < float("inf")) & (tl.abs(v) < float("inf")) & (tl.abs(r) < float("inf"))
    row = info + 14 * i
    tl.store(row, tl.where(ok, 1.0, 0.0), mask=m)
    tl.store(row + 1, z, mask=ok)
    tl.store(row + 2, u, mask=ok)
    tl.store(row + 3, v, mask=ok)
    tl.store(row + 4, Ad, mask=ok)
    tl.store(row + 5, B, mask=ok)
    tl.store(row + 6, Cd, mask=ok)
    tl.store(row + 7, det, mask=ok)
    tl.store(row + 8, ext, mask=ok)
    tl.store(row + 9, tl.minimum(tl.maximum(x0, 0.0), w1), mask=ok)
    tl.store(row + 10, tl.minimum(tl.maximum(x1, 0.0), w1), mask=ok)
    tl.store(row + 11, tl.minimum(tl.maximum(y0, 0.0), h1), mask=ok)
    tl.store(row + 12, tl.minimum(tl.maximum(y1, 0.0), h1), mask=ok)
    tl.store(row + 13, tl.minimum(tl.maximum(r, 0.0), maxr), mask=ok)


@_jit
def _row_span(info, i, m, trow, TS: tl.constexpr):
    """Tile row ``trow`` of Gaussian row i of ``info`` (visible rows, the culling's columns):
    (its first tile column, its number of tiles, 0 if none), the ellipse ``d^T cov^-1 d <=
    extent`` cut to the row's band of pixel-centre y (tiles.py's ``_row_spans``)."""
    row = info + 14 * i
    u = tl.load(row + 2, mask=m, other=0.0)
    v = tl.load(row + 3, mask=m, other=0.0)
    A = tl.load(row + 4, mask=m, other=1.0)
    B = tl.load(row + 5, mask=m, other=0.0)
    C = tl.load(row + 6, mask=m, other=1.0)
    D = tl.load(row + 7, mask=m, other=1.0)
    ext = tl.load(row + 8, mask=m, other=0.0)
    x0 = tl.load(row + 9, mask=m, other=0.0)
    x1 = tl.load(row + 10, mask=m, other=0.0)
    y0 = tl.load(row + 11, mask=m, other=0.0)
    y1 = tl.load(row + 12, mask=m, other=0.0)
    band = (trow * TS).to(tl.float64)
    lo = tl.maximum(band, y0) + 0.5 - v
    hi = tl.minimum(band + (TS - 1), y1) + 0.5 - v
    ylim = tl.sqrt(C * ext)
    empty = (lo > ylim) | (hi < -ylim)
    lo = tl.maximum(tl.minimum(lo, ylim), -ylim)
    hi = tl.minimum(tl.maximum(hi, -ylim), ylim)
    d_ext = B * tl.sqrt(ext / A)
    dl = tl.minimum(tl.maximum(-d_ext, lo), hi)
    dr = tl.minimum(tl.maximum(d_ext, lo), hi)
    xl = (B * dl - tl.sqrt(tl.maximum(D * (C * ext - dl * dl), 0.0))) / C
    xr = (B * dr + tl.sqrt(tl.maximum(D * (C * ext - dr * dr), 0.0))) / C
    i0 = tl.maximum(tl.math.ceil(u + xl - 0.5), x0)
    i1 = tl.minimum(tl.math.floor(u + xr - 0.5), x1)
    none = empty | (i0 > i1) | (i1 < 0.0)
    tx0 = tl.where(none, 0, tl.math.floor(i0 / TS).to(tl.int32))
    ntx = tl.where(none, 0, tl.math.floor(i1 / TS).to(tl.int32) - tx0 + 1)
    return tx0, ntx


@_jit
def _bin_kernel(info, offsets, tile_of, row_of, V, tiles_x, COUNT: tl.constexpr, TS: tl.constexpr,
                BLOCK: tl.constexpr):
    """Binning of the V visible rows (in depth order). ``COUNT``: each row's number of (tile,
    row) intersections into ``offsets`` (V,) int64; else each row writes its intersections, in
    tile-row then column order, from ``offsets`` (the exclusive running sum of the counts) on:
    the tile id into ``tile_of`` (M,) int32 and the row into ``row_of`` (M,) int32."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < V
    ty0 = tl.math.floor(tl.load(info + 14 * i + 11, mask=m, other=0.0) / TS).to(tl.int32)
    ty1 = tl.math.floor(tl.load(info + 14 * i + 12, mask=m, other=0.0) / TS).to(tl.int32)
    nrows = tl.where(m, ty1 - ty0 + 1, 0)
    at = tl.zeros((BLOCK,), tl.int64)
    if not COUNT:
        at = tl.load(offsets + i, mask=m, other=0)
    for r in range(0, tl.max(nrows, 0)):
        active = m & (r < nrows)
        trow = ty0 + r
        tx0, ntx = _row_span(info, i, active, trow, TS)
        ntx = tl.where(active, ntx, 0)
        if not COUNT:
            for j in range(0, tl.max(ntx, 0)):
                put = j < ntx
                tl.store(tile_of + at + j, trow * tiles_x + tx0 + j, mask=put)
                tl.store(row_of + at + j, i, mask=put)
        at = at + ntx
    if COUNT:
        tl.store(offsets + i, at, mask=m)
