"""How many training views see each point of the seabed: what caustic removal has to work with.

A seabed point seen by ``n`` photos offers ``n`` samples of the light that moved over it; how
well any method can tell its colour from the caustics grows with ``n`` (docs/method.md).
Frames of a video taken a fraction of a second apart saw nearly the same light, so they do not
count as independent samples: of the frames that see a point, one counts for every
:data:`PASS_SECONDS` of the clip (times from the survey's ``frames.json``, core/io/frames.py).
Photos without times count each. The count is called *passes* below (a camera that films a
point for three seconds gives three).

* :func:`sparse_coverage`: before training, from the survey's sparse points projected into
  the training cameras (inside the image, in front of the camera; no occlusion test, which
  suits a seabed seen from above).
* :func:`surface_coverage`: with a model, from points on its surface: pixels of every
  training view back-projected at the model's depth, then counted in every training view that
  sees them unoccluded (its own depth there agrees).

Both return :class:`Coverage`: the median views and passes per point and a histogram.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional

import numpy as np
import torch

from ..io.frames import read_frame_times
from ..render.rasterizer import render
from .data import view_tensors

#: Frames of one video less than this many seconds apart saw nearly the same light at a point
#: (the waves that focus it move at 0.2-0.5 Hz): one of them counts as independent.
PASS_SECONDS = 1.0
#: The light's decorrelation time assumed until a survey's own is measured (seconds): light at a
#: point shares ``exp(-dt / LIGHT_SECONDS)`` of its variance between frames ``dt`` apart, so a
#: video at 3 frames a second gives about one independent look a second, as :data:`PASS_SECONDS`
#: counts them (``caustics.passes.light_statistics`` measures a survey's own).
LIGHT_SECONDS = 0.5
#: Relative depth agreement that counts a point as unoccluded in a view.
DEPTH_TOL = 0.03
#: Long side (pixels) of the depth renders the surface coverage tests against.
COVERAGE_SIDE = 400
#: Views a run's closing coverage takes points from, at most (evenly spread: the median needs no more).
COVERAGE_VIEWS = 64


def spread(ids: list[int], count: int) -> list[int]:
    """At most ``count`` of ``ids``, evenly spread over them (all of them if fewer)."""
    ids = list(ids)
    if len(ids) <= count:
        return ids
    return [ids[int(k * len(ids) / count)] for k in range(count)]


@dataclass
class Coverage:
    """Views (and passes) per seabed point over a survey's training views."""

    points: int
    median_views: float
    median_passes: float
    share_below: dict = field(default_factory=dict)   # views -> share of points seen by fewer
    histogram: list = field(default_factory=list)     # views 0..30 (the last bin: 30 or more)
    source: str = "sparse"
    median_looks: float = 0.0                         # independent looks at the light (:func:`looks_of`)

    def summary(self) -> dict:
        return asdict(self)


def _summarise(counts: np.ndarray, passes: np.ndarray, source: str, looks: np.ndarray) -> Coverage:
    if counts.size == 0:
        return Coverage(0, 0.0, 0.0, source=source)
    hist = np.bincount(np.minimum(counts, 30), minlength=31)
    below = {str(n): float(np.mean(counts < n)) for n in (3, 5, 8)}
    return Coverage(int(counts.size), float(np.median(counts)), float(np.median(passes)), below,
                    [int(h) for h in hist], source, round(float(np.median(looks)), 2))


def looks_of(seen: np.ndarray, times: Optional[np.ndarray] = None, light_seconds: float = LIGHT_SECONDS) -> np.ndarray:
    """(P,) independent looks at the light per point from ``seen`` (P, V) bool over views in
    time order (``times`` (V,) seconds): how many independent samples of the light its views
    are worth, ``1' rho^-1 1`` for the light's correlation ``rho = exp(-|dt| / light_seconds)``
    between them. For that exponential correlation it sums over each point's views in
    time order, ``1 + sum (1 - a) / (1 + a)`` with ``a = exp(-dt / light_seconds)`` between a
    view and the one before: a view of the same instant adds nothing, one of independent light
    adds 1. The count of views where ``times`` is None."""
    counts = seen.sum(1).astype(np.float64)
    if times is None or seen.shape[1] == 0 or not light_seconds > 0:
        return counts
    looks = np.zeros(seen.shape[0])
    last = np.full(seen.shape[0], -np.inf)
    for v in range(seen.shape[1]):
        a = np.exp(-(times[v] - last) / light_seconds)
        looks += seen[:, v] * (1 - a) / (1 + a)
        last = np.where(seen[:, v], times[v], last)
    return looks


def passes_of(seen: np.ndarray, times: Optional[np.ndarray] = None, gap_s: float = PASS_SECONDS) -> np.ndarray:
    """(P,) independent views per point from ``seen`` (P, V) bool over views in time order: a
    seeing view counts when it comes at least ``gap_s`` after the last one counted (``times``
    (V,) seconds); every seeing view counts where ``times`` is None."""
    if times is None or seen.shape[1] == 0:
        return seen.sum(1)
    passes = np.zeros(seen.shape[0], np.int64)
    last = np.full(seen.shape[0], -np.inf)
    for v in range(seen.shape[1]):
        s = seen[:, v] & (times[v] - last >= gap_s)
        passes += s
        last = np.where(s, times[v], last)
    return passes


def _time_order(data, ids: list[int]) -> tuple[list[int], Optional[np.ndarray]]:
    """``ids`` in time order (name order without times) and their times, if the survey has them."""
    names = [data.scene.cameras[i].name for i in ids]
    times = read_frame_times(data.scene.scene_dir)
    if times is None or not all(n in times for n in names):
        return [ids[k] for k in sorted(range(len(ids)), key=lambda k: names[k])], None
    order = sorted(range(len(ids)), key=lambda k: (times[names[k]], names[k]))
    return [ids[k] for k in order], np.array([times[names[k]] for k in order])


def sparse_coverage(data, max_points: int = 20000, seed: int = 0) -> Coverage:
    """Coverage of the survey's sparse points by the training views (no occlusion test)."""
    pts = np.asarray(data.scene.points, np.float64)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    ids, times = _time_order(data, list(data.train_ids))
    seen = np.zeros((len(pts), len(ids)), bool)
    for k, i in enumerate(ids):
        cam = data.scene.cameras[i]
        uv, z = cam.project(pts)
        seen[:, k] = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    counts = seen.sum(1)
    keep = counts > 0
    return _summarise(counts[keep], passes_of(seen[keep], times), "sparse", looks_of(seen[keep], times))


@torch.no_grad()
def surface_coverage(trainer, per_view: int = 400, seed: int = 0, source_ids: Optional[list[int]] = None,
                     max_side: int = COVERAGE_SIDE, light_seconds: float = LIGHT_SECONDS) -> Coverage:
    """Coverage of the model's surface by the training views: about ``per_view`` pixels of each
    of ``source_ids`` (default: every training view) where the model is opaque (alpha above
    0.5), back-projected at its depth and counted in every training view whose own depth there
    agrees (:data:`DEPTH_TOL`). Depth is rendered at most ``max_side`` pixels on the long side;
    ``light_seconds``: the light's decorrelation time the looks are counted with (the survey's,
    where measured)."""
    data = trainer.data
    ids, times = _time_order(data, list(data.train_ids))
    sources = set(ids if source_ids is None else source_ids)
    rng = np.random.default_rng(seed)
    depth, cams, points = [], [], []
    for i in ids:
        w, h = data.sizes[i]
        cam = data.camera(i, max(1, -(-max(w, h) // max_side)))
        viewmat, K = view_tensors(cam, trainer.device)
        p = trainer.params
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], trainer._sh(), viewmat, K,
                     cam.width, cam.height, sh_degree=trainer.sh_degree, compiled=trainer.compiler.compiled())
        d = (out.depth / out.alpha.clamp_min(1e-6)).cpu().numpy()   # the expected depth of the surface
        ok = (out.alpha > 0.5).cpu().numpy()
        depth.append(np.where(ok, d, np.nan))
        cams.append(cam)
        ys, xs = np.nonzero(ok)
        if i in sources and len(ys):
            pick = rng.choice(len(ys), min(per_view, len(ys)), replace=False)
            u, v, z = xs[pick] + 0.5, ys[pick] + 0.5, d[ys[pick], xs[pick]]
            pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
            points.append((pc - cam.t) @ cam.R)    # camera -> world
    if not points:
        return _summarise(np.zeros(0, np.int64), np.zeros(0, np.int64), "surface", np.zeros(0))
    pts = np.concatenate(points)
    seen = np.zeros((len(pts), len(ids)), bool)
    for k, (cam, dm) in enumerate(zip(cams, depth)):
        uv, z = cam.project(pts)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        col = np.clip(np.nan_to_num(uv[:, 0]).astype(np.int64), 0, cam.width - 1)
        row = np.clip(np.nan_to_num(uv[:, 1]).astype(np.int64), 0, cam.height - 1)
        there = dm[row, col]
        seen[:, k] = inside & (np.abs(there - z) <= DEPTH_TOL * np.maximum(z, 1e-6))
    counts = seen.sum(1)
    keep = counts > 0
    return _summarise(counts[keep], passes_of(seen[keep], times), "surface", looks_of(seen[keep], times, light_seconds))
