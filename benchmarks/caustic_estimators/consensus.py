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

import math
from typing import Optional

import torch

from recgs_addon.core.caustics.estimate import LOG_EPS
from recgs_addon.core.caustics.fft_filter import lowpass
from recgs_addon.core.caustics.passes import apply_count_gain, gain_by_count
from recgs_addon.core.caustics.warp import backproject, inside, project, sample

STATS = ("mean", "median", "min", "quantile")


def warp(points, view, depth_tol, min_alpha):
    """Sample another view's ``photo`` at the projections of ``points`` (H, W, 3). Returns
    (samples (H, W, 3), valid (H, W) bool): valid where the point projects inside the other
    image, in front of it, onto a pixel its model covers (alpha >= ``min_alpha``), and where
    its rendered surface depth agrees with the point's within ``depth_tol`` (relative): the
    other view sees that surface, not something in front of it."""
    grid, z = project(points, view)
    samp = sample(view["photo"], grid, "bilinear")
    near = sample(view["surface"], grid, "nearest")
    alpha = sample(view["alpha"], grid, "nearest")
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


def consensus_targets(views: list[dict], stat: str = "median", q: float = 0.25, depth_tol: float = 0.03,
                      gain: bool = True) -> tuple[list[torch.Tensor], list[torch.Tensor], Optional[dict]]:
    """Gain-restored consensus targets (see the module's docstring): (targets, counts, gains)."""
    stats, counts = consensus(views, stat, q, depth_tol)
    if not gain or stat == "mean":
        return stats, counts, None
    gains = gain_by_count([v["photo"] for v in views], stats, counts)
    return [apply_count_gain(s, c, gains) for s, c in zip(stats, counts)], counts, gains


def integrate_gradients(gx: torch.Tensor, gy: torch.Tensor) -> torch.Tensor:
    """The field ``u`` (H, W, C) whose forward differences best match ``gx``, ``gy`` (H, W, C)
    in least squares, with zero mean per channel: the Neumann Poisson problem
    ``laplace(u) = div(g)``, solved exactly with the FFT of the mirrored divergence (a DCT).

    ``gx[:, j] = u[:, j + 1] - u[:, j]`` and ``gy[i] = u[i + 1] - u[i]``; their last column
    (``gx``) and row (``gy``) are ignored. Float64 inside, returns the input dtype."""
    if gx.dim() != 3 or gx.shape != gy.shape:
        raise ValueError(f"expected two (H, W, C) gradient fields, got {tuple(gx.shape)} and {tuple(gy.shape)}")
    h, w, _ = gx.shape
    dtype = gx.dtype
    gx = gx.to(torch.float64).clone()
    gy = gy.to(torch.float64).clone()
    gx[:, -1] = 0
    gy[-1] = 0
    div = gx + gy
    div[:, 1:] -= gx[:, :-1]
    div[1:] -= gy[:-1]
    d = div.permute(2, 0, 1)
    ext = torch.cat([d, d.flip(-1)], -1)
    ext = torch.cat([ext, ext.flip(-2)], -2)
    ky = torch.arange(2 * h, dtype=torch.float64, device=gx.device)
    kx = torch.arange(2 * w, dtype=torch.float64, device=gx.device)
    lam = (2 * torch.cos(math.pi * ky / h) - 2)[:, None] + (2 * torch.cos(math.pi * kx / w) - 2)[None, :]
    lam[0, 0] = 1.0
    spec = torch.fft.fft2(ext) / lam
    spec[..., 0, 0] = 0
    u = torch.fft.ifft2(spec).real[..., :h, :w]
    return u.permute(1, 2, 0).to(dtype).contiguous()
