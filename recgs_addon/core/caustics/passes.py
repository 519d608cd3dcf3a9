"""Caustic-free targets from the passes that saw each seabed point.

A seabed point of colour ``A`` (under the caustics' mean light) shows ``g A`` in a photo,
``g`` the caustic gain at that point and instant (grey, in linear light; mean 1: caustics move
light, they add none). A survey sees each point from several frames; frames a fraction of a
second apart saw nearly the same light, frames from another pass over the seabed (or more than
:data:`~..train.coverage.PASS_SECONDS` later in the same one) saw independent light. So for
each training frame ``i``:

1. **Geometry.** Each frame's surface depth comes from the survey's sparse points (dense
   enough on a seabed, and unaffected by the light), refined by a plane sweep that aligns the
   frame's texture with its neighbours' (``geometry.survey_geometry``); the model's depth fills in
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
   floor's over all pixels seen by ``n`` frames (:func:`gain_by_count`). What varies
   between passes at a point is light, whatever its frequency, so this replaces the whole band.
5. **The light, then the colour** (``statistic="field"``, the default). The floor is a first
   colour; each frame's *light* is then modelled against it, in the frame's own image: the
   grey log-ratio of its photo to the floor colour, denoised by total variation (the light at
   one instant is one continuous field of long lines and dark cells; what the floor got
   wrong, resampled texture and noise, is flattened) and kept where it is above the floor
   (:func:`frame_light`). The colour is then the frame's own photo with its modelled light
   taken off (it needs no resampling, so it keeps the detail the warped frames blur), the
   floor where the photo was under a bright line whose level is least certain
   (:func:`field_colour`); calibrated per number of frames as the floor is.
   ``statistic="floor"`` stops at step 4.
6. **Too few passes.** Where fewer than ``min_passes`` independent passes saw a pixel (by
   default: none, the surface unknown there), the frame keeps its per-frame estimate
   (``fallback``, RecGS's low-pass target), blended in over one pass.

**Independent looks.** Frames close in time saw nearly the same light. With the light's
correlation ``exp(-dt / light_seconds)`` between frames ``dt`` apart (``light_seconds``
measured by :func:`light_statistics`), the frames that saw a pixel are worth
:func:`effective_looks` independent samples of the light; the run reports their median, and
the coverage of a survey is counted the same way (``train/coverage.py``).

:func:`pass_targets` returns the targets and, per frame, the share of pixels that came from
the passes and the looks they had.

Shapes: photos and targets (H, W, 3) float32 sRGB in [0, 1]; frames are ``geometry.PassView``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..model.colour import linear_to_srgb, srgb_to_linear
from ..train.coverage import DEPTH_TOL, LIGHT_SECONDS, PASS_SECONDS, looks_of
from .geometry import PassView, depth_map, overlap_matrix, smooth, warp
from .tv import tv_denoise
from .warp import backproject

#: A frame that sees less than this share of another's covered pixels is not its neighbour.
MIN_OVERLAP = 0.05
#: Iterations of a frame's light's total-variation denoising (20, 40 and 100 gave targets within
#: 0.05 dB of each other on a lawnmower survey, benchmarks/RESULTS.md#caustics-light-then-colour).
FIELD_ITERS = 30
#: Frames further apart in time than this saw independent light (waves that focus sunlight
#: pass in a few seconds); the light's correlation time is looked for below it.
MAX_LAG_S = 4.0


@dataclass
class PassSettings:
    pass_seconds: float = PASS_SECONDS   # frames closer in time than this saw the same light
    per_pass: int = 4                    # frames kept of each pass (the best-overlapping)
    max_frames: int = 24                 # frames gathered for one frame, at most
    min_passes: int = 1                  # fewer independent passes: the frame's own estimate
    floor_tol: float = 0.2               # the floor: passes within this (relative) of the lowest
    floor_sigma: float = 3.0             # ... compared blurred by this many pixels (at 320 px wide)
    own_weight: float = 100.0            # the frame's own pixel, where it is on the floor, weighs this
    depth_tol: float = DEPTH_TOL
    light_seconds: float = LIGHT_SECONDS  # the light's decorrelation time (s): how independent two looks are
    statistic: str = "field"             # "field": each frame's light modelled, then the colour; "floor": the floor's mean
    field_lambda: float = 0.1            # field: TV weight of a frame's light (log units per pixel of edge)
    field_trust: float = 1.0             # field: the frame's own light (log units over the floor) at which its
    field_kappa: float = 0.3             # ... photo and the floor weigh alike; its weight falls as exp(-light / kappa)
    spread: bool = False                 # where max_frames binds, every pass's best frame first (look frames)


def settings_for(light: dict, **fields) -> PassSettings:
    """The settings for a survey whose light :func:`light_statistics` measured: frames closer
    than its correlation time are one pass, looks counted with its decorrelation time."""
    measured = {"pass_seconds": light.get("correlation_s"), "light_seconds": light.get("light_seconds")}
    return PassSettings(**{k: v for k, v in measured.items() if v is not None}, **fields)


#: With look frames a frame gathers from at most this many frames (24 without: a video's frames
#: between the keyframes bring more independent looks than the keyframes' passes hold). On a
#: 12-frames-a-second survey under fast light the targets were, against the keyframes alone,
#: -0.2 dB at 24, +0.3 at 36 and +0.5 at 48, the peak memory 1.25, 1.4 and 1.7 times theirs
#: (benchmarks/RESULTS.md#look-frames): 36 keeps within 1.5 times.
LOOK_MAX_FRAMES = 36


def with_looks(s: PassSettings, times: Sequence[Optional[float]]) -> PassSettings:
    """The settings where look frames join the keyframes (frames at ``times``): frames closer
    in time than the light's decorrelation time (not than the keyframes' interval, the finest
    lag the keyframes alone could measure) are one pass, and a frame gathers from up to
    :data:`LOOK_MAX_FRAMES`, every pass's best frame first (more of them come, each in a pass
    of its own; the cap then drops frames of a pass, not passes)."""
    t = np.sort(np.asarray([x for x in times if x is not None], float))
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    return replace(s, pass_seconds=min(s.pass_seconds, max(s.light_seconds, step)),
                   max_frames=max(s.max_frames, LOOK_MAX_FRAMES), spread=True)


def _linear(image: torch.Tensor) -> torch.Tensor:
    return srgb_to_linear(image.clamp(0, 1))


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
    if s.spread:   # round by round: each pass's next-best frame, so the cap drops frames, not passes
        picked: list[list[int]] = [[] for _ in groups]
        left, depth = s.max_frames - used, 0
        while left > 0 and any(depth < len(g) for g in groups):
            for g, p in zip(groups, picked):
                if depth < len(g) and left > 0:
                    p.append(g[depth])
                    left -= 1
            depth += 1
        return out + [p for p in picked if p]
    for g in groups:
        g = g[:max(0, s.max_frames - used)]
        if not g:
            break
        out.append(g)
        used += len(g)
    return out


def _centre(v: PassView) -> torch.Tensor:
    R, t = v.viewmat[:3, :3], v.viewmat[:3, 3]
    return -(R.T @ t)


def _water_frame(vi: PassView, water: dict, pts: Optional[torch.Tensor] = None):
    """Frame ``vi``'s pixels' world points and ranges, and the water's coefficients as tensors
    (``pts``: the points, if already made)."""
    pts = backproject(depth_map(vi), vi.viewmat, vi.K) if pts is None else pts
    terms = tuple(torch.as_tensor(water[k], dtype=pts.dtype, device=pts.device)
                  for k in ("attenuation", "backscatter", "veil"))
    return pts, torch.linalg.vector_norm(pts - _centre(vi), dim=-1).unsqueeze(-1), terms


def _direct_at(lin: torch.Tensor, pts: torch.Tensor, r_i: torch.Tensor, vj: PassView, terms) -> torch.Tensor:
    """Linear light ``lin`` that frame ``vj`` saw at world points ``pts``, as direct light at the
    ranges ``r_i``: ``vj``'s veil taken off, the attenuation over the difference put back."""
    att, back, veil = terms
    r_j = torch.linalg.vector_norm(pts - _centre(vj), dim=-1).unsqueeze(-1)
    return (lin - veil * (1 - torch.exp(-back * r_j))) * torch.exp(-att * (r_i - r_j))


def gather(i: int, views: Sequence[PassView], groups: list[list[int]], depth_tol: float = DEPTH_TOL,
           water: Optional[dict] = None):
    """Frame ``i``'s pixels as the frames of ``groups`` saw them (``choose_passes``; ``i``
    itself first): (samples (F, H, W, 3) linear light, valid (F, H, W) bool, passes (H, W):
    the groups with a valid frame at each pixel, veil (H, W, 3) or None).

    With ``water`` (the fitted medium's coefficients, ``Medium.values()``) each sample is the
    direct light as frame ``i`` would have seen it from its own range: the other frame's veil
    taken off and the attenuation over the difference of the ranges put back (frames see a
    point from different distances, and the water, not the light, makes them differ by that);
    ``veil`` is then frame ``i``'s own, to add to the estimate."""
    vi = views[i]
    samples, valid = [], []
    passes = torch.zeros(vi.surface.shape, dtype=torch.int64, device=vi.surface.device)
    veil_i = None
    pts = backproject(depth_map(vi), vi.viewmat, vi.K)   # once for every frame warped into i
    if water is not None:
        pts, r_i, terms = _water_frame(vi, water, pts)
        veil_i = terms[2] * (1 - torch.exp(-terms[1] * r_i))
    for g in groups:
        seen = torch.zeros_like(vi.covered)
        for j in g:
            if j == i:
                sample, ok = vi.photo, vi.covered
            else:
                sample, ok = warp(vi, views[j], depth_tol, points=pts)
            lin = _linear(sample)
            samples.append(lin if water is None else _direct_at(lin, pts, r_i, views[j], terms))
            valid.append(ok)
            seen |= ok
        passes += seen
    return torch.stack(samples), torch.stack(valid), passes, veil_i


def pass_estimates(views: Sequence[PassView], settings: Optional[PassSettings] = None,
                   ids: Optional[Sequence[int]] = None, overlap: Optional[np.ndarray] = None,
                   sources: Optional[Sequence[int]] = None, gains: Optional[dict] = None,
                   water: Optional[dict] = None, check: Optional[Callable[[], None]] = None,
                   keyframes: Optional[set] = None):
    """The passes' caustic-free estimate of frames ``ids`` (default all; module docstring) and
    where to use it: (estimates (sRGB, list of (H, W, 3)), weights (list of (H, W) in [0, 1]:
    1 where at least ``min_passes`` passes saw the pixel, 0 where fewer than ``min_passes - 1``
    did or the surface is unknown), info dict: per frame ``passes`` (the median passes over its
    covered pixels) and ``share`` (its mean weight), and the calibration ``gains`` ({frames: (3,)
    tensor})). Neither depends on the model: a run makes them once.

    ``overlap``: ``overlap_matrix(views)`` if already made; ``sources``: the frames whose photos
    may be gathered (default all; held-out frames get references gathered from the training
    frames alone); ``gains``: the calibration to use (default: made from ``ids``' own photos);
    ``water``: the fitted water's coefficients, if the run models it (:func:`gather`): the
    light's floor is then taken on the direct light at each frame's own range. ``check()`` is
    called before each frame's gather (it may raise to give the work up). ``keyframes``: where
    some sources are look frames, the frames that are not; ``info["looks_keyframes"]`` then
    counts each frame's looks as the keyframes alone would give them."""
    s = settings or PassSettings()
    ids = list(range(len(views))) if ids is None else list(ids)
    overlap = overlap_matrix(views, s.depth_tol) if overlap is None else overlap
    stats, counts, passes, owns, veils = [], [], [], [], []
    groups = {i: choose_passes(i, views, overlap, s, sources) for i in ids}
    looks, key_looks = [], []
    for i in ids:
        if check is not None:
            check()
        samples, valid, npass, veil = gather(i, views, groups[i], s.depth_tol, water)
        order = [j for g in groups[i] for j in g]
        looks.append(effective_looks(valid, [views[j].time for j in order], s.light_seconds))
        if keyframes is not None:
            rows = [k for k, j in enumerate(order) if j in keyframes]
            key_looks.append(effective_looks(valid[rows], [views[order[k]].time for k in rows], s.light_seconds))
        veils.append(veil)
        sigma = s.floor_sigma * views[i].photo.shape[1] / 320.0
        stats.append(floor_statistic(samples, valid, s.floor_tol, sigma, s.own_weight))
        counts.append(valid.sum(0))
        passes.append(npass)
        owns.append(samples[0].clone())   # a copy: a view would keep every gathered frame alive
    if s.statistic == "field":   # the light, then the colour
        for k, i in enumerate(ids):
            stats[k] = field_colour(owns[k], stats[k], frame_light(owns[k], stats[k], views[i].covered, s),
                                    views[i].covered, s)
    # the floor is darker than the mean light by a factor that depends on how many frames it
    # was taken over: calibrated on the photos themselves (they hold the mean light)
    if gains is None:
        gains = gain_by_count(owns, stats, counts)
    estimates, weights, info = [], [], {"passes": [], "looks": [], "share": [], "gains": gains}
    for k, i in enumerate(ids):
        lin = apply_count_gain(stats[k], counts[k], _for_counts(gains, counts[k]))
        if veils[k] is not None:
            lin = lin.clamp_min(0) + veils[k]
        estimates.append(linear_to_srgb(lin.clamp_min(0)))
        cov = views[i].covered
        w = (passes[k].to(estimates[-1].dtype) - (s.min_passes - 1)).clamp(0, 1) * cov
        weights.append(w)
        info["passes"].append(float(passes[k][cov].float().median()) if cov.any() else 0.0)
        info["looks"].append(float(looks[k][cov].median()) if cov.any() else 0.0)
        if keyframes is not None:
            info.setdefault("looks_keyframes", []).append(float(key_looks[k][cov].median()) if cov.any() else 0.0)
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


def _for_counts(gains: dict, counts: torch.Tensor) -> dict:
    """``gains`` with an entry for every count in ``counts`` (a count it lacks takes the
    nearest's; 0, where no frame saw the pixel, keeps it unscaled)."""
    have = sorted(gains)
    one = torch.ones(3, device=counts.device)
    return {int(n): (gains[n] if n in gains else gains[min(have, key=lambda k: abs(k - n))]) if n >= 1 and have else one
            for n in torch.unique(counts).tolist()}


def floor_statistic(samples: torch.Tensor, valid: torch.Tensor, tol: float = 0.15, sigma: float = 1.0,
                    own_weight: float = 1.0) -> torch.Tensor:
    """The mean of the frames that saw a pixel under the floor of its light: ``samples`` (F, H,
    W, 3) linear light, ``valid`` (F, H, W), the frame's own photo first. A frame is on the floor
    where its grey level, blurred by ``sigma`` pixels (so that resampled texture does not
    decide), lies within ``tol`` (relative) of the lowest; the own photo, where it is on the
    floor, weighs ``own_weight`` (it needs no resampling). Where every frame saw the same light
    this is the mean of them all; where some caught a bright line, those are left out."""
    grey = samples.mean(-1)
    key = smooth(grey, valid, sigma)
    key = torch.where(valid, key, torch.full_like(key, float("inf")))
    lo = key.amin(0, keepdim=True)
    m = (valid & (key <= (1 + tol) * lo)).to(samples.dtype)
    m[0] *= own_weight
    return torch.einsum("fhwc,fhw->hwc", samples, m) / m.sum(0).clamp_min(1e-6).unsqueeze(-1)


def effective_looks(valid: torch.Tensor, times: Sequence[Optional[float]], light_seconds: float) -> torch.Tensor:
    """(H, W) the independent looks at the light each pixel got from the frames that saw it
    (``valid`` (F, H, W), the frames' ``times``), counted as :func:`.coverage.looks_of` counts a
    seabed point's: a frame of the same instant as another adds nothing, one of independent
    light adds 1."""
    timed = all(t is not None for t in times)
    order = sorted(range(len(times)), key=lambda k: times[k]) if timed else list(range(len(times)))
    seen = valid[order].reshape(len(order), -1).T.cpu().numpy()
    looks = looks_of(seen, np.asarray([times[k] for k in order], float) if timed else None, light_seconds)
    return torch.from_numpy(looks).float().reshape(valid.shape[1:]).to(valid.device)


def frame_light(own: torch.Tensor, colour: torch.Tensor, covered: torch.Tensor, s: PassSettings) -> torch.Tensor:
    """A frame's light over the floor, in its own image (H, W; log units): the grey log-ratio
    of its photo ``own`` (linear) to its colour estimate ``colour`` (linear, under the floor
    light), denoised by total variation (the light is one continuous field of lines and cells;
    what the colour estimate got wrong is texture and noise, which it flattens) and kept where
    it is above the floor (caustics add light over it)."""
    r = torch.log(own.mean(-1).clamp_min(0) + 0.01) - torch.log(colour.mean(-1).clamp_min(0) + 0.01)
    r = torch.where(covered, r, torch.zeros_like(r))
    w = covered.to(r.dtype) + 1e-3
    return tv_denoise(r.unsqueeze(0), s.field_lambda, w.unsqueeze(0), iters=FIELD_ITERS)[0].clamp_min(0)


def field_colour(own: torch.Tensor, floor: torch.Tensor, light: torch.Tensor, covered: torch.Tensor,
                 s: PassSettings) -> torch.Tensor:
    """A frame's colour under the floor light (H, W, 3, linear): its own photo ``own`` with its
    modelled ``light`` (:func:`frame_light`) taken off, where that light is known well enough
    (the floor best: its weight falls as ``exp((field_trust - light) / field_kappa)``), the
    passes' ``floor`` where the photo was under a bright line (where the light is strongest its
    level is least certain). The photo needs no resampling, so it keeps the detail that the
    warped frames blur."""
    w = torch.exp((s.field_trust - light) / s.field_kappa) * covered
    w = w.unsqueeze(-1)
    return (w * own * torch.exp(-light).unsqueeze(-1) + floor) / (w + 1)


#: Frames that share this much of the light's variance saw the same light (one pass).
SAME_LIGHT = 0.5


def light_statistics(views: Sequence[PassView], overlap: np.ndarray, sources: Optional[Sequence[int]] = None,
                     sigma: float = 3.0, pairs: int = 8, shared: float = SAME_LIGHT,
                     water: Optional[dict] = None) -> dict:
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
    ``shared``: frames closer than that saw the same light (None without frame times). With
    ``water`` the two frames' direct light is compared at ``i``'s range (:func:`gather`): the
    water makes frames at different distances differ, not the light."""
    pool = list(range(len(views))) if sources is None else list(sources)
    times = [views[i].time for i in pool]
    timed = all(t is not None for t in times)
    rng = np.random.default_rng(0)

    def pair_var(i: int, j: int) -> Optional[float]:
        vi = views[i]
        other, ok = warp(vi, views[j])
        if int(ok.sum()) < 100:
            return None
        s = sigma * vi.photo.shape[1] / 320.0
        own, seen = _linear(vi.photo), _linear(other)
        if water is not None:   # both frames' direct light at i's range (as gather compares them)
            pts, r_i, terms = _water_frame(vi, water)
            own = _direct_at(own, pts, r_i, vi, terms).clamp_min(0)
            seen = _direct_at(seen, pts, r_i, views[j], terms).clamp_min(0)
        a = smooth(own.mean(-1).unsqueeze(0), ok.unsqueeze(0), s)[0]
        b = smooth(seen.mean(-1).unsqueeze(0), ok.unsqueeze(0), s)[0]
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
    out["light_seconds"] = decorrelation_time(out["shared"], dt)
    return out


def decorrelation_time(shared: dict, dt: float) -> float:
    """The time ``l`` (s) of ``exp(-lag / l)`` fitted through the light's shared variance by lag
    (least squares on its logarithm): how fast the light at a seabed point forgets itself. Light
    that shares nothing even one frame apart gets a tenth of the frame interval ``dt``."""
    pts = [(float(lag), float(f)) for lag, f in shared.items() if 0 < f < 1]
    if not pts:
        return round(dt / 10, 3) if all(f <= 0 for f in shared.values()) and shared else LIGHT_SECONDS
    lags = np.array([p[0] for p in pts])
    decay = -np.log(np.array([p[1] for p in pts]))
    return round(float((lags * lags).sum() / (lags * decay).sum()), 3)


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
