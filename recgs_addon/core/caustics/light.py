"""What light a survey shows, found before anything is removed: sunlight caustics, light fixed
to the camera (a lamp's cone and fall-off, vignetting), changes of exposure, or none.

Caustics are sunlight focused by the waves into bright lines that move over the seabed, each
frame under its own pattern. A lamp or strobe on the camera lights each point differently from
each view too, but by where the point lies in the image and how far it is: the light is fixed
to the camera. Vignetting is fixed in the image; a change of exposure scales a whole frame.
Any of them makes the same seabed point differ between frames, so the difference alone (the
pass estimator's ``light_std``) cannot tell them apart; what moves with the seabed can.

For pairs of frames that see the same seabed (from the survey's sparse points, no model
needed), frame ``j`` is warped into frame ``i`` and the log ratio of their grey levels taken
at each pixel (linear light, blurred a little so resampled texture counts little):

    log(j / i) = F(x_j) - F(x_i) + a (log r_j - log r_i) + b (r_j - r_i) + e_ij + m

``x`` is where the point lies in each image (centred, in half-widths), ``r`` its range from
each camera, ``F`` a smooth pattern over the image (polynomial terms of degree 1 to 4: a
lamp's cone, vignetting; the terms of core/model/lamp.py, which this fit starts) shared by
every frame, ``a`` and ``b`` the fall-off with range (a
lamp's inverse square, the water's attenuation over the path), ``e_ij`` the pair's exposure,
and ``m`` the rest: light that moves over the seabed. One robust least-squares fit over every
pair (Huber weights) finds the camera's part; the rest, band-passed, on the flattest seabed, is
what moves.

What moves is not all light. A warp that lands a little off (the points' depth over relief,
repetitive tiles matched wrongly, grazing views) leaves a residual on the texture's edges, and
gloss changes with the view: both grow with the pair's *baseline* (how far apart the cameras
are, over the range), and vanish between frames taken from nearly the same place. Sunlight
caustics do not depend on the baseline; they change with time. So every frame spread over the
survey gets two partners: the one furthest away in time (independent light), and the nearest
in space among those at least :data:`NEAR_LAG_S` apart in time (independent light too, the
least misregistration). The moving light is the spread of the near pairs; how much more the far
pairs show is the misregistration's share, reported beside it. Its *noise floor* is measured on
the survey: the same statistic on what differs between the colour channels of the near pairs
(sunlight caustics are grey: they multiply every channel alike; what the channels do not share
is the photos' noise, their compression and the misregistration's colour), times
:data:`FLOOR_FACTOR`, and at least :data:`MOVING_FLOOR`. Caustics are found where the moving
light stands above that floor and is :data:`MOVING_SHARE` of how the frames differ; the other
parts are reported for what they are, and the finding says which evidence decided.

Shapes: photos (H, W, 3) float32 sRGB in [0, 1]; cameras ``viewmat`` (4, 4), ``K`` (3, 3).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch

from ..model.colour import srgb_to_linear
from ..model.lamp import POWERS
from ..train.data import as_float
from .warp import backproject, inside, project, sample
from .geometry import PassView, depth_map, points_depth, smooth

#: Long side (pixels) the frames are compared at: caustic cells span tens of pixels there.
LIGHT_SIDE = 320
#: Pairs compared at most (evenly spread over the survey).
LIGHT_PAIRS = 24
#: Least share of a frame's sparse points the other frame must see to be its pair.
PAIR_OVERLAP = 0.3
#: Frames further apart in time than this saw independent sunlight (:data:`.passes.MAX_LAG_S`).
INDEPENDENT_S = 4.0
#: Blur (pixels at :data:`LIGHT_SIDE`) of the grey levels compared: resampled texture, not light.
LIGHT_SIGMA = 2.0
#: The least noise floor of the moving light's spread (standard deviation of its log gain at a
#: point): 0.03 log units is 3 % of the light. Generated surveys without caustics read
#: 0.008-0.013, real footage without them 0.011-0.015 at the near baseline (0.027-0.094 at the
#: far one), caustic surveys 0.10-0.40 (benchmarks/RESULTS.md#light-evidence).
MOVING_FLOOR = 0.03
#: The moving light must stand this many times above the survey's measured noise (the near
#: pairs' colour residual, which sunlight does not make).
FLOOR_FACTOR = 3.0
#: The near partner: the nearest frame in space at least this many seconds apart in time
#: (caustics decorrelate in about 0.1-1 s; frames without times count as apart).
NEAR_LAG_S = 1.0
#: ... and the share of the frames' differences it must make (its variance over its own and the
#: camera's light's and exposure's together): sunlight caustics are the main reason a seabed
#: point differs between frames; under a lamp on the camera what the fit leaves (the lamp's
#: shading of relief, the warp's misregistration) is a few per cent of it.
MOVING_SHARE = 0.2
#: A light fixed to the camera is reported from this spread of its log pattern over the frame
#: (5 %: what the eye sees as uneven light).
CAMERA_FLOOR = 0.05
#: Pixels a pair contributes to the fit at most, and the Huber threshold (log units).
PAIR_PIXELS = 3000
HUBER = 0.05
#: Ridge on the pattern's and range's terms (per pixel of the fit): keeps terms no pair's motion pins at 0.
RIDGE = 1e-4
#: Linear grey level below which a pixel is too dark to say anything of the light.
DARK = 0.01
#: The smooth part of a pair's residual left out of the moving light: blurred over this share
#: of the width (a lamp's pattern beyond the polynomial; caustic cells are smaller).
SMOOTH_SCALE = 0.12
#: The moving light is measured on this share of a pair's pixels with the least texture.
FLAT_SHARE = 0.3


@dataclass
class LightFinding:
    """What :func:`survey_light` found (log units: the natural log of a brightness ratio)."""

    caustics: bool
    moving: float                 # spread of the light that moves over the seabed (per frame)
    share: float                  # ... against it and what the camera's light and exposure add
    camera: float                 # spread of the camera-fixed light over the frame (pattern and range)
    pattern: float                # ... of its pattern over the image alone
    range_slope: float            # d log(light) / d log(range) at the median range
    exposure: float               # spread of a frame's exposure
    total: float                  # spread of a point's brightness between frames, all causes
    explained: float              # share of the pairs' variance the camera's part and exposure explain
    pairs: int
    independent: bool             # the pairs were far enough apart in time to see independent light
    seconds: float = 0.0
    reason: str = ""
    moving_far: float = 0.0       # the moving light of the pairs furthest apart (misregistration grows there)
    floor: float = MOVING_FLOOR   # the survey's noise floor for the moving light (module docstring)
    colour_noise: float = 0.0     # ... measured from what the channels do not share, near pairs
    decided_by: str = ""          # the evidence that decided (one phrase)
    pattern_coef: list = field(default_factory=list)   # the lamp's pattern terms (core/model/lamp.py)
    range_coef: list = field(default_factory=list)     # its fall-off: (a, b) of a log(r) + b r

    def summary(self) -> dict:
        out = asdict(self)
        for k, v in out.items():
            if isinstance(v, float):
                out[k] = round(v, 4)
        out["pattern_coef"] = [round(float(c), 5) for c in self.pattern_coef]
        out["range_coef"] = [round(float(c), 5) for c in self.range_coef]
        return out


def pattern_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., K) the lamp's polynomial terms (core/model/lamp.py: x^i y^j, 1 <= i + j <= 4; the
    constant cancels in a ratio)."""
    px, py = [np.ones_like(x)], [np.ones_like(y)]
    for _ in range(max(i for i, _ in POWERS)):
        px.append(px[-1] * x)
        py.append(py[-1] * y)
    return np.stack([px[i] * py[j] for i, j in POWERS], -1)


def _centre(viewmat: torch.Tensor) -> torch.Tensor:
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return -(R.T @ t)


def _frame(photo: torch.Tensor, cam, points: torch.Tensor, time: Optional[float]) -> Optional[PassView]:
    """A frame at :data:`LIGHT_SIDE` with its depth from the sparse points (None if they miss it)."""
    scale = max(1, math.ceil(max(cam.width, cam.height) / LIGHT_SIDE))
    small = cam.resized(max(1, round(cam.width / scale)), max(1, round(cam.height / scale)))
    x = photo.permute(2, 0, 1).unsqueeze(0).float()
    img = torch.nn.functional.adaptive_avg_pool2d(x, (small.height, small.width))[0].permute(1, 2, 0)
    viewmat = torch.tensor(small.viewmat, dtype=torch.float32)
    K = torch.tensor(small.K, dtype=torch.float32)
    d = points_depth(viewmat, K, small.height, small.width, points)
    ok = torch.isfinite(d)
    if int(ok.sum()) < 0.2 * ok.numel():
        return None
    return PassView(img.cpu(), torch.where(ok, d, torch.zeros_like(d)), ok, viewmat, K, time)


def choose_pairs(points: np.ndarray, cameras: Sequence, ids: Sequence[int], times: dict,
                 count: int = LIGHT_PAIRS, seed: int = 0) -> list[tuple[int, int, str]]:
    """Pairs ``(i, j, kind)`` of ``ids`` that see the same seabed: for up to ``count`` frames
    spread over the survey, the partner that sees at least :data:`PAIR_OVERLAP` of the frame's
    sparse points and is furthest in time (``"far"``: independent light; any partner without
    times), and the partner nearest in space at least :data:`NEAR_LAG_S` away in time
    (``"near"``: the least misregistration; module docstring)."""
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, np.float64)
    if len(pts) > 5000:
        pts = pts[rng.choice(len(pts), 5000, replace=False)]
    seen = np.zeros((len(pts), len(ids)), bool)
    centres = np.zeros((len(ids), 3))
    for k, i in enumerate(ids):
        cam = cameras[i]
        uv, z = cam.project(pts)
        seen[:, k] = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        centres[k] = -np.asarray(cam.viewmat)[:3, :3].T @ np.asarray(cam.viewmat)[:3, 3]
    n = seen.sum(0)
    order = list(range(len(ids)))
    starts = order if len(order) <= count else [order[int(k * len(order) / count)] for k in range(count)]
    sf = seen.astype(np.float32)
    used = np.zeros(len(ids))
    pairs: list[tuple[int, int, str]] = []

    def add(a, b, kind):
        pair = (min(ids[a], ids[b]), max(ids[a], ids[b]), kind)
        if pair[:2] not in [p[:2] for p in pairs]:
            pairs.append(pair)
    for a in starts:
        if n[a] < 20:
            continue
        share = (sf[:, a] @ sf) / n[a]
        share[a] = 0
        cand = np.nonzero(share >= PAIR_OVERLAP)[0]
        if not len(cand):
            continue
        # frames that saw independent light first (far apart in time), then the overlap; a
        # partner already taken counts less, so the pairs spread over the survey
        ta = times.get(cameras[ids[a]].name)
        tb = [times.get(cameras[ids[b]].name) for b in cand]
        lag = np.array([abs(t - ta) if t is not None and ta is not None else np.inf for t in tb])
        far = np.where(np.isinf(lag), 1.0, np.minimum(lag / INDEPENDENT_S, 1.0))
        score = 2.0 * far + share[cand] * (0.5 + 0.5 * rng.random(len(cand))) - used[cand]
        b = int(cand[int(np.argmax(score))])
        used[b] += 1
        add(a, b, "far")
        apart = cand[lag >= NEAR_LAG_S]
        if len(apart):
            add(a, int(apart[int(np.argmin(np.linalg.norm(centres[apart] - centres[a], axis=1)))]), "near")
    return pairs


@dataclass
class PairSamples:
    """A pair's pixels where both frames see the same surface (numpy, one entry a pixel)."""

    d: np.ndarray          # log ratio of frame j's grey level to frame i's (linear light, blurred)
    xi: np.ndarray         # (2, P) the point's position in frame i (centred, in half-widths)
    xj: np.ndarray         # ... and in frame j
    ri: np.ndarray         # its range from each camera
    rj: np.ndarray
    texture: np.ndarray    # frame i's log-grey gradient there (per pixel of LIGHT_SIDE)
    index: np.ndarray      # flat pixel index in frame i
    shape: tuple           # frame i's (H, W)
    colour: Optional[np.ndarray] = None   # (2, P) what the channels do not share: the log ratio of
    #                                       red and of blue, less green's (None: a grey photo)


def _pair_samples(vi: PassView, vj: PassView) -> Optional[PairSamples]:
    """The pair's pixels (:class:`PairSamples`), or None where they share too few."""
    pts = backproject(depth_map(vi), vi.viewmat, vi.K)
    grid, z = project(pts, {"viewmat": vj.viewmat, "K": vj.K, "depth": vj.surface})
    near = sample(depth_map(vj), grid, "nearest")
    g = grid[0]
    ok = (inside(grid, *vj.surface.shape) & (z > 1e-6) & ((near - z).abs() <= 0.03 * z) & vi.covered)
    h, w = vi.surface.shape
    s = LIGHT_SIGMA * w / LIGHT_SIDE
    other = sample(vj.photo, grid, "bilinear")
    own_rgb, other_rgb = srgb_to_linear(vi.photo.clamp(0, 1)), srgb_to_linear(other.clamp(0, 1))
    own_lin = own_rgb.mean(-1)
    a = smooth(own_lin.unsqueeze(0), ok.unsqueeze(0), s)[0]
    b = smooth(other_rgb.mean(-1).unsqueeze(0), ok.unsqueeze(0), s)[0]
    bright = ok & (a > DARK) & (b > DARK)     # too dark to carry light (housing corners, shadow)
    colour = None
    if float((vi.photo - vi.photo.mean(-1, keepdim=True)).abs().max()) > 1e-3:   # not a grey photo
        mask3 = ok.unsqueeze(0).expand(3, -1, -1)
        ca = smooth(own_rgb.permute(2, 0, 1), mask3, s).clamp_min(DARK / 3)
        cb = smooth(other_rgb.permute(2, 0, 1), mask3, s).clamp_min(DARK / 3)
        d = torch.log(cb) - torch.log(ca)
        colour = torch.stack([d[0] - d[1], d[2] - d[1]])
    idx = torch.nonzero(bright.reshape(-1))[:, 0].numpy()
    if len(idx) < 200:
        return None
    lg = torch.log(smooth(own_lin.unsqueeze(0), torch.ones_like(ok).unsqueeze(0), 0.5 * s)[0] + DARK)
    gy, gx = torch.gradient(lg)
    tex = smooth(torch.sqrt(gx * gx + gy * gy).unsqueeze(0), torch.ones_like(ok).unsqueeze(0), s)[0] * (w / LIGHT_SIDE)

    def flat(t):
        return t.reshape(-1, *t.shape[2:]).numpy()[idx].astype(np.float64)
    v, u = np.divmod(idx, w)
    half = 0.5 * w
    hj, wj = vj.surface.shape
    p = flat(pts)
    return PairSamples(
        d=np.log(flat(b)) - np.log(flat(a)),
        xi=np.stack([(u + 0.5 - 0.5 * w) / half, (v + 0.5 - 0.5 * h) / half]),
        xj=np.stack([flat(g[..., 0]), flat(g[..., 1]) * hj / wj]),   # grid_sample coordinates, centred
        ri=np.linalg.norm(p - _centre(vi.viewmat).numpy(), axis=1),
        rj=np.linalg.norm(p - _centre(vj.viewmat).numpy(), axis=1),
        texture=flat(tex), index=idx, shape=(h, w),
        colour=None if colour is None else np.stack([flat(c) for c in colour]))


def _robust_var(r: np.ndarray) -> float:
    return float((1.4826 * np.median(np.abs(r - np.median(r)))) ** 2)


def _design(s: PairSamples) -> np.ndarray:
    return np.concatenate([pattern_terms(*s.xj) - pattern_terms(*s.xi),
                           np.stack([np.log(s.rj) - np.log(s.ri), s.rj - s.ri], -1)], -1)


def fit_light(samples: Sequence[PairSamples], iterations: int = 6, seed: int = 0) -> dict:
    """The robust fit of the module docstring over the pairs ``samples``: pattern coefficients,
    range terms (log r, r), each pair's exposure, and each pair's residual at every pixel. The
    pattern's and the range's terms are kept small where the pairs do not pin them (a ridge): a
    pattern term that no pair's motion crosses cancels in every ratio, and at one altitude the
    range changes with the position in the image, as the pattern does."""
    rng = np.random.default_rng(seed)
    k = pattern_terms(np.zeros(1), np.zeros(1)).shape[-1]
    n_pairs = len(samples)
    rows, ys, pid = [], [], []
    for p, s in enumerate(samples):
        take = np.arange(len(s.d)) if len(s.d) <= PAIR_PIXELS else rng.choice(len(s.d), PAIR_PIXELS, replace=False)
        rows.append(_design(s)[take])
        ys.append(s.d[take])
        pid.append(np.full(len(take), p))
    A0, y, pid = np.concatenate(rows), np.concatenate(ys), np.concatenate(pid)
    E = np.zeros((len(y), n_pairs))
    E[np.arange(len(y)), pid] = 1.0
    A = np.concatenate([A0, E], 1)
    ridge = np.zeros(A.shape[1])
    ridge[:k + 2] = RIDGE * len(y)
    w = np.ones(len(y))
    for _ in range(iterations):
        Aw = A * w[:, None]
        coef = np.linalg.solve(Aw.T @ A + np.diag(ridge) + 1e-9 * np.eye(A.shape[1]), Aw.T @ y)
        r = y - A @ coef
        w = np.minimum(1.0, HUBER / np.maximum(np.abs(r), 1e-12))
    camera = [_design(s) @ coef[:k + 2] for s in samples]
    residual = [s.d - c - coef[k + 2 + p] for p, (s, c) in enumerate(zip(samples, camera))]
    return {"pattern": coef[:k], "range": coef[k:k + 2], "exposure": coef[k + 2:], "residual": residual,
            "camera": camera}


def moving_light(s: PairSamples, residual: np.ndarray) -> float:
    """The spread of the light that moves over the seabed in one pair: the residual of the fit,
    less its smooth part (what a light fixed to the camera leaves beyond the fitted pattern),
    where the seabed has little texture (a residual that follows texture is the warp's
    misregistration, not light; caustics show best on sand). Variance of a log ratio of two
    frames, so twice the light's own. (Any residual of the pair's pixels: the channels' too.)"""
    h, w = s.shape
    img = torch.zeros(h * w, dtype=torch.float64)
    mask = torch.zeros(h * w, dtype=torch.bool)
    img[s.index] = torch.from_numpy(residual)
    mask[s.index] = True
    img, mask = img.view(1, h, w), mask.view(1, h, w)
    broad = smooth(img, mask, SMOOTH_SCALE * w)[0].reshape(-1).numpy()[s.index]
    band = residual - broad
    flat = s.texture <= np.quantile(s.texture, FLAT_SHARE)
    return _robust_var(band[flat])


def survey_light(data, ids: Optional[Sequence[int]] = None, times: Optional[dict] = None,
                 count: int = LIGHT_PAIRS) -> LightFinding:
    """Find what light the survey ``data`` (a ``TrainData``) shows (module docstring), from its
    training views ``ids`` (default all) and frame ``times`` ({name: seconds}, default none)."""
    import time as _time

    t0 = _time.perf_counter()
    ids = list(data.train_ids if ids is None else ids)
    times = times or {}
    cams = data.scene.cameras
    pts = torch.as_tensor(np.asarray(data.scene.points, np.float32))
    pairs = choose_pairs(data.scene.points, cams, ids, times, count)
    frames: dict[int, Optional[PassView]] = {}

    def frame(i):
        if i not in frames:
            v = frames[i] = _frame(as_float(data.photo(i).cpu()), data.camera(i), pts, times.get(cams[i].name))
            keep = None if v is None or not hasattr(data, "valid") else data.valid(i, *v.covered.shape)
            if keep is not None:   # a burned-in overlay is no seabed
                v.covered = v.covered & keep.cpu()
        return frames[i]

    samples, lags, kinds = [], [], []
    for i, j, kind in pairs:
        vi, vj = frame(i), frame(j)
        if vi is None or vj is None:
            continue
        s = _pair_samples(vi, vj)
        if s is not None:
            samples.append(s)
            kinds.append(kind)
            ti, tj = times.get(cams[i].name), times.get(cams[j].name)
            lags.append(None if ti is None or tj is None else abs(tj - ti))
    if len(samples) < 2:
        return LightFinding(False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, len(samples), False,
                            round(_time.perf_counter() - t0, 2),
                            "too few overlapping frames to compare the light: caustics not looked for",
                            decided_by="too few overlapping frames")
    fit = fit_light(samples)
    far_ids = [k for k, kind in enumerate(kinds) if kind == "far"] or list(range(len(samples)))
    independent = [lags[k] is None or lags[k] > INDEPENDENT_S for k in far_ids]
    use = [k for k, ind in zip(far_ids, independent) if ind] or far_ids
    near = [k for k, kind in enumerate(kinds) if kind == "near"] or use
    spread = lambda ks, f: math.sqrt(float(np.median([f(k) for k in ks])) / 2)   # noqa: E731
    moving_far = spread(use, lambda k: moving_light(samples[k], fit["residual"][k]))
    moving = spread(near, lambda k: moving_light(samples[k], fit["residual"][k]))
    coloured = [k for k in near if samples[k].colour is not None]
    # what the channels do not share, as the grey light's noise: a channel's log ratio less
    # green's holds six times the noise variance of the three channels' mean
    colour_noise = spread(coloured, lambda k: float(np.mean([moving_light(samples[k], c) for c in samples[k].colour]))
                          ) / math.sqrt(6.0) if coloured else 0.0
    floor = max(MOVING_FLOOR, FLOOR_FACTOR * colour_noise)
    total = math.sqrt(float(np.median([_robust_var(samples[k].d) for k in use])) / 2)
    resid = math.sqrt(float(np.median([_robust_var(fit["residual"][k]) for k in use])) / 2)
    explained = 1.0 - (resid / total) ** 2 if total > 0 else 0.0
    # the camera's light where the pairs saw the seabed: its pattern over those image positions,
    # its fall-off over those ranges
    xs = np.concatenate([s.xi for s in samples], 1)
    pat = pattern_terms(*xs) @ fit["pattern"]
    ranges = np.concatenate([s.ri for s in samples])
    a, b = fit["range"]
    fall = a * np.log(ranges) + b * ranges
    camera = math.sqrt(float(np.var(pat + fall)))
    r_med = float(np.median(ranges))
    exposure = float(np.std(fit["exposure"]) / math.sqrt(2)) if len(fit["exposure"]) > 1 else 0.0
    # what the camera's light and the exposure make a point differ by between two frames
    fixed = float(np.median([np.var(fit["camera"][k]) for k in near])) / 2 + exposure ** 2
    share = moving ** 2 / (moving ** 2 + fixed) if moving > 0 else 0.0
    found = moving >= floor and share >= MOVING_SHARE
    f = LightFinding(found, moving, share, camera, math.sqrt(float(np.var(pat))), float(a + b * r_med),
                     exposure, total, explained, len(samples), all(independent),
                     round(_time.perf_counter() - t0, 2), pattern_coef=list(fit["pattern"]),
                     range_coef=[float(a), float(b)], moving_far=moving_far, floor=floor, colour_noise=colour_noise)
    f.decided_by = evidence(f)
    f.reason = describe(f)
    return f


#: The far pairs' moving light over the near pairs' from which what moves is said to grow with
#: the distance between the cameras (misregistration, gloss) rather than with time.
GROWTH = 2.0


def evidence(f: LightFinding) -> str:
    """The evidence that decided the finding, in one phrase."""
    pct = lambda v: f"{100 * (math.exp(v) - 1):.1f} %"   # noqa: E731
    floor = (f"the noise measured on the survey's photos ({pct(f.floor)}: {FLOOR_FACTOR:g} times what the colour "
             f"channels do not share)" if f.floor > MOVING_FLOOR else f"the floor of {pct(MOVING_FLOOR)}")
    if f.caustics:
        return (f"between frames taken from nearly the same place the light moves by {pct(f.moving)}, above "
                f"{floor}, and makes {100 * f.share:.0f} % of how they differ")
    if f.moving >= f.floor:
        return (f"the light fixed to the camera and the exposure make most of how the frames differ (what moves "
                f"makes {100 * f.share:.0f} %, caustics make {100 * MOVING_SHARE:.0f} % or more)")
    if f.moving_far >= f.floor and f.moving_far >= GROWTH * f.moving:
        return (f"what moves grows with the distance between the cameras ({pct(f.moving)} between frames taken from "
                f"nearly the same place, {pct(f.moving_far)} between frames far apart): the warp's misregistration "
                f"or gloss, not light; below {floor} where the cameras are close")
    return f"what moves between frames ({pct(f.moving)}) stays below {floor}"


def describe(f: LightFinding) -> str:
    """One sentence: what was found, and why."""
    pct = lambda v: f"{100 * (math.exp(v) - 1):.0f} %"   # noqa: E731
    parts = []
    if f.camera >= CAMERA_FLOOR:
        parts.append(f"a light fixed to the camera (a lamp's cone and fall-off, or vignetting) varies by "
                     f"{pct(f.camera)} over the frame")
    if f.exposure >= CAMERA_FLOOR:
        parts.append(f"the exposure changes by {pct(f.exposure)} between frames")
    seen = (f"light that moves over the seabed between frames varies by {pct(f.moving)}, "
            f"{100 * f.share:.0f} % of how the frames differ")
    if not f.independent:
        seen += " (some frames compared were close in time, and their light may not have changed)"
    if f.caustics:
        return "; ".join([f"caustics found: {seen}"] + parts)
    return "; ".join([f"no caustics found: {f.decided_by}"] + parts)
