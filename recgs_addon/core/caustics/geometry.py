"""Where each frame of a survey sees the seabed: the geometry the pass estimator gathers along.

* :class:`PassView`: a frame (photo, camera, the depth of the surface it sees, its time).
* Depth from the survey's sparse points (:func:`points_depth`: the nearest point's inverse
  depth per pixel, spread by a normalised blur whose width follows the points' spacing),
  refined by a plane sweep (:func:`refine_depth`: relative depth offsets around the prior,
  scored by normalised cross-correlation of log grey images between the frame and its
  neighbours; moving light changes a frame's brightness, which the correlation ignores, the
  seabed's texture stays), with two more hypotheses where the seabed has relief
  (:func:`relief_layers`: depth spread from only the locally nearest, or furthest, points) and
  the model's depth where the points miss relief. :func:`survey_geometry` does both for a
  survey. A model trained on photos with moving light puts Gaussians in front of the seabed to
  paint each frame's light, so its own depth runs short (benchmarks/RESULTS.md#caustics-passes).
* :func:`overlap_matrix`: how much of each frame every other frame sees, unoccluded.

Shapes: photos (H, W, 3) float32 sRGB in [0, 1]; depths (H, W) camera-space z (NaN or 0 where
unknown); cameras ``viewmat`` (4, 4) world-to-camera (OpenCV axes) and ``K`` (3, 3), pixel
centres at +0.5.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..train.coverage import DEPTH_TOL
from .warp import backproject, inside, project, sample, within

#: Overlap grid: pixels of a frame sampled along each side to measure what another frame sees of it.
OVERLAP_GRID = 24
#: Depth from sparse points: the blur's width in units of the points' mean spacing in the image
#: (from 0.3 holes open between points; above 0.6 relief flattens: measured on a dive survey).
POINT_SIGMA = 0.45
#: ... and the least density of points (relative to the mean) near a pixel that gives it a depth.
POINT_SUPPORT = 0.02
#: Depth refinement: relative depth offsets tried around the prior (a plane sweep; 0.5 % apart,
#: the parabola through the best three between them: 13 gave the same targets at twice the
#: cost, benchmarks/RESULTS.md#relief-geometry), and the half-width of the correlation windows
#: (pixels).
SWEEP = tuple(float(x) for x in np.linspace(-0.015, 0.015, 7))
SWEEP_RADIUS = 2
#: The most elements (depths x frames compared x pixels x 3) one batch of a sweep's scoring
#: holds (32 MB of float32; its running sums take about four times that while they run).
SWEEP_BATCH = 1 << 23
#: ... the frames it compares with (most overlap times baseline) and the least correlation a
#: pixel's best offset needs to count (others take their neighbours' offsets).
SWEEP_FRAMES = 6
SWEEP_MIN_SCORE = 0.2
#: ... and how much better than at the prior a pixel's best correlation must be to move it.
SWEEP_MIN_GAIN = 0.02
#: Relief the points' blur flattens (a rock, a box, a wreck's side standing out of the seabed):
#: the points nearest (furthest) in their neighbourhood, within ``RELIEF_TOL`` (relative) of
#: its nearest (furthest), spread as the prior is; the neighbourhood reaches ``RELIEF_REACH``
#: times the points' spacing. Swept by ``LAYER_SWEEP`` around each.
RELIEF_TOL = 0.03
RELIEF_REACH = 1.5
LAYER_SWEEP = (-0.008, 0.0, 0.008)
#: Offsets swept around the alternative depth (the model's) where the points' may miss relief.
ALTERNATIVE_SWEEP = tuple(float(x) for x in np.linspace(-0.006, 0.006, 5))


#: Ambiguous depth, where the passes abstain: a textured window (its log grey's spread at least
#: TEXTURE_MIN) whose sweep has two separate peaks within UNIQUE_MARGIN of the best (repetitive
#: texture: tiles, grids, ripples match at several depths; the uniqueness test of stereo matching),
#: or a surface seen at a grazing angle (its normal more than GRAZING_DEG from the view ray).
TEXTURE_MIN = 0.05
UNIQUE_MARGIN = 0.03
GRAZING_DEG = 75.0


@dataclass
class PassView:
    """One training frame as the estimator needs it."""

    photo: torch.Tensor            # (H, W, 3) sRGB in [0, 1]
    surface: torch.Tensor          # (H, W) camera-space depth of the seabed it sees
    covered: torch.Tensor          # (H, W) bool: that depth is known
    viewmat: torch.Tensor          # (4, 4)
    K: torch.Tensor                # (3, 3)
    time: Optional[float] = None   # seconds into the survey's clip (None: a photo of its own)
    ambiguous: Optional[torch.Tensor] = None   # (H, W) bool: covered, but the depth is not to trust


def depth_map(v: PassView) -> torch.Tensor:
    """The surface depth with uncovered pixels at 0 (which no projected point matches)."""
    d = v.surface.float()
    return torch.where(v.covered, torch.nan_to_num(d, nan=0.0), torch.zeros_like(d))


def _grid_points(v: PassView, n: int = OVERLAP_GRID) -> torch.Tensor:
    """(M, 3) world points of a coarse grid of ``v``'s covered pixels."""
    h, w = v.surface.shape
    rows = torch.linspace(0, h - 1, min(n, h), device=v.surface.device).round().long()
    cols = torch.linspace(0, w - 1, min(n, w), device=v.surface.device).round().long()
    pts = backproject(depth_map(v), v.viewmat, v.K)[rows][:, cols]
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
    out = overlap_block(views, views, depth_tol)
    np.fill_diagonal(out, 1.0)
    return out


def with_looks_overlap(overlap: np.ndarray, views: Sequence[PassView], looks: Sequence[PassView],
                       rows: Sequence[int]) -> np.ndarray:
    """The :func:`overlap_matrix` ``overlap`` of ``views`` widened by the look frames ``looks``
    (indices ``len(views)`` on): the share of each of the frames ``rows`` that each look frame
    sees; look frames gather nothing, so their own rows stay 0."""
    n, m = len(views), len(looks)
    wide = np.zeros((n + m, n + m))
    wide[:n, :n] = overlap
    wide[np.ix_(list(rows), range(n, n + m))] = overlap_block([views[k] for k in rows], looks)
    return wide


def overlap_block(rows: Sequence[PassView], cols: Sequence[PassView], depth_tol: float = DEPTH_TOL) -> np.ndarray:
    """(len(rows), len(cols)) share of each frame of ``rows``' covered grid pixels that each of
    ``cols`` sees (:func:`overlap_matrix` of one set, or between two: the keyframes and the look
    frames they gather from); a frame against itself is left at 0."""
    out = np.zeros((len(rows), len(cols)))
    depths = [depth_map(v) for v in cols]
    for i, vi in enumerate(rows):
        pts = _grid_points(vi)
        if len(pts) == 0:
            continue
        for j, vj in enumerate(cols):
            if vj is not vi:
                out[i, j] = float(_sees(pts, vj, depths[j], depth_tol).float().mean())
    return out


def alignment(vi: PassView, vj: PassView, radius: int = SWEEP_RADIUS) -> Optional[float]:
    """How well frame ``vj`` lines up with frame ``vi`` through ``vi``'s depth: the median
    windowed correlation (:func:`zncc`) of the log grey of ``vi``'s photo and of ``vj``'s warped
    into it, over the textured pixels both see (moving light scales the grey level, which the
    correlation does not see; a frame placed a few pixels off loses it on the texture). None
    where they share fewer than 100 such pixels."""
    other, ok = warp(vi, vj)
    a, b = log_grey(vi.photo), log_grey(other)
    textured = box((a - box(a[None], radius)[0])[None] ** 2, radius)[0].sqrt() >= TEXTURE_MIN
    use = ok & textured
    if int(use.sum()) < 100:
        return None
    return float(zncc(a[None], b[None], radius)[0][use].median())


def warp(vi: PassView, vj: PassView, depth_tol: float = DEPTH_TOL,
         image: Optional[torch.Tensor] = None,
         points: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame ``vj``'s photo sampled (bilinear) at the projections of frame ``vi``'s pixels, and
    where that is the same surface: (sRGB (H, W, 3), valid (H, W) bool: half a pixel or more
    inside ``vj`` (:func:`.warp.inside`), in front of it, ``vj``'s own depth there within
    ``depth_tol`` (relative), ``vi``'s depth known). ``image``: an (H', W', C) image of ``vj``'s
    size to sample instead of its photo; ``points``: ``vi``'s pixels' world points
    (:func:`.warp.backproject` of its :func:`depth_map`), if already made (a frame warped
    from many others makes them once)."""
    pts = backproject(depth_map(vi), vi.viewmat, vi.K) if points is None else points
    grid, z = project(pts, {"viewmat": vj.viewmat, "K": vj.K, "depth": vj.surface})
    near = sample(depth_map(vj), grid, "nearest")
    ok = (inside(grid, *vj.surface.shape) & (z > 1e-6)
          & ((near - z).abs() <= depth_tol * z) & vi.covered)
    return sample(vj.photo if image is None else image, grid, "bilinear"), ok


def blur(x: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
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


def smooth(x: torch.Tensor, w: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised blur of ``x`` (P, H, W) over the pixels where ``w`` is set, by two box filters
    of the width whose variance is a Gaussian's of ``sigma`` (its cost does not grow with
    ``sigma``; twenty times quicker than :func:`blur` at 3 pixels)."""
    r = max(1, int(round((math.sqrt(6 * sigma * sigma + 1) - 1) / 2)))
    wf = w.to(x.dtype)
    return box(box(x * wf, r), r) / box(box(wf, r), r).clamp_min(1e-6)


def box(x: torch.Tensor, r: int) -> torch.Tensor:
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
    ma, mb = box(a, r), box(b, r)
    va = (box(a * a, r) - ma * ma).clamp_min(0)
    vb = (box(b * b, r) - mb * mb).clamp_min(0)
    return (box(a * b, r) - ma * mb) / torch.sqrt(va * vb + eps * eps)


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
    """(``grid_sample`` grid (D, H, W, 2), inside (D, H, W)) of points at the depths ``z``
    (D, H, W) (``_pair_rays``)."""
    x = rays.unsqueeze(1) * z + e.view(3, 1, 1, 1)
    zj = x[2]
    zs = zj.clamp_min(1e-6)
    hh, ww = vj.surface.shape
    gx = 2 * (x[0] / zs) / ww - 1
    gy = 2 * (x[1] / zs) / hh - 1
    grid = torch.stack([gx, gy], -1)
    return grid, within(grid, hh, ww) & (zj > 1e-6)


def points_depth(viewmat: torch.Tensor, K: torch.Tensor, height: int, width: int, points: torch.Tensor) -> torch.Tensor:
    """(H, W) depth interpolated from the sparse ``points`` (M, 3) that project into the view:
    the nearest point's inverse depth per pixel, spread by a normalised Gaussian blur whose
    width follows the points' spacing in the image; NaN where no point is near."""
    got = _scatter_points(viewmat, K, height, width, points)
    if got is None:
        return torch.full((height, width), float("nan"), device=points.device)
    return _spread(*got)


def _scatter_points(viewmat, K, height, width, points):
    """The points that project into the view as images (1, H, W): their inverse depth (nearer
    points win a pixel) and where they are; and their spacing in pixels. None where fewer than
    3 do."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    ok = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    if int(ok.sum()) < 3:
        return None
    u, v, z = u[ok].long(), v[ok].long(), z[ok]
    idx = v * width + u
    order = torch.argsort(z, descending=True)          # nearer points written last win
    inv = torch.zeros(height * width, device=points.device)
    has = torch.zeros(height * width, dtype=torch.bool, device=points.device)
    inv[idx[order]] = 1.0 / z[order]
    has[idx[order]] = True
    spacing = math.sqrt(height * width / float(has.sum()))
    return inv.view(1, height, width), has.view(1, height, width), spacing


def _spread(inv, has, spacing):
    """Depth (H, W) from scattered inverse depths: a normalised blur of POINT_SIGMA spacings,
    NaN where too few points are near."""
    sigma = POINT_SIGMA * spacing
    filled = blur(inv, has, sigma)[0]
    support = blur(has.float(), torch.ones_like(has), sigma)[0]
    return torch.where(support > POINT_SUPPORT / spacing ** 2, 1.0 / filled.clamp_min(1e-9),
                       torch.full_like(filled, float("nan")))


def _max_pool(x: torch.Tensor, r: int) -> torch.Tensor:
    """Maximum over (2r+1)^2 windows of ``x`` (1, H, W), as two passes (rows, then columns)."""
    x = F.max_pool2d(x.unsqueeze(0), (1, 2 * r + 1), 1, (0, r))
    return F.max_pool2d(x, (2 * r + 1, 1), 1, (r, 0))[0]


def relief_layers(viewmat: torch.Tensor, K: torch.Tensor, height: int, width: int,
                  points: torch.Tensor) -> list[torch.Tensor]:
    """Two more depth hypotheses (H, W) where the seabed has relief: each spread from only the
    points that are the nearest (the furthest) in their neighbourhood (``RELIEF_REACH`` spacings),
    within ``RELIEF_TOL``. The prior blurs a rock's top into the sand around it; on the rock the
    near layer is the rock, beside it the far layer is the sand. Empty without points."""
    got = _scatter_points(viewmat, K, height, width, points)
    if got is None:
        return []
    inv, has, spacing = got
    r = max(1, int(math.ceil(RELIEF_REACH * spacing)))
    big = torch.where(has, inv, torch.full_like(inv, -1.0))
    small = torch.where(has, inv, torch.full_like(inv, float("inf")))
    near = _max_pool(big, r)          # largest inverse depth: nearest
    far = -_max_pool(-small, r)
    out = []
    for keep in (has & (inv >= near / (1 + RELIEF_TOL)), has & (inv <= far * (1 + RELIEF_TOL))):
        out.append(_spread(inv * keep, keep, spacing))
    return out


def camera_height(views: Sequence[PassView]) -> float:
    """The median over the frames of their median surface depth (NaN where none is known)."""
    return float(np.nanmedian([float(v.surface.float().nanmedian()) for v in views]))


def sweep_neighbours(i: int, views: Sequence[PassView], overlap: np.ndarray, count: int = SWEEP_FRAMES,
                     height: Optional[float] = None) -> list[int]:
    """The frames a depth refinement of frame ``i`` compares with: those that see most of it
    from furthest away (overlap times baseline, the baseline capped at the median camera
    height, :func:`camera_height` unless given: beyond it parallax adds nothing the overlap
    does not lose)."""
    centres = torch.stack([-(v.viewmat[:3, :3].T @ v.viewmat[:3, 3]) for v in views])
    base = (centres - centres[i]).norm(dim=1).cpu().numpy()
    height = camera_height(views) if height is None else height
    score = overlap[i] * np.minimum(base, height if np.isfinite(height) else base.max())
    score[i] = -1.0
    order = [int(j) for j in np.argsort(-score) if score[j] > 0]
    return order[:count]


def log_grey(photo: torch.Tensor) -> torch.Tensor:
    """(H, W) log grey level of an sRGB photo: what the plane sweep compares (moving light
    scales it, which normalised correlation does not see)."""
    return torch.log(photo.mean(-1) + 0.02)


def _sweep_scores(i: int, views: Sequence[PassView], neighbours: Sequence[int], depths, radius: int,
                  greys: Sequence[torch.Tensor], window: Optional[tuple[slice, slice]] = None,
                  pairs: Optional[list] = None) -> torch.Tensor:
    """(D, H, W) how well the neighbours' photos agree with frame ``i``'s own at each of the
    candidate ``depths`` ((H, W) each): the mean over the neighbours that see the point of the
    normalised cross-correlation of log grey images over (2 radius + 1)^2 windows. ``window``:
    (rows, columns) slices of frame ``i`` to score alone (``depths`` of that size); ``pairs``:
    ``_pair_rays`` of ``i`` with each neighbour, if already made."""
    vi = views[i]
    window = window or (slice(None), slice(None))
    own = greys[i][window].unsqueeze(0)
    ma = box(own, radius)
    va = (box(own * own, radius) - ma * ma).clamp_min(0)
    pairs = pairs if pairs is not None else [_pair_rays(vi, views[j]) for j in neighbours]
    pairs = [(rays[:, window[0], window[1]], e) for rays, e in pairs]
    others = [greys[j].unsqueeze(0).unsqueeze(0) for j in neighbours]
    n = len(neighbours)
    # All depths' samples in one batch, up to SWEEP_BATCH elements (three box filters of it
    # in one call: per call, the running sums' overhead outweighs their work at pass size).
    step = max(1, SWEEP_BATCH // max(1, 3 * n * own[0].numel()))
    scores = []
    for k in range(0, len(depths), step):
        z = torch.stack(list(depths[k:k + step]))
        d = z.shape[0]
        bs, oks = [], []
        for (r, e), j, o in zip(pairs, neighbours, others):
            g, ok = _pair_grid(r, e, z, views[j])
            bs.append(F.grid_sample(o.expand(d, -1, -1, -1), g, mode="bilinear", align_corners=False)[:, 0])
            oks.append(ok)
        b = torch.stack(bs, 1)                               # (d, n, H, W)
        m = box(torch.cat([b, b * b, own * b]).flatten(0, 1), radius).view(3, d, n, *b.shape[2:])
        mb, mbb, mab = m[0], m[1], m[2]
        vb = (mbb - mb * mb).clamp_min(0)
        c = (mab - ma * mb) / torch.sqrt(va * vb + 1e-8)
        ok = torch.stack(oks, 1)
        scores.append((c * ok).sum(1) / ok.sum(1).clamp_min(1))
    return torch.cat(scores)


def _best_offset(s: torch.Tensor, offsets) -> tuple[torch.Tensor, torch.Tensor]:
    """(offset (H, W), its score) at each pixel's best of ``s`` (D, H, W), refined by a parabola
    through the best three."""
    s0, best = s.max(0)
    n = len(offsets)
    sm = s.gather(0, (best - 1).clamp(0, n - 1).unsqueeze(0))[0]
    sp = s.gather(0, (best + 1).clamp(0, n - 1).unsqueeze(0))[0]
    den = sm - 2 * s0 + sp
    inner = (den < -1e-6) & (best > 0) & (best < n - 1)
    frac = torch.where(inner, 0.5 * (sm - sp) / torch.where(inner, den, -torch.ones_like(den)),
                       torch.zeros_like(den)).clamp(-0.5, 0.5)
    step = (offsets[-1] - offsets[0]) / max(1, n - 1)
    return torch.tensor(offsets, dtype=s.dtype, device=s.device)[best] + frac * step, s0


def _bounds(mask: torch.Tensor, margin: int) -> tuple[slice, slice]:
    """(rows, columns) slices around the set pixels of ``mask`` (H, W), ``margin`` pixels wider."""
    rows = mask.any(1).nonzero().flatten()
    cols = mask.any(0).nonzero().flatten()
    h, w = mask.shape
    return (slice(max(0, int(rows[0]) - margin), min(h, int(rows[-1]) + 1 + margin)),
            slice(max(0, int(cols[0]) - margin), min(w, int(cols[-1]) + 1 + margin)))


def _hypothesis(i: int, views: Sequence[PassView], neighbours: Sequence[int], base: torch.Tensor, offsets,
                eligible: torch.Tensor, best: torch.Tensor, radius: int, greys, pairs,
                window: Optional[tuple[slice, slice]] = None):
    """Another depth ``base`` (H, W) for frame ``i``, swept by ``offsets`` (in ``window`` only,
    if given): (its best depth, that depth's score, where to take it: ``eligible`` pixels whose
    score is at least ``SWEEP_MIN_SCORE`` and clearly better than ``best``, the choice smoothed
    so that lone pixels do not switch)."""
    win = window or (slice(None), slice(None))
    s = _sweep_scores(i, views, neighbours, [base[win] * (1 + d) for d in offsets], radius, greys, window, pairs)
    off, score = torch.zeros_like(base), torch.full_like(base, -1.0)
    off[win], score[win] = _best_offset(s, offsets)
    take = eligible & (score >= SWEEP_MIN_SCORE) & (score >= best + SWEEP_MIN_GAIN)
    take = smooth(take.float().unsqueeze(0), views[i].covered.unsqueeze(0), 1.0)[0] > 0.5
    return base * (1 + off), score, take


def ambiguity(s: torch.Tensor, own: torch.Tensor, radius: int) -> torch.Tensor:
    """(H, W) bool: pixels whose sweep scores ``s`` (D, H, W) have two separate peaks (local
    maxima over the depths, not neighbours) within :data:`UNIQUE_MARGIN` of the best, where the
    frame's own log grey ``own`` (H, W) is textured (its window's spread at least
    :data:`TEXTURE_MIN`)."""
    d = s.shape[0]
    if d < 3:
        return torch.zeros(s.shape[1:], dtype=torch.bool, device=s.device)
    pad = torch.cat([torch.full_like(s[:1], -2.0), s, torch.full_like(s[:1], -2.0)])
    peak = (s > pad[:-2]) & (s >= pad[2:])
    close = peak & (s >= s.max(0, keepdim=True).values - UNIQUE_MARGIN)
    idx = torch.arange(d, device=s.device).view(-1, 1, 1).expand_as(s)
    first = torch.where(close, idx, torch.full_like(idx, d)).min(0).values
    last = torch.where(close, idx, torch.full_like(idx, -1)).max(0).values
    x = own.unsqueeze(0)
    spread = (box(x * x, radius) - box(x, radius) ** 2).clamp_min(0).sqrt()[0]
    return (last - first >= 2) & (spread >= TEXTURE_MIN)


def grazing(v: PassView, depth: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: pixels whose surface (the normal of ``depth`` backprojected) is seen more
    than :data:`GRAZING_DEG` from the view ray."""
    pts = backproject(depth, v.viewmat, v.K)
    dy, dx = torch.gradient(pts, dim=(0, 1))
    n = torch.linalg.cross(dx, dy, dim=-1)
    R, t = v.viewmat[:3, :3], v.viewmat[:3, 3]
    ray = pts + (R.T @ t)     # from the camera centre -R^T t to the point
    cos = (n * ray).sum(-1).abs() / (torch.linalg.vector_norm(n, dim=-1) * torch.linalg.vector_norm(ray, dim=-1)
                                      ).clamp_min(1e-12)
    return cos < math.cos(math.radians(GRAZING_DEG))


def refine_depth(i: int, views: Sequence[PassView], neighbours: Sequence[int], offsets=SWEEP,
                 radius: int = SWEEP_RADIUS, greys: Optional[Sequence[torch.Tensor]] = None,
                 alternative: Optional[torch.Tensor] = None, layers: Sequence[torch.Tensor] = ()) -> torch.Tensor:
    """Frame ``i``'s surface depth refined by a plane sweep around it: each pixel takes the
    relative offset (from ``offsets``, with a parabola through the best three) at which the
    other frames' photos agree best with its own, by normalised cross-correlation of the
    log grey images over small windows (moving light changes brightness between frames, the
    seabed's texture stays). A pixel moves off its prior only where the best offset correlates
    clearly better than the prior (``SWEEP_MIN_GAIN``); offsets no frame confirms are filled
    from their neighbours'. ``alternative`` (H, W): another depth (the model's), swept over
    ``ALTERNATIVE_SWEEP`` and taken where it agrees clearly better: relief the sparse points
    are too few to follow (a rock standing out of the seabed). ``layers``: more depths (H, W) (the frame's
    :func:`relief_layers`), each swept by ``LAYER_SWEEP`` where it differs from the prior and
    taken where it agrees clearly better. ``greys``: ``log_grey`` of every
    frame, if already made. Returns the refined (H, W) depth, and sets the frame's
    ``ambiguous`` pixels (:func:`ambiguity` of the prior's sweep)."""
    vi = views[i]
    prior = depth_map(vi)
    if not neighbours:
        return vi.surface.float()
    greys = greys if greys is not None else [log_grey(v.photo) for v in views]
    pairs = [_pair_rays(vi, views[j]) for j in neighbours]
    s = _sweep_scores(i, views, neighbours, [prior * (1 + d) for d in offsets], radius, greys, pairs=pairs)
    vi.ambiguous = ambiguity(s, greys[i], radius) & vi.covered
    off, s0 = _best_offset(s, offsets)
    # a pixel moves off its prior only where the texture there clearly agrees better elsewhere
    at_prior = s[int(np.argmin(np.abs(np.asarray(offsets))))]
    good = (s0 >= SWEEP_MIN_SCORE) & (s0 >= at_prior + SWEEP_MIN_GAIN) & vi.covered
    off = torch.where(good, off, torch.zeros_like(off))
    good = good | ((at_prior >= SWEEP_MIN_SCORE) & vi.covered)
    depth = prior * (1 + smooth(off.unsqueeze(0), good.unsqueeze(0), 1.5)[0])
    best = torch.maximum(s0, at_prior)
    for layer in layers:   # relief: the near and far layers where they agree clearly better
        lay = torch.nan_to_num(layer.float(), nan=0.0)
        differs = vi.covered & (lay > 0) & ((lay - prior).abs() > 0.5 * RELIEF_TOL * prior)
        if not bool(differs.any()):
            continue
        # relief is seldom all over a frame: scored only around it
        cand, score, take = _hypothesis(i, views, neighbours, lay, LAYER_SWEEP, differs, best, radius, greys,
                                        pairs, _bounds(differs, radius + 2))
        depth = torch.where(take, cand, depth)
        best = torch.where(take, score, best)
    if alternative is not None:
        alt = torch.nan_to_num(alternative.float(), nan=0.0)
        cand, _, take = _hypothesis(i, views, neighbours, alt, ALTERNATIVE_SWEEP, alt > 0, best, radius, greys, pairs)
        depth = torch.where(take, cand, depth)
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
                    alternatives: Optional[Sequence[torch.Tensor]] = None,
                    points: Optional[torch.Tensor] = None, check: Optional[Callable[[], None]] = None) -> None:
    """Refine every frame's ``surface`` by the plane sweep (:func:`refine_depth`), with the
    depths ``alternatives`` (the model's) and, from the sparse ``points``, each frame's
    :func:`relief_layers` as other hypotheses. ``check()`` is called before each frame (it may
    raise to give the work up: the frames are then as they were)."""
    greys = [log_grey(v.photo) for v in views]
    height = camera_height(views)   # once: the frames' depths change only when all are refined
    refined = []
    for i, v in enumerate(views):
        if check is not None:
            check()
        h, w = v.surface.shape
        layers = relief_layers(v.viewmat, v.K, h, w, points.to(v.viewmat.device, v.viewmat.dtype)) \
            if points is not None and len(points) else []
        refined.append(refine_depth(i, views, sweep_neighbours(i, views, overlap, height=height), greys=greys,
                                    alternative=None if alternatives is None else alternatives[i], layers=layers))
    for v, d in zip(views, refined):
        v.surface = d
        steep = grazing(v, depth_map(v)) & v.covered
        v.ambiguous = steep if v.ambiguous is None else v.ambiguous | steep


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
        refine_geometry(views, overlap, brought, points)
    return overlap
