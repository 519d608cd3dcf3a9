"""Applying a similarity transform (rotation, uniform scale, translation) to Gaussians.

Used when an object that was moved, rotated or scaled in Blender is exported: the transform
is baked into means, rotations, log-scales, and view-dependent colour (SH of degree >= 1 is
rotated so that the colour seen from a rotated direction is unchanged).
"""
from __future__ import annotations

import numpy as np

from ..errors import RecGSError
from ..model.gaussians import SH_C0, SH_C1, SH_C2, SH_C3, GaussianSet


def sh_basis_np(dirs: np.ndarray, degree: int) -> np.ndarray:
    """Real SH basis (INRIA signs and order) for unit directions (M, 3) -> (M, (degree+1)^2), float64.

    The numpy twin of :func:`.sh.sh_basis` (torch): the export path must not need torch.
    """
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=1)


def sh_rotation_matrix(R: np.ndarray, degree: int) -> np.ndarray:
    """(K, K) matrix D with coefficients' = D @ coefficients for the function rotated by R.

    The rotated function is f'(d) = f(R^T d). Each SH band is closed under rotation, so D is
    block diagonal; each block is found exactly by least squares on sample directions
    (Y(R^T d_i) = Y(d_i) D_l, stacked over samples: B = A D), which is exact up to rounding for band-limited functions.
    """
    k = (degree + 1) ** 2
    rng = np.random.default_rng(12345)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    A = sh_basis_np(dirs, degree)
    B = sh_basis_np(dirs @ np.asarray(R, dtype=np.float64), degree)  # rows: Y(R^T d_i)
    D = np.zeros((k, k))
    for lvl in range(degree + 1):
        s = slice(lvl * lvl, (lvl + 1) ** 2)
        D[s, s] = np.linalg.lstsq(A[:, s], B[:, s], rcond=None)[0]
    return D


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def decompose_similarity(matrix: np.ndarray, tol: float = 1e-5):
    """Split a 4x4 affine matrix into (R (3,3), s float, t (3,)). Refuses non-uniform or mirrored scale."""
    m = np.asarray(matrix, dtype=np.float64)
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise RecGSError("the object's matrix has a perspective part; only moves, rotations and "
                         "uniform scales can be baked into Gaussians")
    A = m[:3, :3]
    scales = np.linalg.norm(A, axis=0)
    s = float(scales.mean())
    if s <= 0 or np.abs(scales - s).max() > tol * s:
        raise RecGSError(f"the object has a non-uniform scale ({', '.join(f'{v:.6g}' for v in scales)}); "
                         "Gaussians can only be exported with a uniform scale. Apply the scale or make it uniform")
    R = A / s
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4:
        raise RecGSError("the object's matrix has shear; Gaussians can only be exported with a "
                         "rotation and a uniform scale")
    if np.linalg.det(R) < 0:
        raise RecGSError("the object is mirrored (negative scale); mirrored Gaussians cannot be exported")
    return R, s, m[:3, 3].copy()


def transform_gaussians(g: GaussianSet, matrix: np.ndarray) -> GaussianSet:
    """Gaussians as seen after applying the 4x4 similarity ``matrix`` (object to world)."""
    R, s, t = decompose_similarity(matrix)
    if np.allclose(R, np.eye(3), atol=0, rtol=0) and s == 1.0 and not np.any(t):
        return GaussianSet(g.means.copy(), g.log_scales.copy(), g.quats.copy(),
                           g.logit_opacities.copy(), g.sh.copy())
    from ..model.cameras import rotmat_to_quat

    means = (g.means.astype(np.float64) * s) @ R.T + t
    log_scales = g.log_scales.astype(np.float64) + np.log(s)
    q = g.quats.astype(np.float64)
    q_r = rotmat_to_quat(R)
    quats = quat_multiply(q_r[None, :], q)  # keeps each quaternion's own norm
    sh = g.sh
    if g.sh_degree >= 1:
        D = sh_rotation_matrix(R, g.sh_degree)
        sh = np.einsum("kj,njc->nkc", D, g.sh.astype(np.float64))
    return GaussianSet(means, log_scales, quats, g.logit_opacities.copy(), sh)
