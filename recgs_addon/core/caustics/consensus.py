"""Multi-view consensus targets: what the views agree on, per pixel, with the model's depth.

For each training view, every other training view is warped into it with the model's
rendered depth (back-project the pixel, project into the other camera, sample its photo
there, keep the sample only where the other view sees the same surface: its own rendered
depth agrees within ``depth_tol``). Each pixel then has ``n`` samples of the same surface
point under ``n`` different caustic patterns (its own photo included), and a robust
statistic of them estimates the surface under the light that is always there:

* ``mean``: what a model fitted to the photos converges to (the bound in benchmarks/RESULTS.md);
* ``median`` / ``min`` / a ``q``-quantile: a lower envelope. Caustic light is a sparse network
  of bright lines over a base, moving between shots: its lower envelope over a few shots is
  close to the base, and varies far less between points than the mean of a few shots.

A lower envelope is darker than the mean light the ground truth shows, by a factor that
depends on the number of samples ``n``. The *gain restore* measures, for each ``n`` and
colour channel, the survey-wide ratio of the photos to the envelope over the pixels with
``n`` samples, and multiplies the envelope by it (the photos hold the mean light).

``log_gradient_targets`` takes the high band from the median of the samples' log-gradients
instead (Weiss 2001; illumination edges are sparse and move, reflectance edges stay), integrated
with a Poisson solve, and the low band from their mean.

Shapes: photos and targets (H, W, 3) float32; depth, counts (H, W). Cameras: ``viewmat``
(4, 4) world-to-camera (OpenCV axes), ``K`` (3, 3), pixel centres at +0.5.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from .estimate import LOG_EPS
from .fft_filter import integrate_gradients, lowpass

STATS = ("mean", "median", "min", "quantile")


def backproject(depth: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) world points of the pixel centres at camera-space depth ``depth`` (H, W)."""
    h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5,
                          torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5,
                          indexing="ij")
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    cam = torch.stack([x, y, depth], -1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return (cam - t) @ R   # R^T (cam - t), row vectors


def project(points, view):
    """(grid (1, H, W, 2) of ``grid_sample`` coordinates, z (H, W)) of ``points`` (H, W, 3) in
    ``view`` (``viewmat``, ``K``, and ``depth`` for its size)."""
    R, t, K = view["viewmat"][:3, :3], view["viewmat"][:3, 3], view["K"]
    cam = points @ R.T + t
    z = cam[..., 2]
    zs = z.clamp_min(1e-6)
    hh, ww = view["depth"].shape
    u = K[0, 0] * cam[..., 0] / zs + K[0, 2]
    v = K[1, 1] * cam[..., 1] / zs + K[1, 2]
    return torch.stack([2 * u / ww - 1, 2 * v / hh - 1], -1).unsqueeze(0), z


def inside(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W) bool: the ``grid_sample`` coordinates ``grid`` (1, H, W, 2) lie half a pixel or more
    inside an image of ``height x width`` (:func:`within`)."""
    return within(grid[0], height, width)


def within(g: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(...) bool: the ``grid_sample`` coordinates ``g`` (..., 2) lie half a pixel or more inside
    an image of ``height x width``, where a bilinear sample mixes its pixels only (nearer the
    edge it mixes in the padding around them: a dark seam along the other frame's edge)."""
    return (g[..., 0].abs() <= 1 - 1 / width) & (g[..., 1].abs() <= 1 - 1 / height)


def _sample(image, grid, mode):
    """``image`` (H', W', C) or (H', W') at ``grid``: (H, W, C) or (H, W)."""
    x = image.unsqueeze(-1) if image.dim() == 2 else image
    out = F.grid_sample(x.permute(2, 0, 1).unsqueeze(0), grid.to(x.dtype), mode=mode, align_corners=False)
    out = out[0].permute(1, 2, 0)
    return out[..., 0] if image.dim() == 2 else out


def warp(points, view, depth_tol, min_alpha):
    """Sample another view's ``photo`` at the projections of ``points`` (H, W, 3). Returns
    (samples (H, W, 3), valid (H, W) bool): valid where the point projects inside the other
    image, in front of it, onto a pixel its model covers (alpha >= ``min_alpha``), and where
    its rendered surface depth agrees with the point's within ``depth_tol`` (relative): the
    other view sees that surface, not something in front of it."""
    grid, z = project(points, view)
    samp = _sample(view["photo"], grid, "bilinear")
    near = _sample(view["surface"], grid, "nearest")
    alpha = _sample(view["alpha"], grid, "nearest")
    within = inside(grid, *view["photo"].shape[:2]) & (z > 1e-6)
    return samp, within & ((near - z).abs() <= depth_tol * z) & (alpha >= min_alpha)


def robust_stat(samples: torch.Tensor, valid: torch.Tensor, stat: str = "median", q: float = 0.25) -> torch.Tensor:
    """Per-pixel statistic over the valid samples: ``samples`` (V, H, W, 3), ``valid`` (V, H, W).
    Pixels without a valid sample get NaN."""
    if stat not in STATS:
        raise ValueError(f"unknown statistic {stat!r} (choose from {', '.join(STATS)})")
    m = valid.unsqueeze(-1)
    if stat == "mean":
        n = m.sum(0).to(samples.dtype)
        return (samples * m).sum(0) / n
    x = torch.where(m, samples, torch.full_like(samples, float("nan")))
    if stat == "min":
        return torch.where(m.any(0), torch.where(m, samples, torch.full_like(samples, float("inf"))).amin(0),
                           torch.full_like(samples[0], float("nan")))
    if stat == "median":
        return torch.nanmedian(x, 0).values   # the lower middle sample for an even count
    return torch.nanquantile(x, q, dim=0)


def consensus(views, stat="median", q=0.25, depth_tol=0.03, min_alpha=0.5):
    """Consensus image and sample count of every view.

    ``views``: one dict per training view with ``photo`` (H, W, 3), ``depth`` and ``alpha``
    (H, W) of the model's render (``depth`` not normalised, as ``render`` returns it),
    ``viewmat``, ``K``. Returns (statistics, counts); pixels the model does not cover
    (alpha < ``min_alpha``) keep their own photo and count 1."""
    _add_surfaces(views)
    out, counts = [], []
    for i in range(len(views)):
        samples, valid = sample_stack(views, i, depth_tol, min_alpha)
        out.append(robust_stat(samples, valid, stat, q))
        counts.append(valid.sum(0))
    return out, counts


def _add_surfaces(views) -> None:
    for v in views:
        v["surface"] = v["depth"] / v["alpha"].clamp_min(1e-6)


def sample_stack(views, i: int, depth_tol: float = 0.03, min_alpha: float = 0.5):
    """View ``i``'s own photo and every other photo warped into it: (samples (V, H, W, 3),
    valid (V, H, W) bool), the own photo first and valid everywhere. ``views`` as for
    ``consensus``, with ``surface`` (depth / alpha) added."""
    vi = views[i]
    pts = backproject(vi["surface"], vi["viewmat"], vi["K"])
    covered = vi["alpha"] >= min_alpha
    samples, valid = [vi["photo"]], [torch.ones_like(covered)]
    for j, vj in enumerate(views):
        if j != i:
            s_, ok = warp(pts, vj, depth_tol, min_alpha)
            samples.append(s_)
            valid.append(ok & covered)
    return torch.stack(samples), torch.stack(valid)


def median_log_gradients(samples: torch.Tensor, valid: torch.Tensor, eps: float = LOG_EPS):
    """Per-pixel median over the views of the forward differences of ``log(samples + eps)``
    (Weiss 2001: illumination edges move between shots and are sparse, so the median of the
    log-image gradients is the reflectance's). ``samples`` (V, H, W, 3), ``valid`` (V, H, W).
    Returns (gx, gy), each (H, W, 3), 0 where no view has both pixels of a difference."""
    log = torch.log(samples.clamp_min(0) + eps)
    nan = torch.tensor(float("nan"), dtype=log.dtype, device=log.device)
    vx = (valid[:, :, 1:] & valid[:, :, :-1]).unsqueeze(-1)
    vy = (valid[:, 1:] & valid[:, :-1]).unsqueeze(-1)
    mx = torch.nanmedian(torch.where(vx, log[:, :, 1:] - log[:, :, :-1], nan), 0).values
    my = torch.nanmedian(torch.where(vy, log[:, 1:] - log[:, :-1], nan), 0).values
    gx = torch.zeros_like(log[0])
    gy = torch.zeros_like(log[0])
    gx[:, :-1] = torch.nan_to_num(mx)
    gy[:-1] = torch.nan_to_num(my)
    return gx, gy


def log_gradient_targets(views, k: int = 25, depth_tol: float = 0.03, min_alpha: float = 0.5,
                         eps: float = LOG_EPS) -> list[torch.Tensor]:
    """Targets from log-gradient consensus (Weiss 2001) for the high band and the mean
    consensus for the low band: ``exp(lowpass_k(log mean) + highpass_k(u)) - eps``, where ``u``
    integrates the median log-gradients (``median_log_gradients``). The integration fixes
    only gradients, so the lowest ``k x k`` frequencies come from the mean of the views."""
    _add_surfaces(views)
    out = []
    for i in range(len(views)):
        samples, valid = sample_stack(views, i, depth_tol, min_alpha)
        mean = robust_stat(samples, valid, "mean")
        u = integrate_gradients(*median_log_gradients(samples, valid, eps))
        low = lowpass(torch.log(mean.clamp_min(0) + eps), k)
        out.append(torch.exp(low + u - lowpass(u, k)) - eps)
    return out


def gain_by_count(photos: list[torch.Tensor], stats: list[torch.Tensor], counts: list[torch.Tensor],
                  min_pixels: int = 500) -> dict[int, torch.Tensor]:
    """Per sample count n, the (3,) ratio sum(photo) / sum(statistic) over the pixels with n
    samples in all views. Pixels without a sample (n = 0: the statistic says nothing there)
    take no part. A count with fewer than ``min_pixels`` pixels takes the ratio of the nearest
    count that has enough (the pixels of all counts, if none has)."""
    sums: dict[int, list] = {}
    for p, s, c in zip(photos, stats, counts):
        for n in torch.unique(c).tolist():
            if n < 1:
                continue
            m = c == n
            acc = sums.setdefault(int(n), [torch.zeros(3, dtype=torch.float64, device="cpu"),
                                           torch.zeros(3, dtype=torch.float64, device="cpu"), 0])
            acc[0] += p[m].double().sum(0).cpu()
            acc[1] += s[m].double().sum(0).cpu()
            acc[2] += int(m.sum())
    if not sums:
        return {}
    ok = {n: (a[0] / a[1].clamp_min(1e-12)).float() for n, a in sums.items() if a[2] >= min_pixels}
    if not ok:
        tot = [sum(a[0] for a in sums.values()), sum(a[1] for a in sums.values())]
        g = (tot[0] / tot[1].clamp_min(1e-12)).float()
        return {n: g for n in sums}
    return {n: ok[n] if n in ok else ok[min(ok, key=lambda k: abs(k - n))] for n in sums}


def apply_count_gain(stat: torch.Tensor, count: torch.Tensor, gains: dict[int, torch.Tensor]) -> torch.Tensor:
    """The statistic (H, W, 3) times the gain of each pixel's sample count."""
    out = stat.clone()
    for n, g in gains.items():
        m = count == n
        out[m] = stat[m] * g
    return out


def consensus_targets(views: list[dict], stat: str = "median", q: float = 0.25, depth_tol: float = 0.03,
                      gain: bool = True) -> tuple[list[torch.Tensor], list[torch.Tensor], Optional[dict]]:
    """Gain-restored consensus targets (see the module's docstring): (targets, counts, gains)."""
    stats, counts = consensus(views, stat, q, depth_tol)
    if not gain or stat == "mean":
        return stats, counts, None
    gains = gain_by_count([v["photo"] for v in views], stats, counts)
    return [apply_count_gain(s, c, gains) for s, c in zip(stats, counts)], counts, gains
