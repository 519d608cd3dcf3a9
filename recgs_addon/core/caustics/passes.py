"""Caustic-free targets from the passes that saw each seabed point.

A seabed point of colour ``A`` (under the caustics' mean light) shows ``g A`` in a photo,
``g`` the caustic gain at that point and instant (grey, in linear light; mean 1: caustics move
light, they add none). A survey sees each point from several frames; frames a fraction of a
second apart saw nearly the same light, frames from another pass over the seabed (or more than
:data:`~..train.coverage.PASS_SECONDS` later in the same one) saw independent light. So for
each training frame ``i``:

1. **Geometry.** Each frame's surface depth comes from the survey's sparse points (dense
   enough on a seabed, and unaffected by the light), refined by a plane sweep that aligns the
   frame's texture with its neighbours' (:func:`survey_geometry`); the model's depth fills in
   where there are no points. A model trained on photos with moving light puts Gaussians in
   front of the seabed to paint each frame's own light, so its depth runs short.
2. **Neighbours by overlap.** A coarse grid of each frame's pixels is projected into every
   other frame to measure how much of it that frame sees unoccluded. The frames that see
   enough of ``i`` are grouped into *passes* by time (a new pass every ``pass_seconds``; the
   frames within ``pass_seconds`` of ``i`` join ``i``'s own pass) and the best-overlapping
   ``per_pass`` frames of each pass kept, at most ``max_frames`` in all: the cost is O(N K)
   warps, not O(N^2).
3. **Gather.** Each kept frame's photo is sampled at the projections of ``i``'s pixels (in
   linear light), where it sees the same surface (its own depth agrees).
4. **The floor of the light, over the whole band.** Caustics focus sunlight into bright lines
   over a dimmer floor. At each pixel the frames whose (slightly blurred, so that resampled
   texture does not decide) grey level lies within ``floor_tol`` of the lowest are taken as
   the ones that saw the point on the floor; their mean, with ``i``'s own pixel weighted up
   where it is among them (it needs no resampling), is the point under the floor light. The
   floor is darker than the mean light the ground truth shows, by a factor that depends on how
   many frames it was taken over: the survey's own photos calibrate it (they hold the mean
   light), per number of frames ``n`` and channel, as the ratio of the photos' sum to the
   floor's over all pixels seen by ``n`` frames (``consensus.gain_by_count``). What varies
   between passes at a point is light, whatever its frequency, so this replaces the whole band.
5. **Too few passes.** Where fewer than ``min_passes`` independent passes saw a pixel, the
   frame keeps its per-frame estimate (``fallback``, RecGS's low-pass target), blended in over
   one pass.

:func:`pass_targets` returns the targets and, per frame, the share of pixels that came from
the passes.

Shapes: photos and targets (H, W, 3) float32 sRGB in [0, 1]; ``surface`` (H, W) camera-space
depth of the model's surface (NaN or 0 where it covers nothing); cameras ``viewmat`` (4, 4)
world-to-camera (OpenCV axes) and ``K`` (3, 3), pixel centres at +0.5.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..train.coverage import DEPTH_TOL, PASS_SECONDS
from .consensus import _sample, apply_count_gain, backproject, project
from .lightfield import linear_to_srgb, srgb_to_linear

#: Overlap grid: pixels of a frame sampled along each side to measure what another frame sees of it.
OVERLAP_GRID = 24
#: A frame that sees less than this share of another's covered pixels is not its neighbour.
MIN_OVERLAP = 0.05
#: A count of frames needs this many pixels in the survey to calibrate its own gain.
CALIBRATION_PIXELS = 500
#: Frames further apart in time than this saw independent light (waves that focus sunlight
#: pass in a few seconds); the light's correlation time is looked for below it.
MAX_LAG_S = 4.0
#: Depth from sparse points: the blur's width in units of the points' mean spacing in the image
#: (from 0.3 holes open between points; above 0.6 relief flattens: measured on a dive survey).
POINT_SIGMA = 0.45
#: ... and the least density of points (relative to the mean) near a pixel that gives it a depth.
POINT_SUPPORT = 0.02
#: Depth refinement: relative depth offsets tried around the prior (a plane sweep), and the
#: half-width of the correlation windows (pixels).
SWEEP = tuple(float(x) for x in np.linspace(-0.015, 0.015, 13))
SWEEP_RADIUS = 2
#: ... the frames it compares with (most overlap times baseline) and the least correlation a
#: pixel's best offset needs to count (others take their neighbours' offsets).
SWEEP_FRAMES = 6
SWEEP_MIN_SCORE = 0.2
#: ... and how much better than at the prior a pixel's best correlation must be to move it.
SWEEP_MIN_GAIN = 0.02
#: Offsets swept around the alternative depth (the model's) where the points' may miss relief.
ALTERNATIVE_SWEEP = tuple(float(x) for x in np.linspace(-0.006, 0.006, 5))


@dataclass
class PassView:
    """One training frame as the estimator needs it."""

    photo: torch.Tensor            # (H, W, 3) sRGB in [0, 1]
    surface: torch.Tensor          # (H, W) camera-space depth of the model's surface
    covered: torch.Tensor          # (H, W) bool: the model covers the pixel
    viewmat: torch.Tensor          # (4, 4)
    K: torch.Tensor                # (3, 3)
    time: Optional[float] = None   # seconds into the survey's clip (None: a photo of its own)


@dataclass
class PassSettings:
    pass_seconds: float = PASS_SECONDS   # frames closer in time than this saw the same light
    per_pass: int = 4                    # frames kept of each pass (the best-overlapping)
    max_frames: int = 24                 # frames gathered for one frame, at most
    min_passes: int = 3                  # fewer independent passes: the frame's own estimate
    floor_tol: float = 0.2               # the floor: passes within this (relative) of the lowest
    floor_sigma: float = 3.0             # ... compared blurred by this many pixels (at 320 px wide)
    own_weight: float = 100.0            # the frame's own pixel, where it is on the floor, weighs this
    depth_tol: float = DEPTH_TOL


def _linear(image: torch.Tensor) -> torch.Tensor:
    return srgb_to_linear(image.clamp(0, 1))


def _depth_map(v: PassView) -> torch.Tensor:
    """The surface depth with uncovered pixels at 0 (which no projected point matches)."""
    d = v.surface.float()
    return torch.where(v.covered, torch.nan_to_num(d, nan=0.0), torch.zeros_like(d))


def _grid_points(v: PassView, n: int = OVERLAP_GRID) -> torch.Tensor:
    """(M, 3) world points of a coarse grid of ``v``'s covered pixels."""
    h, w = v.surface.shape
    rows = torch.linspace(0, h - 1, min(n, h), device=v.surface.device).round().long()
    cols = torch.linspace(0, w - 1, min(n, w), device=v.surface.device).round().long()
    pts = backproject(_depth_map(v), v.viewmat, v.K)[rows][:, cols]
    ok = v.covered[rows][:, cols]
    return pts[ok]


def _sees(points: torch.Tensor, v: PassView, depth: torch.Tensor, depth_tol: float) -> torch.Tensor:
    """(M,) bool: ``v`` (its depth map ``depth``) sees each world point unoccluded."""
    R, t, K = v.viewmat[:3, :3], v.viewmat[:3, 3], v.K
    cam = points @ R.T + t
    z = cam[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    y = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    h, w = depth.shape
    inside = (z > 1e-6) & (u >= 0) & (u < w) & (y >= 0) & (y < h)
    d = depth[y.clamp(0, h - 1).long(), u.clamp(0, w - 1).long()]
    return inside & ((d - z).abs() <= depth_tol * z)


def overlap_matrix(views: Sequence[PassView], depth_tol: float = DEPTH_TOL) -> np.ndarray:
    """(N, N) share of frame i's covered grid pixels that frame j sees (diagonal 1)."""
    n = len(views)
    out = np.eye(n)
    depths = [_depth_map(v) for v in views]
    for i, vi in enumerate(views):
        pts = _grid_points(vi)
        if len(pts) == 0:
            continue
        for j, vj in enumerate(views):
            if j != i:
                out[i, j] = float(_sees(pts, vj, depths[j], depth_tol).float().mean())
    return out


def choose_passes(i: int, views: Sequence[PassView], overlap: np.ndarray, s: PassSettings,
                  sources: Optional[Sequence[int]] = None) -> list[list[int]]:
    """The frames gathered for frame ``i``, grouped by pass (module docstring, step 1): the
    first group is ``i``'s own pass (``i`` and the frames within ``pass_seconds`` of it), the
    others follow in time, a new one every ``pass_seconds``; each keeps its ``per_pass``
    best-overlapping frames, the passes that see most of ``i`` first, ``max_frames`` in all.
    ``sources``: the frames that may be gathered (default all)."""
    t_i = views[i].time
    pool = range(len(views)) if sources is None else sources
    cand = [j for j in pool if j != i and overlap[i, j] >= MIN_OVERLAP]
    own = [j for j in cand if t_i is not None and views[j].time is not None
           and abs(views[j].time - t_i) < s.pass_seconds]
    rest = [j for j in cand if j not in own]
    timed = sorted((j for j in rest if views[j].time is not None), key=lambda j: views[j].time)
    groups: list[list[int]] = []
    start = None
    for j in timed:
        if start is None or views[j].time - start >= s.pass_seconds:
            groups.append([])
            start = views[j].time
        groups[-1].append(j)
    groups += [[j] for j in rest if views[j].time is None]
    groups = [sorted(g, key=lambda j: -overlap[i, j])[:s.per_pass] for g in groups]
    groups.sort(key=lambda g: -max(overlap[i, j] for j in g))
    out = [[i] + sorted(own, key=lambda j: -overlap[i, j])[:max(0, s.per_pass - 1)]]
    used = len(out[0]) - 1
    for g in groups:
        g = g[:max(0, s.max_frames - used)]
        if not g:
            break
        out.append(g)
        used += len(g)
    return out


def gather(i: int, views: Sequence[PassView], groups: list[list[int]], depth_tol: float = DEPTH_TOL):
    """Frame ``i``'s pixels as the frames of ``groups`` saw them (``choose_passes``; ``i``
    itself first): (samples (F, H, W, 3) linear light, valid (F, H, W) bool, passes (H, W):
    the groups with a valid frame at each pixel)."""
    vi = views[i]
    pts = backproject(_depth_map(vi), vi.viewmat, vi.K)
    samples, valid = [], []
    passes = torch.zeros(vi.surface.shape, dtype=torch.int64, device=vi.surface.device)
    for g in groups:
        seen = torch.zeros_like(vi.covered)
        for j in g:
            if j == i:
                samples.append(_linear(vi.photo))
                valid.append(vi.covered)
                seen |= vi.covered
                continue
            vj = views[j]
            grid, z = project(pts, {"viewmat": vj.viewmat, "K": vj.K, "depth": vj.surface})
            near = _sample(_depth_map(vj), grid, "nearest")
            gg = grid[0]
            ok = ((gg[..., 0].abs() <= 1) & (gg[..., 1].abs() <= 1) & (z > 1e-6)
                  & ((near - z).abs() <= depth_tol * z) & vi.covered)
            samples.append(_linear(_sample(vj.photo, grid, "bilinear")))
            valid.append(ok)
            seen |= ok
        passes += seen
    return torch.stack(samples), torch.stack(valid), passes


def pass_estimates(views: Sequence[PassView], settings: Optional[PassSettings] = None,
                   ids: Optional[Sequence[int]] = None, overlap: Optional[np.ndarray] = None,
                   sources: Optional[Sequence[int]] = None, gains: Optional[dict] = None):
    """The passes' caustic-free estimate of frames ``ids`` (default all; module docstring) and
    where to use it: (estimates (sRGB, list of (H, W, 3)), weights (list of (H, W) in [0, 1]:
    1 where at least ``min_passes`` passes saw the pixel, 0 where fewer than ``min_passes - 1``
    did or the surface is unknown), info dict: per frame ``passes`` (the median passes over its
    covered pixels) and ``share`` (its mean weight), and the calibration ``gains`` ({frames: (3,)
    tensor})). Neither depends on the model: a run makes them once.

    ``overlap``: ``overlap_matrix(views)`` if already made; ``sources``: the frames whose photos
    may be gathered (default all; held-out frames get references gathered from the training
    frames alone); ``gains``: the calibration to use (default: made from ``ids``' own photos)."""
    s = settings or PassSettings()
    ids = list(range(len(views))) if ids is None else list(ids)
    overlap = overlap_matrix(views, s.depth_tol) if overlap is None else overlap
    stats, counts, passes, owns = [], [], [], []
    for i in ids:
        groups = choose_passes(i, views, overlap, s, sources)
        samples, valid, npass = gather(i, views, groups, s.depth_tol)
        sigma = s.floor_sigma * views[i].photo.shape[1] / 320.0
        stats.append(floor_statistic(samples, valid, s.floor_tol, sigma, s.own_weight))
        counts.append(valid.sum(0))
        passes.append(npass)
        owns.append(samples[0])
    # the floor is darker than the mean light by a factor that depends on how many frames it
    # was taken over: calibrated on the photos themselves (they hold the mean light)
    if gains is None:
        gains = calibrate(owns, stats, counts)
    estimates, weights, info = [], [], {"passes": [], "share": [], "gains": gains}
    for k, i in enumerate(ids):
        estimates.append(linear_to_srgb(apply_count_gain(stats[k], counts[k], _for_counts(gains, counts[k])).clamp_min(0)))
        cov = views[i].covered
        w = (passes[k].to(estimates[-1].dtype) - (s.min_passes - 1)).clamp(0, 1) * cov
        weights.append(w)
        info["passes"].append(float(passes[k][cov].float().median()) if cov.any() else 0.0)
        info["share"].append(float(w.mean()))
    return estimates, weights, info


def blend(estimate: torch.Tensor, weight: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """A frame's target: the passes' ``estimate`` where ``weight`` says so, ``fallback`` elsewhere."""
    w = weight.unsqueeze(-1)
    return w * estimate + (1 - w) * fallback


def pass_targets(views: Sequence[PassView], settings: Optional[PassSettings] = None,
                 fallback: Optional[Sequence[torch.Tensor]] = None, ids: Optional[Sequence[int]] = None, **kw):
    """Caustic-free targets of frames ``ids`` (:func:`pass_estimates`, blended with each frame's
    ``fallback``, default its photo, where too few passes saw a pixel): (targets, info)."""
    ids = list(range(len(views))) if ids is None else list(ids)
    est, wts, info = pass_estimates(views, settings, ids, **kw)
    base = [views[i].photo for i in ids] if fallback is None else fallback
    return [blend(e, w, b) for e, w, b in zip(est, wts, base)], info


def calibrate(photos: Sequence[torch.Tensor], stats: Sequence[torch.Tensor], counts: Sequence[torch.Tensor],
              min_pixels: int = CALIBRATION_PIXELS) -> dict[int, torch.Tensor]:
    """Per number of frames ``n`` a pixel's floor was taken over, the (3,) ratio of the photos'
    sum to the floor's over all pixels with ``n`` (linear light; the photos hold the mean
    light). Pixels no frame saw (``n`` = 0) take no part; a count with fewer than ``min_pixels``
    pixels takes the ratio of the nearest count that has enough (of all pixels, if none has)."""
    sums: dict[int, list] = {}
    for p, st, c in zip(photos, stats, counts):
        for n in torch.unique(c).tolist():
            if n < 1:
                continue
            m = c == n
            acc = sums.setdefault(int(n), [torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0])
            acc[0] += p[m].double().sum(0).cpu()
            acc[1] += st[m].double().sum(0).cpu()
            acc[2] += int(m.sum())
    if not sums:
        return {}
    ok = {n: (a[0] / a[1].clamp_min(1e-12)).float() for n, a in sums.items() if a[2] >= min_pixels}
    if not ok:
        pooled = (sum(a[0] for a in sums.values()) / sum(a[1] for a in sums.values()).clamp_min(1e-12)).float()
        return {n: pooled for n in sums}
    return {n: ok[n] if n in ok else ok[min(ok, key=lambda k: abs(k - n))] for n in sums}


def _for_counts(gains: dict, counts: torch.Tensor) -> dict:
    """``gains`` with an entry for every count in ``counts`` (a count it lacks takes the
    nearest's; 0, where no frame saw the pixel, keeps it unscaled)."""
    have = sorted(gains)
    one = torch.ones(3)
    return {int(n): (gains[n] if n in gains else gains[min(have, key=lambda k: abs(k - n))]) if n >= 1 and have else one
            for n in torch.unique(counts).tolist()}


def _blur(x: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised Gaussian blur of ``x`` (P, H, W) over the pixels where ``w`` (P, H, W) is set."""
    if sigma <= 0:
        return x
    r = max(1, int(math.ceil(3 * sigma)))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    wf = w.to(x.dtype)

    def conv(a):
        a = a.unsqueeze(1)
        a = F.conv2d(F.pad(a, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
        a = F.conv2d(F.pad(a, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
        return a.squeeze(1)
    return conv(x * wf) / conv(wf).clamp_min(1e-6)


def _smooth(x: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised blur of ``x`` (P, H, W) over the pixels where ``w`` is set, by two box filters
    of the width whose variance is a Gaussian's of ``sigma`` (its cost does not grow with
    ``sigma``; twenty times quicker than :func:`_blur` at 3 pixels)."""
    r = max(1, int(round((math.sqrt(6 * sigma * sigma + 1) - 1) / 2)))
    wf = w.to(x.dtype)
    return _box(_box(x * wf, r), r) / _box(_box(wf, r), r).clamp_min(1e-6)


def floor_statistic(samples: torch.Tensor, valid: torch.Tensor, tol: float = 0.15, sigma: float = 1.0,
                    own_weight: float = 1.0) -> torch.Tensor:
    """The mean of the frames that saw a pixel under the floor of its light: ``samples`` (F, H,
    W, 3) linear light, ``valid`` (F, H, W), the frame's own photo first. A frame is on the floor
    where its grey level, blurred by ``sigma`` pixels (so that resampled texture does not
    decide), lies within ``tol`` (relative) of the lowest; the own photo, where it is on the
    floor, weighs ``own_weight`` (it needs no resampling). Where every frame saw the same light
    this is the mean of them all; where some caught a bright line, those are left out."""
    grey = samples.mean(-1)
    key = _smooth(grey, valid, sigma)
    key = torch.where(valid, key, torch.full_like(key, float("inf")))
    lo = key.amin(0, keepdim=True)
    m = (valid & (key <= (1 + tol) * lo)).to(samples.dtype)
    m[0] *= own_weight
    return torch.einsum("fhwc,fhw->hwc", samples, m) / m.sum(0).clamp_min(1e-6).unsqueeze(-1)


# --- geometry --------------------------------------------------------------------------------

def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over (2r+1)^2 windows of ``x`` (B, H, W), edges replicated (running sums: a cost
    that does not grow with the window)."""
    k = 2 * r + 1
    c = F.pad(x, (r + 1, r, 0, 0), mode="replicate").cumsum(-1)
    y = c[..., k:] - c[..., :-k]
    c = F.pad(y, (0, 0, r + 1, r), mode="replicate").cumsum(-2)
    return (c[..., k:, :] - c[..., :-k, :]) / (k * k)


def zncc(a: torch.Tensor, b: torch.Tensor, r: int = 2, eps: float = 1e-4) -> torch.Tensor:
    """Zero-mean normalised cross-correlation of ``a`` (1 or B, H, W) and ``b`` (B, H, W) over
    (2r+1)^2 windows: 1 where one is an affine copy of the other (a smooth gain does not change it)."""
    ma, mb = _box(a, r), _box(b, r)
    va = (_box(a * a, r) - ma * ma).clamp_min(0)
    vb = (_box(b * b, r) - mb * mb).clamp_min(0)
    return (_box(a * b, r) - ma * mb) / torch.sqrt(va * vb + eps * eps)


def _pair_rays(vi: PassView, vj: PassView) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame ``vi``'s pixels in frame ``vj`` as a function of their depth ``z`` in ``vi``: the
    homogeneous image point is ``rays * z + e``, with ``rays`` (3, H, W) and ``e`` (3,)."""
    h, w = vi.surface.shape
    dev, dt = vi.viewmat.device, vi.viewmat.dtype
    v, u = torch.meshgrid(torch.arange(h, dtype=dt, device=dev) + 0.5,
                          torch.arange(w, dtype=dt, device=dev) + 0.5, indexing="ij")
    Ri, ti, Rj, tj = vi.viewmat[:3, :3], vi.viewmat[:3, 3], vj.viewmat[:3, :3], vj.viewmat[:3, 3]
    ray = torch.stack([(u - vi.K[0, 2]) / vi.K[0, 0], (v - vi.K[1, 2]) / vi.K[1, 1], torch.ones_like(u)])
    M = vj.K @ Rj @ Ri.T
    e = vj.K @ (tj - Rj @ Ri.T @ ti)
    return torch.einsum("ab,bhw->ahw", M, ray), e


def _pair_grid(rays: torch.Tensor, e: torch.Tensor, z: torch.Tensor, vj: PassView) -> tuple[torch.Tensor, torch.Tensor]:
    """(``grid_sample`` grid (1, H, W, 2), inside (H, W)) of points at depth ``z`` (``_pair_rays``)."""
    x = rays * z + e[:, None, None]
    zj = x[2]
    zs = zj.clamp_min(1e-6)
    hh, ww = vj.surface.shape
    gx = 2 * (x[0] / zs) / ww - 1
    gy = 2 * (x[1] / zs) / hh - 1
    inside = (gx.abs() <= 1) & (gy.abs() <= 1) & (zj > 1e-6)
    return torch.stack([gx, gy], -1).unsqueeze(0), inside


def points_depth(viewmat: torch.Tensor, K: torch.Tensor, height: int, width: int, points: torch.Tensor) -> torch.Tensor:
    """(H, W) depth interpolated from the sparse ``points`` (M, 3) that project into the view:
    the nearest point's inverse depth per pixel, spread by a normalised Gaussian blur whose
    width follows the points' spacing in the image; NaN where no point is near."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    ok = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    nan = torch.full((height, width), float("nan"), device=points.device)
    if int(ok.sum()) < 3:
        return nan
    u, v, z = u[ok].long(), v[ok].long(), z[ok]
    idx = v * width + u
    order = torch.argsort(z, descending=True)          # nearer points written last win
    inv = torch.zeros(height * width, device=points.device)
    has = torch.zeros(height * width, dtype=torch.bool, device=points.device)
    inv[idx[order]] = 1.0 / z[order]
    has[idx[order]] = True
    spacing = math.sqrt(height * width / float(has.sum()))
    sigma = POINT_SIGMA * spacing
    inv, has = inv.view(1, height, width), has.view(1, height, width)
    filled = _blur(inv, has, sigma)[0]
    support = _blur(has.float(), torch.ones_like(has), sigma)[0]
    return torch.where(support > POINT_SUPPORT / spacing ** 2, 1.0 / filled.clamp_min(1e-9), nan)


def sweep_neighbours(i: int, views: Sequence[PassView], overlap: np.ndarray, count: int = SWEEP_FRAMES) -> list[int]:
    """The frames a depth refinement of frame ``i`` compares with: those that see most of it
    from furthest away (overlap times baseline, the baseline capped at the median camera
    height: beyond it parallax adds nothing the overlap does not lose)."""
    centres = torch.stack([-(v.viewmat[:3, :3].T @ v.viewmat[:3, 3]) for v in views])
    base = (centres - centres[i]).norm(dim=1).cpu().numpy()
    height = float(np.nanmedian([float(v.surface.float().nanmedian()) for v in views]))
    score = overlap[i] * np.minimum(base, height if np.isfinite(height) else base.max())
    score[i] = -1.0
    order = [int(j) for j in np.argsort(-score) if score[j] > 0]
    return order[:count]


def log_grey(photo: torch.Tensor) -> torch.Tensor:
    """(H, W) log grey level of an sRGB photo: what the plane sweep compares (moving light
    scales it, which normalised correlation does not see)."""
    return torch.log(photo.mean(-1) + 0.02)


def _sweep_scores(i: int, views: Sequence[PassView], neighbours: Sequence[int], depths, radius: int,
                  greys: Sequence[torch.Tensor]) -> torch.Tensor:
    """(D, H, W) how well the neighbours' photos agree with frame ``i``'s own at each of the
    candidate ``depths`` ((H, W) each): the mean over the neighbours that see the point of the
    normalised cross-correlation of log grey images over (2 radius + 1)^2 windows."""
    vi = views[i]
    own = greys[i].unsqueeze(0)
    ma = _box(own, radius)
    va = (_box(own * own, radius) - ma * ma).clamp_min(0)
    pairs = [_pair_rays(vi, views[j]) for j in neighbours]
    others = [greys[j].unsqueeze(0).unsqueeze(0) for j in neighbours]
    scores = []
    for z in depths:
        grids, oks = zip(*(_pair_grid(r, e, z, views[j]) for (r, e), j in zip(pairs, neighbours)))
        b = torch.cat([F.grid_sample(o, g, mode="bilinear", align_corners=False)[0] for o, g in zip(others, grids)])
        mb = _box(b, radius)
        vb = (_box(b * b, radius) - mb * mb).clamp_min(0)
        c = (_box(own * b, radius) - ma * mb) / torch.sqrt(va * vb + 1e-8)
        ok = torch.stack(oks)
        scores.append((c * ok).sum(0) / ok.sum(0).clamp_min(1))
    return torch.stack(scores)


def _best_offset(s: torch.Tensor, offsets) -> tuple[torch.Tensor, torch.Tensor]:
    """(offset (H, W), its score) at each pixel's best of ``s`` (D, H, W), refined by a parabola
    through the best three."""
    best = s.argmax(0)
    n = len(offsets)
    s0 = s.gather(0, best.unsqueeze(0))[0]
    sm = s.gather(0, (best - 1).clamp(0, n - 1).unsqueeze(0))[0]
    sp = s.gather(0, (best + 1).clamp(0, n - 1).unsqueeze(0))[0]
    den = sm - 2 * s0 + sp
    inner = (den < -1e-6) & (best > 0) & (best < n - 1)
    frac = torch.where(inner, 0.5 * (sm - sp) / torch.where(inner, den, -torch.ones_like(den)),
                       torch.zeros_like(den)).clamp(-0.5, 0.5)
    step = (offsets[-1] - offsets[0]) / max(1, n - 1)
    return torch.tensor(offsets, dtype=s.dtype, device=s.device)[best] + frac * step, s0


def refine_depth(i: int, views: Sequence[PassView], neighbours: Sequence[int], offsets=SWEEP,
                 radius: int = SWEEP_RADIUS, greys: Optional[Sequence[torch.Tensor]] = None,
                 alternative: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Frame ``i``'s surface depth refined by a plane sweep around it: each pixel takes the
    relative offset (from ``offsets``, with a parabola through the best three) at which the
    other frames' photos agree best with its own, by normalised cross-correlation of the
    log grey images over small windows (moving light changes brightness between frames, the
    seabed's texture stays). A pixel moves off its prior only where the best offset correlates
    clearly better than the prior (``SWEEP_MIN_GAIN``); offsets no frame confirms are filled
    from their neighbours'. ``alternative`` (H, W): another depth (the model's), swept over
    ``ALTERNATIVE_SWEEP`` and taken where it agrees clearly better: relief the sparse points
    are too few to follow (a rock standing out of the seabed). ``greys``: ``log_grey`` of every
    frame, if already made. Returns the refined (H, W) depth."""
    vi = views[i]
    prior = _depth_map(vi)
    if not neighbours:
        return vi.surface.float()
    greys = greys if greys is not None else [log_grey(v.photo) for v in views]
    s = _sweep_scores(i, views, neighbours, [prior * (1 + d) for d in offsets], radius, greys)
    off, s0 = _best_offset(s, offsets)
    # a pixel moves off its prior only where the texture there clearly agrees better elsewhere
    at_prior = s[int(np.argmin(np.abs(np.asarray(offsets))))]
    good = (s0 >= SWEEP_MIN_SCORE) & (s0 >= at_prior + SWEEP_MIN_GAIN) & vi.covered
    off = torch.where(good, off, torch.zeros_like(off))
    good = good | ((at_prior >= SWEEP_MIN_SCORE) & vi.covered)
    depth = prior * (1 + _smooth(off.unsqueeze(0), good.unsqueeze(0), 1.5)[0])
    if alternative is not None:
        alt = torch.nan_to_num(alternative.float(), nan=0.0)
        sa = _sweep_scores(i, views, neighbours, [alt * (1 + d) for d in ALTERNATIVE_SWEEP], radius, greys)
        aoff, a0 = _best_offset(sa, ALTERNATIVE_SWEEP)
        take = (alt > 0) & (a0 >= SWEEP_MIN_SCORE) & (a0 >= torch.maximum(s0, at_prior) + SWEEP_MIN_GAIN)
        take = _smooth(take.float().unsqueeze(0), vi.covered.unsqueeze(0), 1.0)[0] > 0.5
        depth = torch.where(take, alt * (1 + aoff), depth)
    return torch.where(vi.covered, depth, vi.surface.float())


def prior_geometry(views: Sequence[PassView], points: Optional[torch.Tensor]) -> list[torch.Tensor]:
    """Set every frame's ``surface`` from the survey's sparse ``points`` (M, 3) where they are
    dense enough (the depth the views bring, the model's, elsewhere); returns the depths the
    views brought (NaN where they covered nothing), for :func:`refine_geometry`."""
    brought = [torch.where(v.covered, v.surface.float(), torch.full_like(v.surface.float(), float("nan")))
               for v in views]
    if points is not None and len(points):
        for v in views:
            h, w = v.surface.shape
            d = points_depth(v.viewmat, v.K, h, w, points.to(v.viewmat.device, v.viewmat.dtype))
            ok = torch.isfinite(d)
            v.surface = torch.where(ok, d, v.surface.float())
            v.covered = v.covered | ok
    return brought


def refine_geometry(views: Sequence[PassView], overlap: np.ndarray,
                    alternatives: Optional[Sequence[torch.Tensor]] = None) -> None:
    """Refine every frame's ``surface`` by the plane sweep (:func:`refine_depth`), with the
    depths ``alternatives`` (the model's) as the other hypothesis."""
    greys = [log_grey(v.photo) for v in views]
    refined = [refine_depth(i, views, sweep_neighbours(i, views, overlap), greys=greys,
                            alternative=None if alternatives is None else alternatives[i])
               for i in range(len(views))]
    for v, d in zip(views, refined):
        v.surface = d


def survey_geometry(views: Sequence[PassView], points: Optional[torch.Tensor], refine: bool = True) -> np.ndarray:
    """The survey's geometry for the estimator: depth from the sparse ``points`` (M, 3)
    (:func:`prior_geometry`), refined by the plane sweep with the views' own depth (the
    model's) as the alternative (``refine``, :func:`refine_geometry`); returns the frames'
    overlap matrix. A model trained on photos with moving light puts Gaussians in front of the
    seabed to paint each frame's light, so its depth runs short (a median of 3 % on a dive
    survey, against 0.25 % from the points and 0.09 % refined: benchmarks/RESULTS.md)."""
    brought = prior_geometry(views, points)
    overlap = overlap_matrix(views)
    if refine:
        refine_geometry(views, overlap, brought)
    return overlap


def light_statistics(views: Sequence[PassView], overlap: np.ndarray, sources: Optional[Sequence[int]] = None,
                     sigma: float = 3.0, pairs: int = 8, shared: float = 0.5) -> dict:
    """How strong the moving light is and how long it stays put at a seabed point, from the
    survey itself (frames ``sources``, default all).

    For pairs of well-overlapping frames, ``j`` is warped into ``i`` and the variance of
    ``log(j / i)`` taken (grey, linear light, blurred by ``sigma`` pixels at 320 px wide so
    that resampled texture counts little; a robust variance, from the median absolute
    deviation). Between frames far apart in time (more than :data:`MAX_LAG_S`; or photos without
    times) it is twice the
    variance of the light's log gain: ``light_std`` is the light's standard deviation in log
    units (about 0 without caustics). For frames at each lag (whole multiples of the frame
    interval, up to :data:`MAX_LAG_S`) the share of the light's variance they have in common is
    ``1 - var(lag) / var(far)``; ``correlation_s`` is the first lag at which it falls below
    ``shared``: frames closer than that saw the same light (None without frame times)."""
    pool = list(range(len(views))) if sources is None else list(sources)
    times = [views[i].time for i in pool]
    timed = all(t is not None for t in times)
    rng = np.random.default_rng(0)

    def pair_var(i: int, j: int) -> Optional[float]:
        vi, vj = views[i], views[j]
        pts = backproject(_depth_map(vi), vi.viewmat, vi.K)
        grid, z = project(pts, {"viewmat": vj.viewmat, "K": vj.K, "depth": vj.surface})
        near = _sample(_depth_map(vj), grid, "nearest")
        g = grid[0]
        ok = ((g[..., 0].abs() <= 1) & (g[..., 1].abs() <= 1) & (z > 1e-6) & vi.covered
              & ((near - z).abs() <= DEPTH_TOL * z))
        if int(ok.sum()) < 100:
            return None
        s = sigma * vi.photo.shape[1] / 320.0
        a = _smooth(_linear(vi.photo).mean(-1).unsqueeze(0), ok.unsqueeze(0), s)[0]
        b = _smooth(_linear(_sample(vj.photo, grid, "bilinear")).mean(-1).unsqueeze(0), ok.unsqueeze(0), s)[0]
        r = (torch.log(b + 0.01) - torch.log(a + 0.01))[ok]
        return float((1.4826 * (r - r.median()).abs().median()) ** 2)

    def median_var(cands) -> Optional[float]:
        if not cands:
            return None
        pick = [cands[k] for k in rng.choice(len(cands), min(pairs, len(cands)), replace=False)]
        vals = [v for v in (pair_var(i, j) for i, j in pick) if v is not None]
        return float(np.median(vals)) if vals else None

    close = [(i, j) for i in pool for j in pool if i < j and overlap[i, j] >= 0.5]
    if timed:
        far = [(i, j) for i, j in close if abs(views[j].time - views[i].time) > MAX_LAG_S]
    else:
        far = close
    v_far = median_var(far)
    out: dict = {"light_std": None if v_far is None else round(math.sqrt(v_far / 2), 4),
                 "correlation_s": None, "shared": {}}
    if not timed or not v_far:
        return out
    t = np.sort(np.asarray(times, float))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if not dt > 0:
        return out
    for m in range(1, int(MAX_LAG_S / dt) + 1):
        lag = [(i, j) for i, j in close if abs(abs(views[j].time - views[i].time) - m * dt) < 0.25 * dt]
        v = median_var(lag)
        if v is None:
            continue
        out["shared"][round(m * dt, 3)] = round(1.0 - v / v_far, 3)
        if 1.0 - v / v_far < shared:
            out["correlation_s"] = round(m * dt, 3)
            break
    else:
        out["correlation_s"] = MAX_LAG_S
    return out
