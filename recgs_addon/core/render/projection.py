"""Per-Gaussian part of the renderer: 3D Gaussians -> screen-space ellipses (INRIA 3DGS maths).

Everything here is per Gaussian (no pixels), runs in float64 whatever the parameter dtype
(the cost is small next to the per-pixel compositing, and it keeps the 2D covariance of a
1e5:1 needle or a 1e3 m blob accurate), and is differentiated by torch autograd.

Conventions are those of :mod:`recgs_addon.core.model.cameras`: ``viewmat`` is world-to-camera with
OpenCV axes (x right, y down, z forward); pixel (i, j) is centred at (i + 0.5, j + 0.5) in the
coordinates ``u = fx x / z + cx``.

Screen-space ellipses are handed to the compositor as the Cholesky factor of the conic
(inverse 2D covariance) instead of the conic itself: with ``cov2d = [[A, B], [B, C]]``
(dilated) and ``D = det(cov2d)``, the Mahalanobis distance is

    d^T cov2d^-1 d = (l11 dx + l21 dy)^2 + (l22 dy)^2,
    l11 = sqrt(C / D),  l21 = -B / sqrt(C D),  l22 = 1 / sqrt(C).

This is the same number as INRIA's ``conic.x dx^2 + 2 conic.y dx dy + conic.z dy^2`` but is
evaluated without the quadratic cancellation that makes float32 lose the shape of very
elongated Gaussians, and is smooth everywhere (C >= 0.3, D >= 0.09 thanks to the dilation).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

#: Low-pass dilation added to the 2D covariance (pixels^2), INRIA/EWA: every splat covers at
#: least about one pixel, so that sub-pixel Gaussians do not alias.
COV2D_DILATION = 0.3
#: INRIA clamps x/z and y/z in the projection Jacobian to 1.3 x tan(fov/2): Gaussians far
#: outside the frustum would otherwise get absurdly stretched screen footprints.
FRUSTUM_CLAMP = 1.3
#: Contributions with alpha below this are skipped (8-bit colour resolution), INRIA.
ALPHA_MIN = 1.0 / 255.0
#: Quaternions are normalised by sqrt(|q|^2 + QUAT_EPS^2) (in float64): smooth everywhere
#: (finite gradients even for q = 0, which gives the identity) and equal to q / |q| to 1e-10
#: relative for |q| >= 1e-15.
QUAT_EPS = 1e-20
#: Floor for det(cov)/det(cov + 0.3 I) under the square root of the antialiasing factor
#: (d sqrt(x)/dx is infinite at 0).
AA_RATIO_EPS = 1e-30
#: Relative and absolute margins added to the opacity-aware radius before binning into tiles,
#: so that float32 round-off in the compositor can never see a pixel the binning left out.
BIN_MARGIN_REL = 1e-4
BIN_MARGIN_ABS = 1e-3
#: Largest radius reported (pixels); keeps the int32 cast finite for absurd Gaussians.
MAX_RADIUS = 2 ** 30


class Projection(NamedTuple):
    """Screen-space Gaussians that survived culling, in compositing (depth) order.

    Attributes:
        ids: (V,) int64 indices of visible Gaussians, sorted by camera-space depth, ties broken
            by index (stable), so the order is deterministic.
        means2d: (V, 2) float64 pixel coordinates of the projected centres (differentiable).
        chol: (V, 3) float64 (l11, l21, l22), Cholesky factor of the conic (differentiable).
        opacity: (V,) float64 opacity in (0, 1), times the antialiasing factor (differentiable).
        depth: (V,) float64 camera-space z in scene units (differentiable).
        radii: (N,) int32 opacity-aware screen radius in pixels for every Gaussian, 0 = culled.
        bbox: (V, 4) int64 inclusive pixel ranges (x0, x1, y0, y1) inside the image that can
            receive alpha >= 1/255 from the Gaussian (with a safety margin).
        cov2d: (V, 4) float64 dilated 2D covariance (A, B, C) = ([0,0], [0,1], [1,1]) and its
            determinant D (computed without cancellation), detached.
        extent: (V,) float64 squared Mahalanobis radius of the drawn region, 2 ln(255 o) plus
            the binning margin, detached (pixels with d^T cov2d^-1 d > extent get alpha < 1/255).
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    chol: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    radii: torch.Tensor
    bbox: torch.Tensor
    cov2d: torch.Tensor
    extent: torch.Tensor


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices.

    Normalised by sqrt(|q|^2 + QUAT_EPS^2); a zero quaternion gives the identity (finite
    gradients).
    """
    q = quats * torch.rsqrt((quats * quats).sum(-1, keepdim=True) + QUAT_EPS ** 2)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(quats.shape[:-1] + (3, 3))


def _project_rows(means, log_scales, quats, logit_opacities, viewmat, K, width, height, near,
                  antialiased, extras=False):
    """Float64 EWA projection of some Gaussians. Returns a dict of (n,)-shaped tensors.

    Rows with z <= near get a harmless stand-in depth so that no inf/NaN enters the graph;
    the caller culls them via ``in_front``. ``extras`` adds lam_max and the 2D covariance
    (A, B, C, D) for culling and binning: only for the no-grad pass (sqrt(0) in lam_max of a
    round Gaussian has no finite derivative, and a compiled backward differentiates every
    output, used or not).
    """
    Rw = viewmat[:3, :3]
    tw = viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pc = means @ Rw.T + tw
    x, y, z = pc.unbind(-1)
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))
    inv_z = 1.0 / zs
    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    # Jacobian of the perspective projection at the (frustum-clamped) centre, INRIA style:
    # limits from tan(fov/2) = 0.5 W / fx; clamping x/z (zero gradient outside) then
    # multiplying by z is the same as clamping x/z directly.
    limx = FRUSTUM_CLAMP * 0.5 * width / fx
    limy = FRUSTUM_CLAMP * 0.5 * height / fy
    xz = torch.clamp(x * inv_z, -limx, limx)
    yz = torch.clamp(y * inv_z, -limy, limy)
    # T = J @ Rw, rows (2, 3): J = [[fx/z, 0, -fx xz/z], [0, fy/z, -fy yz/z]]
    t0 = (fx * inv_z)[:, None] * (Rw[0] - xz[:, None] * Rw[2])
    t1 = (fy * inv_z)[:, None] * (Rw[1] - yz[:, None] * Rw[2])
    # Sigma = M M^T with M = R(q) diag(exp(s)); cov2d = (T M)(T M)^T.
    M = quat_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]
    # (T M) rows as broadcast sums (fuses under torch.compile; a batched 1x3 @ 3x3 does not).
    a_row = (t0.unsqueeze(-1) * M).sum(1)
    b_row = (t1.unsqueeze(-1) * M).sum(1)
    A = (a_row * a_row).sum(-1)
    B = (a_row * b_row).sum(-1)
    C = (b_row * b_row).sum(-1)
    # det(cov2d) before dilation as |a x b|^2 (Lagrange identity): >= 0 by construction and
    # free of the A C - B^2 cancellation for needle-like Gaussians.
    det0 = (torch.linalg.cross(a_row, b_row) ** 2).sum(-1)
    Ad = A + COV2D_DILATION
    Cd = C + COV2D_DILATION
    det = det0 + COV2D_DILATION * (A + C) + COV2D_DILATION ** 2
    opacity = torch.sigmoid(logit_opacities)
    if antialiased:
        # Mip-Splatting / gsplat "antialiased": keep the splat's integrated energy.
        opacity = opacity * torch.sqrt(torch.clamp_min(det0 / det, AA_RATIO_EPS))
    sqrt_cd = torch.sqrt(Cd)
    sqrt_det = torch.sqrt(det)
    l11 = sqrt_cd / sqrt_det
    l21 = -B / (sqrt_cd * sqrt_det)
    l22 = 1.0 / sqrt_cd
    out = dict(in_front=in_front, z=zs, u=u, v=v, l11=l11, l21=l21, l22=l22, opacity=opacity)
    if extras:
        half_diff = 0.5 * (Ad - Cd)
        lam_max = 0.5 * (Ad + Cd) + torch.sqrt(half_diff * half_diff + B * B)
        out.update(lam_max=lam_max, A=Ad, B=B, C=Cd, D=det)
    return out


def _draw_extent(opacity):
    """(log_term, extent) per Gaussian: ``o exp(-r^2 / (2 lambda)) = 1/255`` at
    ``r^2 = 2 log_term lambda`` (opacity-aware radius), and the squared Mahalanobis radius that
    binning uses, slightly larger (never smaller than what float32 can draw)."""
    log_term = torch.clamp_min(torch.log(torch.clamp_min(opacity, ALPHA_MIN) / ALPHA_MIN), 0.0)
    return log_term, (2.0 * log_term) * (1.0 + 2.0 * BIN_MARGIN_REL) + BIN_MARGIN_ABS


def _cull_rows(means, log_scales, quats, logit_opacities, viewmat, K, width, height, near,
               antialiased):
    """No-grad first pass over all Gaussians: projection, culling and screen extent.

    Returns (N, 14) float64 columns: ok (1 = drawn), z, u, v, A, B, C, D (dilated cov2d and
    its determinant), extent (binning threshold on d^T cov^-1 d), x0, x1, y0, y1 (inclusive
    pixel range, clipped to the image), radius (opacity-aware, pixels, exact).
    """
    p = _project_rows(means, log_scales, quats, logit_opacities, viewmat, K, width, height,
                      near, antialiased, extras=True)
    o = p["opacity"]
    log_term, extent = _draw_extent(o)
    r = torch.sqrt(2.0 * log_term) * torch.sqrt(p["lam_max"])
    rb = torch.sqrt(extent * p["lam_max"])
    # Pixel (i, j) is centred at (i + 0.5, j + 0.5).
    x0 = torch.ceil(p["u"] - rb - 0.5)
    x1 = torch.floor(p["u"] + rb - 0.5)
    y0 = torch.ceil(p["v"] - rb - 0.5)
    y1 = torch.floor(p["v"] + rb - 0.5)
    ok = p["in_front"] & (o >= ALPHA_MIN)
    ok = ok & (x1 >= 0) & (x0 <= width - 1) & (y1 >= 0) & (y0 <= height - 1)
    ok = ok & torch.isfinite(p["u"]) & torch.isfinite(p["v"]) & torch.isfinite(r)
    return torch.stack([
        ok.to(means.dtype), p["z"], p["u"], p["v"], p["A"], p["B"], p["C"], p["D"], extent,
        torch.clamp(x0, 0, width - 1), torch.clamp(x1, 0, width - 1),
        torch.clamp(y0, 0, height - 1), torch.clamp(y1, 0, height - 1),
        torch.clamp(r, 0.0, MAX_RADIUS)], dim=1)


def _candidates(means, log_scales, logit_opacities, viewmat, K, width, height, near):
    """(N,) bool: the Gaussians that may be visible, by a cheap conservative test (no grad).

    A model of a million Gaussians has most of them outside any one view; the full cull pass
    (rotation matrices, 2D covariance, eigenvalues) is run only on these. The test bounds the
    2D covariance's largest eigenvalue by ``|J|_F^2 max(scale)^2 + dilation`` (J: the
    projection Jacobian with INRIA's frustum clamp; the view rotation and the Gaussian's
    rotation have norm 1), which is never below the exact one, and it widens that bound by
    1 % and the screen rectangle by a pixel, so it never drops a Gaussian the exact test keeps.

    It runs in float32 (several times cheaper than float64 over a whole model): the camera-space
    position is off by at most ``err = 1e-6 (|x| + |y| + |z| + |t|)`` of the float64 one, and
    the slack below grows with it (screen position error ``f err (1 + |x/z|) / z``; Gaussians
    within ``err`` of the near plane are left to the exact pass).
    """
    f32 = torch.float32
    Rw, tw = viewmat[:3, :3].to(f32), viewmat[:3, 3].to(f32)
    Kf = K.to(f32)
    fx, fy, cx, cy = Kf[0, 0], Kf[1, 1], Kf[0, 2], Kf[1, 2]
    mx, my, mz = means.to(f32).unbind(1)
    # elementwise, not a (N, 3) x (3, 3) matmul: one fused pass when compiled
    px, py, z = (Rw[i, 0] * mx + Rw[i, 1] * my + Rw[i, 2] * mz + tw[i] for i in range(3))
    err = 1e-6 * (mx.abs() + my.abs() + mz.abs() + tw.abs().sum())
    zs = torch.where(z > near, z, torch.full_like(z, near))
    limx = FRUSTUM_CLAMP * 0.5 * width / fx
    limy = FRUSTUM_CLAMP * 0.5 * height / fy
    jac2 = (fx * fx * (1 + limx * limx) + fy * fy * (1 + limy * limy)) / (zs * zs)
    smax = torch.exp(2.0 * log_scales.to(f32).amax(1))
    lam = (1.01 + 4.0 * err / zs) * (jac2 * smax + COV2D_DILATION)
    o = torch.sigmoid(logit_opacities.to(f32))
    xz, yz = px / zs, py / zs
    u = fx * xz + cx
    v = fy * yz + cy
    slack = 1.0 + (fx + fy) * err * (1.0 + xz.abs() + yz.abs()) / zs + 1e-5 * (u.abs() + v.abs())
    rb = torch.sqrt(_draw_extent(o)[1] * lam) + slack
    ok = (o >= ALPHA_MIN * (1 - 1e-5)) & (u + rb >= 0) & (u - rb <= width) & (v + rb >= 0) & (v - rb <= height)
    ok |= ~(torch.isfinite(u) & torch.isfinite(v) & torch.isfinite(rb))   # the exact pass decides
    return (ok & (z > near)) | ((z - near).abs() <= err)


_COMPILED: dict = {}

#: Graphs one compiled function may hold. A training run asks for SH degrees 0-3, each with
#: and without autograd (training steps, evaluations): 8 variants of the SH colour alone,
#: torch's default limit, past which dynamo silently runs the function eagerly.
RECOMPILE_LIMIT = 32


def allow_variants() -> None:
    """Raise dynamo's per-function recompile limit to :data:`RECOMPILE_LIMIT` (never lower it)."""
    cfg = torch._dynamo.config
    if getattr(cfg, "recompile_limit", RECOMPILE_LIMIT) < RECOMPILE_LIMIT:
        cfg.recompile_limit = RECOMPILE_LIMIT


def _maybe_compiled(fn, compiled: bool):
    """``fn`` eagerly, or through torch.compile (per Gaussian: fused forward and backward)."""
    if not compiled:
        return fn
    if fn not in _COMPILED:
        allow_variants()
        _COMPILED[fn] = torch.compile(fn, dynamic=True)
    return _COMPILED[fn]


def project_gaussians(means, log_scales, quats, logit_opacities, viewmat, K, width, height,
                      near=0.2, antialiased=False, compiled=False, gather=None) -> Projection:
    """Cull, project and depth-sort Gaussians (see :class:`Projection` for the outputs).

    Args:
        means: (N, 3) world positions (scene units).
        log_scales: (N, 3) natural log of the Gaussian standard deviations (scene units).
        quats: (N, 4) rotations (w, x, y, z), not necessarily normalised.
        logit_opacities: (N,) opacity logits.
        viewmat: (4, 4) world-to-camera matrix (OpenCV axes).
        K: (3, 3) intrinsics in pixels.
        width, height: image size in pixels.
        near: Gaussians with camera-space z <= near are culled (scene units; INRIA: 0.2).
        antialiased: multiply opacity by sqrt(det(cov2d) / det(cov2d + 0.3 I)).
        compiled: run the per-Gaussian maths through torch.compile (same results to ~1e-15).
        gather: ``gather(x, ids)`` reads the visible rows of each input for the differentiable
            pass (default ``x.index_select(0, ids)``); see :mod:`recgs_addon.core.render.rowgrads`.

    Culling (radius 0): z <= near; opacity < 1/255; no pixel centre of the image within the
    opacity-aware radius ``ceil(sqrt(2 ln(255 o)) sqrt(lambda_max))``, beyond which
    ``o exp(-0.5 d^2) < 1/255`` so nothing can be drawn.
    """
    f64 = torch.float64
    vm = viewmat.detach().to(f64)
    Kd = K.detach().to(f64)
    if not near > 0:
        raise ValueError(f"near must be > 0, got {near}")
    with torch.no_grad():
        cand = _maybe_compiled(_candidates, compiled)(
            means.detach(), log_scales.detach(), logit_opacities.detach(), vm, Kd, width, height, near)
        cand = torch.nonzero(cand).squeeze(1)
        info = _maybe_compiled(_cull_rows, compiled)(
            *(x.detach().index_select(0, cand).to(f64) for x in (means, log_scales, quats, logit_opacities)),
            vm, Kd, width, height, near, antialiased)
        radii = torch.zeros(means.shape[0], dtype=torch.int32, device=means.device)
        vis, drawn_radii = drawn_in_depth_order(info)   # cand is increasing: ties still by index
        radii[cand] = drawn_radii
        info = info.index_select(0, vis)
        ids = cand.index_select(0, vis)

    if gather is None:
        gather = _index_rows
    q = _maybe_compiled(_project_rows, compiled)(
        *(gather(x, ids).to(f64) for x in (means, log_scales, quats, logit_opacities)),
        vm, Kd, width, height, near, antialiased)
    means2d = torch.stack([q["u"], q["v"]], dim=-1)
    chol = torch.stack([q["l11"], q["l21"], q["l22"]], dim=-1)
    return Projection(ids=ids, means2d=means2d, chol=chol, opacity=q["opacity"], depth=q["z"],
                      radii=radii, bbox=info[:, 9:13].to(torch.int64), cov2d=info[:, 4:8],
                      extent=info[:, 8])


def _index_rows(x: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    return x.index_select(0, ids)


def drawn_in_depth_order(info: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """From culling columns ``info`` (n, 14) (``_cull_rows``'): (the rows drawn, in depth order,
    ties by row (a stable sort): (V,) int64; each row's radius in pixels, 0 = culled: (n,) int32)."""
    ok = info[:, 0] > 0
    radii = torch.where(ok, torch.ceil(info[:, 13]), torch.zeros_like(info[:, 13])).to(torch.int32)
    vis = torch.nonzero(ok).squeeze(1)
    return vis.index_select(0, torch.sort(info[:, 1].index_select(0, vis), stable=True).indices), radii


def kernel_constants(near: float) -> list[float]:
    """The constants numba's and Triton's per-Gaussian kernels read (their ``cst``, in this
    order): near, dilation, frustum clamp, alpha_min, quaternion eps^2, AA ratio floor, binning
    margins (relative, absolute), max radius. Passed, not frozen into the kernels, so that a
    cached kernel never holds stale values."""
    return [float(near), COV2D_DILATION, FRUSTUM_CLAMP, ALPHA_MIN, QUAT_EPS ** 2, AA_RATIO_EPS,
            BIN_MARGIN_REL, BIN_MARGIN_ABS, float(MAX_RADIUS)]


def camera_centre(viewmat: torch.Tensor) -> torch.Tensor:
    """(3,) world position of the camera centre, -R^T t."""
    R = viewmat[:3, :3]
    return -(R.T @ viewmat[:3, 3])


def opacity_aware_radius(opacity: float, lam_max: float) -> float:
    """Scalar helper (documentation/tests): radius where o exp(-0.5 r^2 / lam_max) = 1/255."""
    if opacity < ALPHA_MIN:
        return 0.0
    return math.sqrt(2.0 * math.log(255.0 * opacity)) * math.sqrt(lam_max)
