"""Dense float64 oracle for the rasterizer tests (numpy; no tiles, no chunks, no torch).

Every pixel meets every Gaussian, front to back in depth order, with INRIA's rules written
out plainly, one Gaussian at a time (vectorised over pixels only):

* covariance R S S^T R^T (normalised quaternion, exp(log_scales)); EWA projection with the
  perspective Jacobian, x/z and y/z clamped to 1.3 * 0.5 W / fx (resp. H / fy);
  +0.3 px^2 dilation; optional antialiasing factor sqrt(det(cov) / det(cov + 0.3 I));
* cull z <= near and opacity < 1/255 (no extent culling: the 1/255 rule alone decides);
* alpha = min(0.99, o exp(-0.5 d^T conic d)); skip alpha < 1/255; if T (1 - alpha) < 1e-4 the
  pixel is done and that Gaussian is not added; colour = sum c_i alpha_i T_i + T_final bg;
  depth = sum z_i alpha_i T_i; alpha = 1 - T_final;
* colour = max(0, SH(dir) + 0.5), dir = normalised (mean - camera centre), INRIA constants.

``reference_render`` also reports how close the scene comes to each threshold, so tests can
pick scenes where central finite differences are meaningful.
"""
from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def sh_to_colour_raw(deg, sh, d):
    """INRIA eval_sh for one Gaussian: sh (K, 3), d (3,) unit -> (3,) before +0.5 / clamp."""
    x, y, z = d
    res = C0 * sh[0]
    if deg > 0:
        res = res - C1 * y * sh[1] + C1 * z * sh[2] - C1 * x * sh[3]
    if deg > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        res = (res + C2[0] * xy * sh[4] + C2[1] * yz * sh[5]
               + C2[2] * (2.0 * zz - xx - yy) * sh[6]
               + C2[3] * xz * sh[7] + C2[4] * (xx - yy) * sh[8])
    if deg > 2:
        res = (res + C3[0] * y * (3 * xx - yy) * sh[9] + C3[1] * xy * z * sh[10]
               + C3[2] * y * (4 * zz - xx - yy) * sh[11]
               + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[12]
               + C3[4] * x * (4 * zz - xx - yy) * sh[13]
               + C3[5] * z * (xx - yy) * sh[14] + C3[6] * x * (xx - 3 * yy) * sh[15])
    return res


def quat_to_rot(q):
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def reference_render(means, log_scales, quats, logit_opacities, sh, viewmat, K, width, height,
                     sh_degree=None, background=None, antialiased=False, near=0.2):
    """Plain float64 render. Arguments as ``recgs_addon.core.render.rasterizer.render`` (numpy arrays).

    Returns dict(rgb (H, W, 3), alpha (H, W), depth (H, W), radii (N,), means2d (N, 2),
    margins dict(name -> smallest relative distance of any sample to that threshold),
    touched (N,) bool (added to some pixel), n_clamped (samples with o g > 0.99 that were
    added or stopped a pixel), n_stopped (pixels that hit the T < 1e-4 stop)).
    """
    means = np.asarray(means, np.float64)
    log_scales = np.asarray(log_scales, np.float64)
    quats = np.asarray(quats, np.float64)
    logit_opacities = np.asarray(logit_opacities, np.float64)
    sh = np.asarray(sh, np.float64)
    viewmat = np.asarray(viewmat, np.float64)
    K = np.asarray(K, np.float64)
    n = means.shape[0]
    if sh_degree is None:
        sh_degree = int(round(np.sqrt(sh.shape[1]))) - 1
    bg = np.zeros(3) if background is None else np.asarray(background, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    campos = -Rw.T @ tw
    limx = 1.3 * 0.5 * width / fx
    limy = 1.3 * 0.5 * height / fy

    margins = dict(alpha_min=np.inf, alpha_max=np.inf, t_min=np.inf, colour=np.inf,
                   frustum=np.inf, near=np.inf)
    gauss = []  # (z, index, mean2d, conic, opacity, colour)
    radii = np.zeros(n, np.int64)
    means2d = np.zeros((n, 2))
    for i in range(n):
        t = Rw @ means[i] + tw
        z = t[2]
        margins["near"] = min(margins["near"], abs(z - near))
        if z <= near:
            continue
        u = fx * t[0] / z + cx
        v = fy * t[1] / z + cy
        txz, tyz = t[0] / z, t[1] / z
        margins["frustum"] = min(margins["frustum"], abs(abs(txz) - limx) / limx,
                                 abs(abs(tyz) - limy) / limy)
        tx = min(limx, max(-limx, txz)) * z
        ty = min(limy, max(-limy, tyz)) * z
        J = np.array([[fx / z, 0.0, -fx * tx / (z * z)], [0.0, fy / z, -fy * ty / (z * z)]])
        R = quat_to_rot(quats[i])
        S = np.diag(np.exp(log_scales[i]))
        Sigma = R @ S @ S.T @ R.T
        T = J @ Rw
        cov = T @ Sigma @ T.T
        det0 = np.linalg.det(cov)
        cov = cov + 0.3 * np.eye(2)
        det = np.linalg.det(cov)
        o = 1.0 / (1.0 + np.exp(-logit_opacities[i]))
        if antialiased:
            o = o * np.sqrt(max(det0 / det, 0.0))
        if o < 1.0 / 255.0:
            continue
        conic = np.linalg.inv(cov)
        d = means[i] - campos
        d = d / np.linalg.norm(d)
        raw = sh_to_colour_raw(sh_degree, sh[i], d) + 0.5
        margins["colour"] = min(margins["colour"], float(np.min(np.abs(raw))))
        colour = np.maximum(raw, 0.0)
        lam = np.linalg.eigvalsh(cov).max()
        radii[i] = int(np.ceil(np.sqrt(2.0 * np.log(255.0 * o)) * np.sqrt(lam)))
        means2d[i] = (u, v)
        gauss.append((z, i, np.array([u, v]), conic, o, colour))
    # Sort by depth, ties by index.
    gauss.sort(key=lambda g: (g[0], g[1]))

    jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    px = ii + 0.5
    py = jj + 0.5
    T = np.ones((height, width))
    done = np.zeros((height, width), bool)
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    touched = np.zeros(n, bool)
    n_clamped = 0
    for z, i, m2, conic, o, colour in gauss:
        dx = px - m2[0]
        dy = py - m2[1]
        power = -0.5 * (conic[0, 0] * dx * dx + 2 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy)
        oa = o * np.exp(power)
        alpha = np.minimum(0.99, oa)
        live = ~done
        margins["alpha_min"] = min(margins["alpha_min"],
                                   float(np.min(np.abs(alpha[live] * 255.0 - 1.0), initial=np.inf)))
        margins["alpha_max"] = min(margins["alpha_max"],
                                   float(np.min(np.abs(oa[live] / 0.99 - 1.0), initial=np.inf)))
        contrib = live & (alpha >= 1.0 / 255.0)
        test_t = T * (1.0 - alpha)
        margins["t_min"] = min(margins["t_min"],
                               float(np.min(np.abs(test_t[contrib] * 1e4 - 1.0), initial=np.inf)))
        n_clamped += int(np.count_nonzero(contrib & (oa > 0.99)))
        stop = contrib & (test_t < 1e-4)
        done |= stop
        add = contrib & ~stop
        w = np.where(add, alpha * T, 0.0)
        touched[i] |= bool(add.any())
        rgb += w[..., None] * colour
        depth += w * z
        T = np.where(add, test_t, T)
    rgb += T[..., None] * bg
    return dict(rgb=rgb, alpha=1.0 - T, depth=depth, radii=radii, means2d=means2d,
                margins=margins, touched=touched, n_clamped=n_clamped,
                n_stopped=int(np.count_nonzero(done)))
