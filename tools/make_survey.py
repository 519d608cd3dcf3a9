"""Synthetic underwater seafloor survey with ground truth, rendered with Blender Cycles.

Builds a procedural seabed (displaced, textured terrain; rocks; a man-made structure: a
rusty pipe and a painted concrete block), flies a downward-looking camera over it in a
lawnmower pattern and renders every view twice: once with moving water caustics and once
without (the ground truth). It also writes the true camera poses and a sparse point cloud
as a COLMAP model, so the dataset can be used exactly like the output of SfM.

Usage (bpy as a Python module, or inside Blender)::

    python tools/make_survey.py --out data/sample --views 24 --width 256 --height 192 --seed 1
    blender -b --factory-startup --python tools/make_survey.py -- --out DIR [options]
    python tools/make_survey.py --out /tmp/survey --sfm   # also run pycolmap SfM on images/

Output folder::

    images/view_000.png ...   8-bit sRGB renders WITH caustics (what a camera would record)
    clean/view_000.png  ...   the same views under the caustics' mean illumination (ground truth)
    sparse/0/               COLMAP binary model (cameras.bin, images.bin, points3D.bin) with the
                            TRUE poses and PINHOLE intrinsics, and sparse points with tracks
    sfm/0/                  (only with --sfm) pycolmap's own reconstruction from images/
    survey.json             every parameter, the cameras, per-shot caustic phase and mean gain
    frames.json             (only with --caustic-motion smooth) each frame's time, as a video import writes it
    README.md               short description of the dataset and the caustic model

Caustic model
-------------
Caustics are the bright, moving network of light focused onto the seabed by the wavy water
surface. They are modelled as a multiplicative gain ``g(x, y; shot)`` on the light reaching the
seabed. For every shot a tileable texture ``T`` (``--caustic-res`` texels square, covering
``--caustic-scale`` metres) is generated in numpy (:func:`caustic_pattern`), softened by a
Gaussian of std ``--caustic-blur`` metres (finite sun disc and forward scattering), with ``T >= 0``
and ``mean(T) == 1`` over the texture, and turned into ``g = 1 + s * (T - 1)`` with the strength
``s = --caustic-strength`` in [0, 1] (:func:`caustic_gain`). Hence ``g >= 0`` and the mean gain
is exactly 1: caustics *redistribute* light, they do not add any. Every seabed material multiplies
its base colour by ``g`` looked up at the surface point projected along the sun direction onto
the plane z = 0 (world XY / tile size, repeating). The rendered linear radiance is then
``I_caustic(p) ~= g(p) * I_clean(p)`` (exact for direct and ambient light, approximate for
inter-reflections; as the gain sits in the albedo, it also shows in shadows, a simplification),
and ``clean/`` (g == 1) is the scene under the caustics' mean illumination: the target of caustic
removal. Between shots the pattern evolves in time (``--caustic-dt`` seconds per shot) and is
shifted by a random offset, as if each photo was taken at a different instant
(``--caustic-motion random``), or drifts smoothly with time as in a video (``--caustic-motion smooth``:
neighbouring frames share much of their light pattern).
Patterns (``--caustic-pattern``):

* ``refraction`` (default): physically motivated. A water surface height field (sum of travelling
  waves with integer wave vectors, so it tiles) refracts a uniform grid of light rays; the rays are
  binned onto the seabed (bilinear splatting, ``np.bincount``), giving the typical caustic network
  with cusps; peaks are softly limited (tanh) so that 8-bit images do not clip everywhere.
* ``waves``: the classic shader trick: bright ridges along the zero set of two sums of travelling
  sine waves.
* ``voronoi``: bright edges of a moving, domain-warped periodic Voronoi diagram.

The defaults (strength 0.45, 3 m tile, 3 cm blur) keep the caustics clearly visible while
pycolmap SfM still registers every view of the 256 x 192 sample; sharper, finer or stronger
caustics (e.g. ``--caustic-strength 0.6 --caustic-scale 1.5``) make SIFT matching on such small
images fail, as it does on real data with strong caustics.

Conventions: world frame is Blender's world frame (metres, z up). Poses are COLMAP
world-to-camera ``(R, t)``; the Blender camera matrix is built with
:func:`recgs_addon.core.model.cameras.blender_matrix_from_pose`. Intrinsics are PINHOLE with
``fx == fy`` and the principal point at exactly ``(width / 2, height / 2)`` (pixel centres at +0.5).
Images are converted from Cycles' linear EXR output with the plain sRGB transfer curve (the
"Standard" view transform) without dithering.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from recgs_addon.core.model.cameras import Camera, blender_matrix_from_pose, project_points  # noqa: E402

CAUSTIC_PATTERNS = ("refraction", "waves", "voronoi")


def log(msg: str) -> None:
    """Progress line (flushed, so it shows up promptly inside Blender too)."""
    print(f"[make_survey] {msg}", flush=True)


# ---------------------------------------------------------------------------------------------
# Caustic textures (pure numpy, no bpy)
# ---------------------------------------------------------------------------------------------

def _texel_grid(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates in tile units, arrays indexed [row, col] with row 0 at v = 0."""
    c = (np.arange(res) + 0.5) / res
    return np.meshgrid(c, c)


def _wavevectors(rng: np.random.Generator, n: int, kmin: float, kmax: float) -> np.ndarray:
    """``n`` distinct integer wave vectors (cycles per tile, so the field tiles) with kmin <= |k| <= kmax."""
    cand = np.array([(i, j) for i in range(-int(kmax), int(kmax) + 1)
                     for j in range(0, int(kmax) + 1) if (j > 0 or i > 0)], float)
    norm = np.hypot(cand[:, 0], cand[:, 1])
    cand = cand[(norm >= kmin) & (norm <= kmax)]
    k = cand[rng.choice(len(cand), size=n, replace=False)]
    return k * rng.choice([-1.0, 1.0], size=(n, 1))


def _pattern_waves(res: int, t: float, offset, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 1])
    k = _wavevectors(rng, 10, 2.0, 5.0)
    omega = 2 * np.pi * rng.uniform(0.3, 0.7, len(k)) * rng.choice([-1.0, 1.0], len(k))
    phi = rng.uniform(0, 2 * np.pi, len(k))
    X, Y = _texel_grid(res)
    X, Y = X + offset[0], Y + offset[1]
    out = np.full(X.shape, 0.15)
    for sel in (slice(0, 5), slice(5, 10)):
        arg = 2 * np.pi * (X[..., None] * k[sel, 0] + Y[..., None] * k[sel, 1]) + omega[sel] * t + phi[sel]
        s = np.sin(arg).sum(-1) / np.sqrt(5 / 2)
        out += np.exp(-(s / 0.22) ** 2)
    return out


def _pattern_voronoi(res: int, t: float, offset, seed: int, n_cells: int = 14,
                     width: float = 0.012) -> np.ndarray:
    rng = np.random.default_rng([seed, 2])
    p0 = rng.uniform(0, 1, (n_cells, 2))
    amp = rng.uniform(0.03, 0.07, (n_cells, 2))
    omega = 2 * np.pi * rng.uniform(0.2, 0.5, (n_cells, 2))
    phi = rng.uniform(0, 2 * np.pi, (n_cells, 2))
    p = p0 + amp * np.sin(omega * t + phi)
    kw = _wavevectors(rng, 4, 1.0, 3.0)
    pw = rng.uniform(0, 2 * np.pi, (4, 2))
    X, Y = _texel_grid(res)
    X, Y = X + offset[0], Y + offset[1]
    # periodic domain warp (integer wave vectors) for curved cell edges
    Xw = X + 0.025 * np.sin(2 * np.pi * (X[..., None] * kw[:, 0] + Y[..., None] * kw[:, 1])
                            + pw[:, 0] + 0.7 * t).sum(-1)
    Yw = Y + 0.025 * np.sin(2 * np.pi * (X[..., None] * kw[:, 1] - Y[..., None] * kw[:, 0])
                            + pw[:, 1] + 0.7 * t).sum(-1)
    dx = (Xw[..., None] - p[:, 0] + 0.5) % 1.0 - 0.5        # minimum-image (periodic) offsets
    dy = (Yw[..., None] - p[:, 1] + 0.5) % 1.0 - 0.5
    d2 = dx * dx + dy * dy
    two = np.argpartition(d2, 1, axis=-1)[..., :2]
    a, b = two[..., 0], two[..., 1]
    da = np.take_along_axis(d2, a[..., None], -1)[..., 0]
    db = np.take_along_axis(d2, b[..., None], -1)[..., 0]
    sep = (p[b] - p[a] + 0.5) % 1.0 - 0.5
    # exact distance to the bisector of the two nearest seeds
    edge = np.abs(db - da) / (2 * np.maximum(np.hypot(sep[..., 0], sep[..., 1]), 1e-6))
    return 0.2 + np.exp(-edge / width)


def _pattern_refraction(res: int, t: float, offset, seed: int, supersample: int = 3,
                        focus: float = 0.06, peak: float = 6.0) -> np.ndarray:
    rng = np.random.default_rng([seed, 3])
    k = _wavevectors(rng, 20, 2.0, 6.0)
    kn = np.hypot(k[:, 0], k[:, 1])
    amp = kn ** -1.5
    omega = 2 * np.pi * 0.35 * np.sqrt(kn) * rng.choice([-1.0, 1.0], len(k))   # dispersive waves
    phi = rng.uniform(0, 2 * np.pi, len(k))
    n = res * supersample
    c = (np.arange(n) + 0.5) / n
    theta = 2 * np.pi * (offset[0] * k[:, 0] + offset[1] * k[:, 1]) + omega * t + phi
    # surface slope (up to a constant); cos(a + b) = cos a cos b - sin a sin b keeps it separable
    gx = np.zeros((n, n))
    gy = np.zeros((n, n))
    for j in range(len(k)):
        ax = 2 * np.pi * k[j, 0] * c
        by = 2 * np.pi * k[j, 1] * c + theta[j]
        cs = np.outer(np.cos(by), np.cos(ax)) - np.outer(np.sin(by), np.sin(ax))   # [row=y, col=x]
        gx += amp[j] * k[j, 0] * cs
        gy += amp[j] * k[j, 1] * cs
    X, Y = np.meshgrid(c, c)
    g = np.sqrt(np.mean(gx ** 2 + gy ** 2))
    px = (X + focus * gx / g) * res - 0.5                 # where each refracted ray lands (texels)
    py = (Y + focus * gy / g) * res - 0.5
    x0, y0 = np.floor(px), np.floor(py)
    fx, fy = px - x0, py - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    acc = np.zeros(res * res)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                      (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        idx = ((y0 + dy) % res) * res + (x0 + dx) % res
        acc += np.bincount(idx.ravel(), weights=w.ravel(), minlength=res * res)
    img = np.maximum(periodic_blur(acc.reshape(res, res), 0.7), 0.0)   # removes photon noise
    img /= img.mean()
    return peak * np.tanh(img / peak)                     # soft limit of the cusps


def periodic_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (std ``sigma`` texels) of a tileable square image, via FFT (mean preserved)."""
    if sigma <= 0:
        return img
    f = np.fft.fftfreq(img.shape[0])
    kernel = np.exp(-2 * (np.pi * sigma) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    return np.real(np.fft.ifft2(np.fft.fft2(img) * kernel))


def caustic_pattern(kind: str, res: int, t: float, offset=(0.0, 0.0), seed: int = 0,
                    blur: float = 0.0) -> np.ndarray:
    """Tileable caustic light pattern ``T`` (res x res, float64) at time ``t`` (seconds).

    The texture covers one tile ([0, 1)^2 in tile units), indexed ``[row, col]`` with row 0 at
    v = 0 (Blender's pixel order). ``offset`` (tile units) shifts the pattern; ``blur`` (tile
    units, Gaussian std) softens it, as the finite sun disc and forward scattering do with depth.
    Always ``T >= 0`` and ``T.mean() == 1`` (to float64 rounding).
    """
    funcs = {"refraction": _pattern_refraction, "waves": _pattern_waves, "voronoi": _pattern_voronoi}
    if kind not in funcs:
        raise ValueError(f"unknown caustic pattern {kind!r}, choose from {CAUSTIC_PATTERNS}")
    T = np.maximum(funcs[kind](int(res), float(t), offset, int(seed)), 0.0)
    T = np.maximum(periodic_blur(T, blur * res), 0.0)
    return T / T.mean()


def caustic_gain(kind: str, res: int, t: float, offset=(0.0, 0.0), seed: int = 0,
                 strength: float = 0.6, blur: float = 0.0) -> np.ndarray:
    """Caustic gain ``g = 1 + strength * (T - 1)`` (float32, res x res) with ``mean(g) == 1``, ``g >= 0``.

    ``strength`` must lie in [0, 1] so that the gain stays non-negative; 0 gives all ones.
    """
    if not 0.0 <= strength <= 1.0:
        raise ValueError("caustic strength must be in [0, 1]")
    if strength == 0.0:
        return np.ones((res, res), np.float32)
    T = caustic_pattern(kind, res, t, offset, seed, blur)
    g = 1.0 + strength * (T - 1.0)
    g /= g.mean()                                         # exact in float64 already; keep it so
    return g.astype(np.float32)


def caustic_shots(n: int, seed: int, dt: float, motion: str = "random", drift=(0.01, 0.004)) -> list[dict]:
    """Per-shot caustic phase: time ``t = i * dt`` (s) and an offset in tile units.

    ``motion="random"``: a random offset per shot, as photos taken at unrelated instants
    (each shot's light independent of the last). ``"smooth"``: as a video, the pattern drifts
    with the waves at ``drift`` tile units per second from one random start, so each frame's
    light is a small step from the last (neighbouring frames share much of their pattern)."""
    rng = np.random.default_rng([seed, 7])
    if motion == "smooth":
        start = rng.uniform(0, 1, 2)
        offsets = start + np.outer(np.arange(n) * dt, np.asarray(drift, float))
    elif motion == "random":
        offsets = rng.uniform(0, 1, (n, 2))
    else:
        raise ValueError(f"unknown caustic motion {motion!r} (random or smooth)")
    return [{"time_s": i * dt, "offset": [float(offsets[i, 0]), float(offsets[i, 1])]} for i in range(n)]


# ---------------------------------------------------------------------------------------------
# Terrain, cameras, image maths (numpy)
# ---------------------------------------------------------------------------------------------

class Heightfield:
    """Smooth random seabed height z = h(x, y) (metres): Fourier modes plus a few mounds/hollows."""

    def __init__(self, rng: np.random.Generator, extent: tuple[float, float]):
        n = 12
        wl = rng.uniform(1.5, 8.0, n)
        ang = rng.uniform(0, np.pi, n)
        self.k = (2 * np.pi / wl)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        self.a = 0.018 * wl ** 0.9 * rng.uniform(0.5, 1.0, n)
        self.phi = rng.uniform(0, 2 * np.pi, n)
        m = 4
        self.mc = rng.uniform(-0.35, 0.35, (m, 2)) * np.asarray(extent)
        self.ma = rng.uniform(0.12, 0.3, m) * rng.choice([-1.0, 1.0], m)
        self.ms = rng.uniform(0.6, 1.4, m)

    def __call__(self, x, y) -> np.ndarray:
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        z = (self.a * np.sin(x[..., None] * self.k[:, 0] + y[..., None] * self.k[:, 1] + self.phi)).sum(-1)
        r2 = (x[..., None] - self.mc[:, 0]) ** 2 + (y[..., None] - self.mc[:, 1]) ** 2
        return z + (self.ma * np.exp(-r2 / (2 * self.ms ** 2))).sum(-1)

    def mean_around(self, x, y, radius: float) -> np.ndarray:
        """Height averaged over a (2 radius)^2 square around each (x, y) (what an altimeter tracks)."""
        o = np.linspace(-radius, radius, 5)
        ox, oy = np.meshgrid(o, o)
        return self(np.asarray(x)[..., None] + ox.ravel(), np.asarray(y)[..., None] + oy.ravel()).mean(-1)


def intrinsics(width: int, height: int, hfov_deg: float) -> tuple[float, float, float, float]:
    """PINHOLE (fx, fy, cx, cy) with square pixels and the principal point at the image centre."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return f, f, width / 2.0, height / 2.0


def _rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(v))
    if th < 1e-12:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def lawnmower_layout(views: int, footprint_along: float, footprint_across: float,
                     overlap: float, sidelap: float, lines: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Serpentine survey lines along world +x / -x (``lines`` of them; 0: about sqrt(views / 3)).

    Returns (xy (views, 2) nadir positions in shooting order, heading (views,) radians, info).
    """
    n_lines = lines if lines > 0 else max(1, int(round(math.sqrt(views / 3.0))))
    per_line = math.ceil(views / n_lines)
    ds = (1 - overlap) * footprint_along
    dl = (1 - sidelap) * footprint_across
    xy, heading = [], []
    for li in range(n_lines):
        ys = (li - (n_lines - 1) / 2) * dl
        xs = (np.arange(per_line) - (per_line - 1) / 2) * ds
        fwd = li % 2 == 0
        for x in (xs if fwd else xs[::-1]):
            if len(xy) < views:
                xy.append((x, ys))
                heading.append(0.0 if fwd else math.pi)
    info = {"lines": n_lines, "per_line": per_line, "along_spacing_m": ds, "line_spacing_m": dl}
    return np.array(xy), np.array(heading), info


def wander_layout(views: int, footprint_along: float, footprint_across: float, overlap: float,
                  seed: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """A diver's wandering track: a smooth random curve that loops back over the same seabed
    (two sums of sines in x and y), views equally spaced along it, heading along the track.

    The spacing is ``(1 - overlap)`` of the footprint along the track; the track spans about
    three footprints each way, so it crosses itself and each seabed point is filmed at several
    passes, minutes apart."""
    rng = np.random.default_rng([seed, 13])
    ds = (1 - overlap) * footprint_along
    length = ds * max(views - 1, 1)
    amp = 1.5 * np.array([footprint_across, footprint_along])
    f = rng.uniform(0.6, 1.4, 4) * np.array([1.0, 2.1, 1.3, 2.9])
    ph = rng.uniform(0, 2 * np.pi, 4)
    u = np.linspace(0.0, 2 * np.pi * max(1.0, length / (4 * amp.mean())), 20000)
    x = amp[0] * (0.7 * np.sin(f[0] * u + ph[0]) + 0.3 * np.sin(f[1] * u + ph[1]))
    y = amp[1] * (0.7 * np.sin(f[2] * u + ph[2]) + 0.3 * np.sin(f[3] * u + ph[3]))
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    arc *= length / arc[-1]                       # the curve's length is the track's
    s = np.arange(views) * ds
    xs, ys = np.interp(s, arc, x), np.interp(s, arc, y)
    dx, dy = np.gradient(xs), np.gradient(ys)
    info = {"lines": 0, "per_line": views, "along_spacing_m": ds, "line_spacing_m": 0.0, "track_m": length}
    return np.stack([xs, ys], 1), np.arctan2(dy, dx), info


def make_cameras(args, hf: Heightfield) -> tuple[list[Camera], dict]:
    """Survey cameras (COLMAP convention) flying a lawnmower pattern (or a wandering track) at
    ``args.altitude`` above the seabed."""
    fx, fy, cx, cy = intrinsics(args.width, args.height, args.hfov)
    across = 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)   # image width on the ground
    along = across * args.height / args.width
    if args.path == "wander":
        xy, heading, info = wander_layout(args.views, along, across, args.overlap, args.seed)
    else:
        xy, heading, info = lawnmower_layout(args.views, along, across, args.overlap, args.sidelap, args.lines)
    rng = np.random.default_rng([args.seed, 11])
    z = hf.mean_around(xy[:, 0], xy[:, 1], 0.8) + args.altitude + rng.normal(0, 0.05, len(xy))
    cams = []
    pitch = math.radians(args.pitch)
    for i, ((x, y), psi, zc) in enumerate(zip(xy, heading, z)):
        d = np.array([math.cos(psi), math.sin(psi), 0.0])        # direction of travel
        zc_axis = math.cos(pitch) * np.array([0.0, 0.0, -1.0]) + math.sin(pitch) * d   # optical axis
        x_axis = np.cross(d, [0.0, 0.0, 1.0])                      # image right (horizontal)
        y_axis = np.cross(zc_axis, x_axis)                         # image down
        R0 = np.stack([x_axis, y_axis, zc_axis])                   # rows: camera axes in world
        jitter = _rotvec_to_matrix(np.radians(rng.normal(0, args.jitter_deg, 3)))
        R = jitter @ R0
        C = np.array([x, y, zc])
        cams.append(Camera(f"view_{i:03d}.png", args.width, args.height, fx, fy, cx, cy,
                           R, -R @ C, camera_id=1, image_id=i + 1))
    info.update({"footprint_across_m": across, "footprint_along_m": along})
    return cams, info


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> 8-bit sRGB (IEC 61966-2-1 curve, clipped, rounded; 'Standard' view)."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def visible_in_view(points: np.ndarray, cam: Camera, depth: np.ndarray, tol: float):
    """Depth-tested visibility of world points in one view.

    Returns (visible (N,) bool, uv (N, 2)). A point is visible when it projects inside the image
    and its camera-space z agrees with the rendered z depth at its pixel within ``tol`` metres.
    """
    uv, z = project_points(points, cam.R, cam.t, cam.K)
    inside = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    col = np.clip(np.floor(np.nan_to_num(uv[:, 0])).astype(np.int64), 0, cam.width - 1)
    row = np.clip(np.floor(np.nan_to_num(uv[:, 1])).astype(np.int64), 0, cam.height - 1)
    vis = inside & (np.abs(depth[row, col] - z) < tol)
    return vis, uv


def sample_triangles(tris: np.ndarray, weights: np.ndarray, n: int, rng: np.random.Generator):
    """Sample ``n`` points on triangles (T, 3, 3) with probability proportional to ``weights``.

    Returns (points (n, 3), triangle index (n,)).
    """
    p = weights / weights.sum()
    idx = rng.choice(len(tris), size=n, p=p)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = 1 - s, s * (1 - r2), s * r2
    T = tris[idx]
    return a[:, None] * T[:, 0] + b[:, None] * T[:, 1] + c[:, None] * T[:, 2], idx


# ---------------------------------------------------------------------------------------------
# Blender scene (bpy imported lazily so that the numpy parts can be used and tested without it)
# ---------------------------------------------------------------------------------------------

def _bpy():
    import bpy  # noqa: WPS433
    return bpy


class NodeBuilder:
    """Tiny helper to build shader node trees: arguments may be sockets or constants."""

    def __init__(self, tree):
        self.tree = tree
        self.nodes = tree.nodes
        self.links = tree.links

    def node(self, kind: str, **props):
        n = self.nodes.new(kind)
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def _set(self, sock, value):
        if hasattr(value, "is_output"):  # a socket
            self.links.new(value, sock)
        elif value is not None:
            sock.default_value = value

    @staticmethod
    def _sock(sockets, identifier):
        return next(s for s in sockets if s.identifier == identifier)

    def coords(self, kind: str = "Object"):
        return self.node("ShaderNodeTexCoord").outputs[kind]

    def position(self):
        return self.node("ShaderNodeNewGeometry").outputs["Position"]

    def noise(self, vec, scale, detail=2.0, rough=0.5, distortion=0.0, out="Fac"):
        n = self.node("ShaderNodeTexNoise")
        for name, v in (("Vector", vec), ("Scale", scale), ("Detail", detail), ("Roughness", rough),
                        ("Distortion", distortion)):
            self._set(n.inputs[name], v)
        return n.outputs[out]

    def voronoi(self, vec, scale, feature="F1", out="Distance", randomness=1.0):
        n = self.node("ShaderNodeTexVoronoi", feature=feature)
        self._set(n.inputs["Vector"], vec)
        self._set(n.inputs["Scale"], scale)
        self._set(n.inputs["Randomness"], randomness)
        return n.outputs[out]

    def wave(self, vec, scale, distortion=4.0, detail=2.0, direction="X"):
        n = self.node("ShaderNodeTexWave", wave_type="BANDS", bands_direction=direction)
        for name, v in (("Vector", vec), ("Scale", scale), ("Distortion", distortion), ("Detail", detail)):
            self._set(n.inputs[name], v)
        return n.outputs["Fac"]

    def ramp(self, fac, stops, interpolation="LINEAR"):
        n = self.node("ShaderNodeValToRGB")
        cr = n.color_ramp
        cr.interpolation = interpolation
        while len(cr.elements) < len(stops):
            cr.elements.new(0.5)
        for el, (pos, col) in zip(cr.elements, stops):
            el.position = pos
            el.color = (*col, 1.0) if len(col) == 3 else col
        self._set(n.inputs["Fac"], fac)
        return n.outputs["Color"]

    def mix(self, fac, a, b, blend="MIX"):
        n = self.node("ShaderNodeMix", data_type="RGBA", blend_type=blend)
        self._set(self._sock(n.inputs, "Factor_Float"), fac)
        self._set(self._sock(n.inputs, "A_Color"), a)
        self._set(self._sock(n.inputs, "B_Color"), b)
        return self._sock(n.outputs, "Result_Color")

    def math(self, op, a, b=None, c=None, clamp=False):
        n = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        for i, v in enumerate((a, b, c)):
            self._set(n.inputs[i], v)
        return n.outputs[0]

    def vmul(self, a, b):
        n = self.node("ShaderNodeVectorMath", operation="MULTIPLY")
        self._set(n.inputs[0], a)
        self._set(n.inputs[1], b)
        return n.outputs[0]

    def map_range(self, x, fmin, fmax, tmin, tmax, clamp=True):
        n = self.node("ShaderNodeMapRange", clamp=clamp)
        for i, v in enumerate((x, fmin, fmax, tmin, tmax)):
            self._set(n.inputs[i], v)
        return n.outputs[0]

    def bump(self, height, strength, distance, normal=None):
        n = self.node("ShaderNodeBump")
        self._set(n.inputs["Height"], height)
        self._set(n.inputs["Strength"], strength)
        self._set(n.inputs["Distance"], distance)
        self._set(n.inputs["Normal"], normal)
        return n.outputs["Normal"]


@dataclass
class CausticRig:
    """Handles to switch the caustics in every seabed material (one shared node group)."""

    group: object
    image_node: object
    enable_node: object
    images: list = field(default_factory=list)

    def set_shot(self, index: int | None) -> None:
        """Caustics of shot ``index`` on, or off (gain identically 1) when ``index`` is None."""
        if index is None:
            self.enable_node.outputs[0].default_value = 0.0
        else:
            self.image_node.image = self.images[index]
            self.enable_node.outputs[0].default_value = 1.0


def build_caustic_group(light_dir: np.ndarray, tile: float):
    """Node group 'CausticGain' -> float gain = 1 + enable * (texture(p projected along sun) - 1)."""
    bpy = _bpy()
    grp = bpy.data.node_groups.new("CausticGain", "ShaderNodeTree")
    grp.interface.new_socket("Gain", in_out="OUTPUT", socket_type="NodeSocketFloat")
    nb = NodeBuilder(grp)
    sep = nb.node("ShaderNodeSeparateXYZ")
    nb.links.new(nb.position(), sep.inputs[0])
    lx, ly, lz = (float(v) for v in light_dir)
    # point projected along the light direction onto z = 0, in tile units
    u = nb.math("MULTIPLY", nb.math("MULTIPLY_ADD", sep.outputs["Z"], -lx / lz, sep.outputs["X"]), 1.0 / tile)
    v = nb.math("MULTIPLY", nb.math("MULTIPLY_ADD", sep.outputs["Z"], -ly / lz, sep.outputs["Y"]), 1.0 / tile)
    comb = nb.node("ShaderNodeCombineXYZ")
    nb.links.new(u, comb.inputs[0])
    nb.links.new(v, comb.inputs[1])
    img = nb.node("ShaderNodeTexImage", interpolation="Linear", extension="REPEAT")
    nb.links.new(comb.outputs[0], img.inputs["Vector"])
    enable = nb.node("ShaderNodeValue")
    enable.outputs[0].default_value = 1.0
    red = nb.node("ShaderNodeSeparateColor")                 # the texture is grey: R = G = B = T
    nb.links.new(img.outputs["Color"], red.inputs[0])
    tex = nb.math("SUBTRACT", red.outputs[0], 1.0)
    gain = nb.math("MULTIPLY_ADD", tex, enable.outputs[0], 1.0)
    out = nb.node("NodeGroupOutput")
    nb.links.new(gain, out.inputs[0])
    return CausticRig(grp, img, enable)


def add_caustic_images(rig: CausticRig, gains: list[np.ndarray]) -> list[dict]:
    """One float, non-colour Blender image per shot; returns the measured stats of each texture."""
    bpy = _bpy()
    stats = []
    for i, g in enumerate(gains):
        res = g.shape[0]
        im = bpy.data.images.new(f"caustic_{i:03d}", res, res, alpha=False, float_buffer=True, is_data=True)
        rgba = np.repeat(g[..., None], 4, axis=-1).astype(np.float32)
        rgba[..., 3] = 1.0
        im.pixels.foreach_set(rgba.ravel())
        im.update()
        back = np.empty(res * res * 4, np.float32)
        im.pixels.foreach_get(back)
        back = back.reshape(res, res, 4)[..., 0].astype(np.float64)
        stats.append({"mean_gain": float(back.mean()), "min_gain": float(back.min()),
                      "max_gain": float(back.max())})
        rig.images.append(im)
    return stats


def _seabed_material(name: str, rig: CausticRig, build) -> object:
    """Material whose base colour (from ``build(nb) -> (colour, roughness, normal)``) is x caustic gain."""
    bpy = _bpy()
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    nb = NodeBuilder(nt)
    colour, rough, normal = build(nb)
    g = nb.node("ShaderNodeGroup")
    g.node_tree = rig.group
    base = nb.vmul(colour, g.outputs[0])
    bsdf = nb.node("ShaderNodeBsdfPrincipled")
    nb._set(bsdf.inputs["Base Color"], base)
    nb._set(bsdf.inputs["Roughness"], rough)
    nb._set(bsdf.inputs["Specular IOR Level"], 0.25)
    nb._set(bsdf.inputs["Normal"], normal)
    out = nb.node("ShaderNodeOutputMaterial")
    nb.links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat


def sand_material(rig: CausticRig, seed: int):
    """Sand / sediment: patchy colours, pebbles with dark crevices, grain, detritus, ripples."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        w = float(seed % 97) * 1.7
        shifted = nb.node("ShaderNodeVectorMath", operation="ADD")
        nb.links.new(p, shifted.inputs[0])
        shifted.inputs[1].default_value = (w, -w, 0.0)
        p = shifted.outputs[0]
        base = nb.ramp(nb.noise(p, 0.45, detail=3, rough=0.55), [
            (0.25, (0.33, 0.26, 0.15)), (0.45, (0.62, 0.52, 0.33)),
            (0.62, (0.74, 0.66, 0.47)), (0.80, (0.50, 0.48, 0.37))])
        # gravel: per-pebble brightness and dark crevices; dense in patches, sparse elsewhere
        cell = nb.node("ShaderNodeRGBToBW")
        nb.links.new(nb.voronoi(p, 16.0, out="Color"), cell.inputs[0])
        pebble = nb.vmul(base, nb.map_range(cell.outputs[0], 0.0, 1.0, 0.2, 1.7))
        crev = nb.map_range(nb.voronoi(p, 16.0, feature="DISTANCE_TO_EDGE"), 0.0, 0.06, 0.25, 1.0)
        pebble = nb.vmul(pebble, crev)
        mask = nb.map_range(nb.noise(p, 0.9, detail=3), 0.40, 0.58, 0.3, 1.0)
        col = nb.mix(mask, base, pebble)
        # fine grain
        col = nb.vmul(col, nb.map_range(nb.noise(p, 45.0, detail=2), 0.3, 0.7, 0.7, 1.25))
        # shell fragments (bright) and dark grains: small blobs at a random subset of cell centres
        sv = nb.node("ShaderNodeTexVoronoi", feature="F1")
        nb.links.new(p, sv.inputs["Vector"])
        sv.inputs["Scale"].default_value = 12.0
        sbw = nb.node("ShaderNodeRGBToBW")
        nb.links.new(sv.outputs["Color"], sbw.inputs[0])
        blob = nb.map_range(sv.outputs["Distance"], 0.25, 0.32, 1.0, 0.0)
        bright = nb.math("MULTIPLY", blob, nb.map_range(sbw.outputs[0], 0.70, 0.72, 0.0, 1.0))
        dark = nb.math("MULTIPLY", blob, nb.map_range(sbw.outputs[0], 0.30, 0.28, 0.0, 1.0))
        col = nb.mix(bright, col, (0.92, 0.90, 0.84, 1.0))
        col = nb.mix(dark, col, (0.04, 0.04, 0.03, 1.0))
        # dark detritus / algae patches
        spots = nb.map_range(nb.noise(p, 2.6, detail=3, rough=0.6), 0.56, 0.66, 0.0, 0.85)
        col = nb.mix(spots, col, (0.10, 0.13, 0.06, 1.0))
        # sand ripples: shading + slight colour modulation
        rip = nb.wave(p, 5.2, distortion=5.0, detail=3.0)
        col = nb.vmul(col, nb.map_range(rip, 0.0, 1.0, 0.85, 1.1))
        height = nb.math("MULTIPLY_ADD", nb.noise(p, 25.0, detail=2), 0.5, rip)   # ripples + grain
        normal = nb.bump(height, 0.4, 0.015)
        return col, 0.9, normal
    return _seabed_material("Sand", rig, build)


def rock_material(rig: CausticRig, name: str, palette, crust):
    """Rough mottled rock with cracks, speckle and an encrusting-growth colour."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        col = nb.ramp(nb.noise(p, 2.5, detail=4, rough=0.6, distortion=0.3),
                      [(0.3, palette[0]), (0.5, palette[1]), (0.7, palette[2])])
        col = nb.vmul(col, nb.map_range(nb.noise(p, 30.0, detail=2), 0.3, 0.7, 0.7, 1.25))
        cracks = nb.map_range(nb.voronoi(p, 5.0, feature="DISTANCE_TO_EDGE"), 0.0, 0.04, 0.25, 1.0)
        col = nb.vmul(col, cracks)
        growth = nb.map_range(nb.noise(p, 3.5, detail=4), 0.55, 0.62, 0.0, 0.9)
        col = nb.mix(growth, col, (*crust, 1.0))
        h = nb.noise(p, 8.0, detail=4, rough=0.65)
        return col, 0.85, nb.bump(h, 0.6, 0.05)
    return _seabed_material(name, rig, build)


def rust_material(rig: CausticRig):
    """Rusty steel pipe with flaking rust and fouling."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        col = nb.ramp(nb.noise(p, 4.0, detail=6, rough=0.6), [
            (0.3, (0.16, 0.07, 0.03)), (0.5, (0.45, 0.18, 0.05)), (0.7, (0.62, 0.32, 0.10))])
        flakes = nb.map_range(nb.voronoi(p, 14.0, out="Distance"), 0.0, 0.5, 0.5, 1.2)
        col = nb.vmul(col, flakes)
        foul = nb.map_range(nb.noise(p, 2.0, detail=4), 0.55, 0.62, 0.0, 0.8)
        col = nb.mix(foul, col, (0.20, 0.28, 0.12, 1.0))
        h = nb.noise(p, 20.0, detail=3)
        return col, 0.7, nb.bump(h, 0.4, 0.02)
    return _seabed_material("Rust", rig, build)


def concrete_material(rig: CausticRig):
    """Concrete block with a painted yellow stripe, stains and pitting."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        sep = nb.node("ShaderNodeSeparateXYZ")
        nb.links.new(p, sep.inputs[0])
        col = nb.ramp(nb.noise(p, 6.0, detail=5), [(0.35, (0.30, 0.29, 0.26)), (0.65, (0.50, 0.48, 0.44))])
        pits = nb.map_range(nb.voronoi(p, 40.0, out="Distance"), 0.0, 0.15, 0.4, 1.0)
        col = nb.vmul(col, pits)
        stripe = nb.math("LESS_THAN", nb.math("ABSOLUTE", sep.outputs["X"]), 0.12)
        worn = nb.math("MULTIPLY", stripe, nb.map_range(nb.noise(p, 12.0, detail=3), 0.35, 0.5, 0.2, 1.0))
        col = nb.mix(worn, col, (0.85, 0.62, 0.05, 1.0))
        stain = nb.map_range(nb.noise(p, 3.0, detail=4), 0.56, 0.64, 0.0, 0.7)
        col = nb.mix(stain, col, (0.15, 0.17, 0.08, 1.0))
        return col, 0.9, nb.bump(nb.noise(p, 25.0, detail=3), 0.3, 0.01)
    return _seabed_material("Concrete", rig, build)


def mesh_object(name: str, verts: np.ndarray, faces: np.ndarray, material, smooth: bool = False,
                matrix=None):
    """Create and link a mesh object from numpy vertices (V, 3) and faces (F, k) (foreach_set, no loops)."""
    bpy = _bpy()
    me = bpy.data.meshes.new(name)
    nv, (nf, k) = len(verts), faces.shape
    me.vertices.add(nv)
    me.vertices.foreach_set("co", np.asarray(verts, np.float32).ravel())
    me.loops.add(nf * k)
    me.loops.foreach_set("vertex_index", np.asarray(faces, np.int32).ravel())
    me.polygons.add(nf)
    me.polygons.foreach_set("loop_start", np.arange(0, nf * k, k, dtype=np.int32))
    me.polygons.foreach_set("use_smooth", np.full(nf, smooth, bool))
    me.update(calc_edges=True)
    me.validate()
    me.materials.append(material)
    ob = bpy.data.objects.new(name, me)
    if matrix is not None:
        import mathutils
        ob.matrix_world = mathutils.Matrix(np.asarray(matrix).tolist())
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _bmesh_arrays(make) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangle faces of a bmesh primitive built by ``make(bm)``."""
    import bmesh
    bpy = _bpy()
    bm = bmesh.new()
    make(bm)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    me = bpy.data.meshes.new("_primitive")
    bm.to_mesh(me)
    bm.free()
    verts = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", verts)
    faces = np.empty(len(me.polygons) * 3, np.int32)
    me.polygons.foreach_get("vertices", faces)
    bpy.data.meshes.remove(me)
    return verts.reshape(-1, 3).astype(np.float64), faces.reshape(-1, 3)


def make_terrain(hf: Heightfield, size: tuple[float, float], spacing: float, material):
    nx, ny = int(round(size[0] / spacing)) + 1, int(round(size[1] / spacing)) + 1
    x = np.linspace(-size[0] / 2, size[0] / 2, nx)
    y = np.linspace(-size[1] / 2, size[1] / 2, ny)
    X, Y = np.meshgrid(x, y)
    verts = np.stack([X, Y, hf(X, Y)], -1).reshape(-1, 3)
    i = np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]
    faces = np.stack([i, i + 1, i + nx + 1, i + nx], -1).reshape(-1, 4)
    return mesh_object("Terrain", verts, faces, material, smooth=True)


def make_rock(name: str, rng: np.random.Generator, center_xy, radius: float, hf: Heightfield, material):
    import bmesh
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_icosphere(bm, subdivisions=4, radius=1.0))
    n = verts / np.linalg.norm(verts, axis=1, keepdims=True)
    m = 16
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    freq = rng.uniform(1.5, 12.0, m)
    r = 1 + ((0.2 / freq ** 0.8) * np.sin(freq * (n @ d.T) * 2 + rng.uniform(0, 6.3, m))).sum(-1)
    planes = rng.normal(size=(4, 3))
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    r = np.minimum(r, (0.85 / np.maximum(n @ planes.T, 1e-3)).min(-1))   # a few flat fracture faces
    scale = radius * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.45, 0.75)])
    v = n * r[:, None] * scale
    ang = rng.uniform(0, 2 * np.pi)
    Rz = np.array([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]])
    ground = float(hf.mean_around(center_xy[0], center_xy[1], radius * 0.7))
    M = np.eye(4)
    M[:3, :3] = Rz
    M[:3, 3] = (center_xy[0], center_xy[1], ground + 0.15 * scale[2])
    return mesh_object(name, v, faces, material, smooth=True, matrix=M)


def make_structure(rng: np.random.Generator, center_xy, hf: Heightfield, mat_rust, mat_concrete):
    """Man-made debris: a rusty pipe segment resting next to a concrete block with a painted stripe.

    Returns (objects, discs (K, 3) covering the footprint as centre x, y and radius).
    """
    import bmesh
    ang = rng.uniform(0, np.pi)
    cz = math.cos(ang)
    sz = math.sin(ang)
    # pipe: cylinder along its local z, laid along direction ang
    radius, length = 0.11, 2.0
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_cone(
        bm, cap_ends=True, segments=32, radius1=radius, radius2=radius, depth=length))
    dirv = np.array([cz, sz, 0.0])
    Rp = np.stack([np.array([-sz, cz, 0.0]), np.array([0.0, 0.0, 1.0]), dirv], 1)   # local z -> dirv
    along = np.linspace(-length / 2, length / 2, 9)
    px = center_xy[0] + along * cz + 0.45 * -sz
    py = center_xy[1] + along * sz + 0.45 * cz
    M = np.eye(4)
    M[:3, :3] = Rp
    M[:3, 3] = (px.mean(), py.mean(), float(hf(px, py).mean()) + 0.5 * radius)
    pipe = mesh_object("Pipe", verts, faces, mat_rust, smooth=True, matrix=M)
    # block, rotated a bit relative to the pipe
    bx, by, bz = 0.8, 0.55, 0.4
    verts, faces = _bmesh_arrays(lambda bm: bmesh.ops.create_cube(bm, size=1.0))
    verts = verts * np.array([bx, by, bz])
    a2 = ang + rng.uniform(-0.4, 0.4)
    Rb = np.array([[math.cos(a2), -math.sin(a2), 0], [math.sin(a2), math.cos(a2), 0], [0, 0, 1]])
    cx, cy = center_xy[0] - 0.35 * -sz, center_xy[1] - 0.35 * cz
    ground = float(hf.mean_around(cx, cy, 0.4))
    M = np.eye(4)
    M[:3, :3] = Rb
    M[:3, 3] = (cx, cy, ground + bz / 2 - 0.1)
    block = mesh_object("ConcreteBlock", verts, faces, mat_concrete, smooth=False, matrix=M)
    # footprint as discs (centre x, y, radius) so that rocks can be kept clear of it
    discs = np.concatenate([np.stack([px, py, np.full_like(px, radius + 0.05)], 1),
                            [[cx, cy, 0.5 * math.hypot(bx, by)]]])
    return [pipe, block], discs


def light_direction(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit direction in which sunlight travels (downwards), tilted from vertical."""
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), -math.cos(t)])


def setup_lighting(light_dir: np.ndarray, args) -> None:
    """Sun along ``light_dir`` plus a blue-green ambient world (no volumetrics)."""
    bpy = _bpy()
    import mathutils
    sun = bpy.data.lights.new("Sun", "SUN")
    sun.energy = args.sun_strength
    sun.color = (0.85, 0.97, 1.0)
    sun.angle = math.radians(2.0)
    ob = bpy.data.objects.new("Sun", sun)
    ob.rotation_euler = mathutils.Vector((-light_dir).tolist()).to_track_quat("Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(ob)
    world = bpy.data.worlds.new("Water")
    nt = world.node_tree
    bg = nt.nodes.get("Background") or nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.06, 0.24, 0.27, 1.0)
    bg.inputs["Strength"].default_value = args.ambient_strength
    out = nt.nodes.get("World Output") or nt.nodes.new("ShaderNodeOutputWorld")
    if not bg.outputs[0].links:
        nt.links.new(bg.outputs[0], out.inputs["Surface"])
    bpy.context.scene.world = world


def configure_render(args) -> bool:
    """Cycles on the CPU, few samples + OIDN when the build has it, deterministic seed, colour and
    depth written by the compositor as float EXRs. Returns whether denoising is on."""
    bpy = _bpy()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = args.samples
    cy.use_adaptive_sampling = False
    cy.seed = args.seed
    cy.use_animated_seed = False
    cy.max_bounces = args.bounces
    cy.diffuse_bounces = args.bounces
    cy.glossy_bounces = min(1, args.bounces)
    cy.transmission_bounces = 0
    cy.volume_bounces = 0
    cy.transparent_max_bounces = 2
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    denoise = False
    if args.denoise:
        try:
            import _cycles
            if getattr(_cycles, "with_openimagedenoise", False):
                cy.use_denoising = True
                cy.denoiser = "OPENIMAGEDENOISE"
                cy.denoising_prefilter = args.denoise_prefilter
                cy.denoising_quality = args.denoise_quality
                denoise = True
        except Exception as exc:  # pragma: no cover - depends on the Blender build
            log(f"denoiser unavailable ({exc}); rendering without")
    if not denoise:
        cy.use_denoising = False
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = args.width, args.height, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.threads_mode = "FIXED"
    r.threads = max(1, args.threads)
    r.use_persistent_data = True
    r.film_transparent = False
    r.dither_intensity = 0.0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = True
    setup_compositor_outputs(scene)
    return denoise


def add_camera(cam0: Camera):
    """Blender camera with PINHOLE intrinsics equal to ``cam0`` (sensor fit horizontal, no shift)."""
    bpy = _bpy()
    cd = bpy.data.cameras.new("SurveyCam")
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.lens_unit = "MILLIMETERS"
    cd.lens = cam0.fx * cd.sensor_width / cam0.width
    cd.shift_x = cd.shift_y = 0.0
    cd.clip_start, cd.clip_end = 0.05, 200.0
    ob = bpy.data.objects.new("SurveyCam", cd)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.scene.camera = ob
    return ob


def set_camera_pose(ob, cam: Camera) -> None:
    import mathutils
    ob.matrix_world = mathutils.Matrix(blender_matrix_from_pose(cam.R, cam.t).tolist())


def setup_compositor_outputs(scene) -> None:
    """Compositor writing the denoised linear colour and the z-depth pass as float EXRs.

    (Blender 5.0 does not put the depth pass into a render written with ``write_still`` and drops
    non-colour inputs of a multilayer File Output node, so two single-layer outputs are used.)
    """
    bpy = _bpy()
    ng = bpy.data.node_groups.new("SurveyOutputs", "CompositorNodeTree")
    scene.compositing_node_group = ng
    scene.render.use_compositing = True
    rl = ng.nodes.new("CompositorNodeRLayers")
    rl.scene = scene
    for item, sock, mode in (("rgb", "Image", "RGB"), ("depth", "Depth", "BW")):
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.name = f"out_{item}"
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "OPEN_EXR"
        fo.format.color_depth = "32"
        fo.format.color_mode = mode
        fo.format.exr_codec = "ZIP"
        fo.save_as_render = False                      # keep scene-linear values
        fo.file_output_items.new("RGBA" if mode == "RGB" else "FLOAT", item)
        ng.links.new(rl.outputs[sock], fo.inputs[item])


def _read_exr(path: Path) -> np.ndarray:
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"cannot open {path}: {oiio.geterror()}")
    data = inp.read_image(0, 0, 0, inp.spec().nchannels, "float")
    inp.close()
    return np.asarray(data, np.float32)


@contextlib.contextmanager
def _quiet_stdout():
    """Silence Blender's per-file 'Saved: ...' lines (C-level stdout) during a render."""
    sys.stdout.flush()
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def render_exr(folder: Path, prefix: str) -> tuple[np.ndarray, np.ndarray]:
    """Render the current camera; return (linear RGB (H, W, 3), planar z depth (H, W)), row 0 = top."""
    bpy = _bpy()
    ng = bpy.context.scene.compositing_node_group
    for item in ("rgb", "depth"):
        fo = ng.nodes[f"out_{item}"]
        fo.directory = str(folder) + "/"
        fo.file_name = prefix
    with _quiet_stdout():
        bpy.ops.render.render(write_still=False)
    rgb = _read_exr(folder / f"{prefix}rgb.exr")[..., :3]
    depth = _read_exr(folder / f"{prefix}depth.exr")[..., 0]
    return rgb, depth


def write_png(path: Path, rgb8: np.ndarray) -> None:
    import OpenImageIO as oiio
    buf = oiio.ImageBuf(np.ascontiguousarray(rgb8))
    if not buf.write(str(path)):
        raise RuntimeError(f"cannot write {path}: {buf.geterror()}")


def scene_triangles(objects) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles (T, 3, 3) of the evaluated objects and the object index of each."""
    bpy = _bpy()
    dg = bpy.context.evaluated_depsgraph_get()
    tris, owner = [], []
    for k, ob in enumerate(objects):
        ev = ob.evaluated_get(dg)
        me = ev.to_mesh()
        me.calc_loop_triangles()
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        tri = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", tri)
        M = np.array(ev.matrix_world, dtype=np.float64)
        co = co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]
        tris.append(co[tri.reshape(-1, 3)])
        owner.append(np.full(len(tri) // 3, k))
        ev.to_mesh_clear()
    return np.concatenate(tris), np.concatenate(owner)


# ---------------------------------------------------------------------------------------------
# Sparse points and the COLMAP model
# ---------------------------------------------------------------------------------------------

def make_sparse_points(args, cams: list[Camera], depths: list[np.ndarray], cleans: list[np.ndarray],
                       tris: np.ndarray, owner: np.ndarray, rng: np.random.Generator) -> dict:
    """Sample surface points, keep those seen (depth test) in >= 2 views, colour them, add noise."""
    # only triangles near the surveyed area (camera centres +- one footprint) are candidates
    centres = np.array([c.center for c in cams])
    reach = 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)
    cxy = tris.mean(1)[:, :2]
    near = np.all((cxy > centres[:, :2].min(0) - reach) & (cxy < centres[:, :2].max(0) + reach), axis=1)
    e1 = tris[:, 1] - tris[:, 0]
    e2 = tris[:, 2] - tris[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    # denser sampling on rocks / structure than on the (large) terrain
    weights = area * near * np.where(owner == 0, 1.0, args.object_point_boost)
    pts, tri_idx = sample_triangles(tris, weights, args.points * 4, rng)
    vis = np.zeros((len(cams), len(pts)), bool)
    uv = np.zeros((len(cams), len(pts), 2))
    for j, (cam, depth) in enumerate(zip(cams, depths)):
        vis[j], uv[j] = visible_in_view(pts, cam, depth, args.depth_tol)
    keep = np.flatnonzero(vis.sum(0) >= 2)[: args.points]
    pts, vis, uv, obj = pts[keep], vis[:, keep], uv[:, keep], owner[tri_idx[keep]]
    # colour: mean clean 8-bit colour over the observations (nearest pixel)
    col_sum = np.zeros((len(pts), 3))
    for j, (cam, img) in enumerate(zip(cams, cleans)):
        c = np.clip(np.floor(uv[j, :, 0]).astype(np.int64), 0, cam.width - 1)
        r = np.clip(np.floor(uv[j, :, 1]).astype(np.int64), 0, cam.height - 1)
        col_sum += vis[j, :, None] * img[r, c].astype(np.float64)
    n_obs = vis.sum(0)
    colors = np.round(col_sum / n_obs[:, None]).astype(np.uint8)
    noisy = pts + rng.normal(0.0, args.point_noise, pts.shape) if args.point_noise > 0 else pts.copy()
    return {"xyz_true": pts, "xyz": noisy, "vis": vis, "uv": uv, "colors": colors, "object": obj}


def write_colmap_model(path: Path, cams: list[Camera], sparse: dict):
    """Write the true-pose COLMAP model (binary) with PINHOLE camera, images, points and tracks."""
    import pycolmap
    rec = pycolmap.Reconstruction()
    c0 = cams[0]
    cam = pycolmap.Camera(model="PINHOLE", width=c0.width, height=c0.height,
                          params=[c0.fx, c0.fy, c0.cx, c0.cy], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    vis, uv = sparse["vis"], sparse["uv"]
    obs_idx = np.cumsum(vis, axis=1) - 1                      # index of each observation in its image
    for j, c in enumerate(cams):
        img = pycolmap.Image(name=c.name, keypoints=np.ascontiguousarray(uv[j][vis[j]], dtype=np.float64),
                             camera_id=1, image_id=c.image_id)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t))
    image_ids = np.array([c.image_id for c in cams])
    for i in range(len(sparse["xyz"])):                      # pycolmap needs one call per point
        views = np.flatnonzero(vis[:, i])
        track = pycolmap.Track([pycolmap.TrackElement(int(image_ids[j]), int(obs_idx[j, i])) for j in views])
        rec.add_point3D(sparse["xyz"][i], track, sparse["colors"][i])
    path.mkdir(parents=True, exist_ok=True)
    rec.write(str(path))
    return rec


def reprojection_errors(rec) -> np.ndarray:
    """Per-observation reprojection error (pixels) of a pycolmap reconstruction (vectorised per image)."""
    errs = []
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        obs = [(p.xy, p.point3D_id) for p in img.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        X = np.array([rec.points3D[o[1]].xyz for o in obs])
        T = img.cam_from_world().matrix() if callable(img.cam_from_world) else img.cam_from_world.matrix()
        pc = X @ T[:3, :3].T + T[:3, 3]
        uv = pc[:, :2] / pc[:, 2:3]
        K = cam.calibration_matrix()
        uv = uv * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        errs.append(np.linalg.norm(uv - xy, axis=1))
    return np.concatenate(errs) if errs else np.zeros(0)


def run_sfm(out: Path, true_rec, threads: int) -> dict:
    """pycolmap SfM (``recgs_addon.core.io.sfm``) on images/ -> sfm/0; compare with the truth."""
    import pycolmap

    from recgs_addon.core.errors import SceneError
    from recgs_addon.core.io.sfm import SfmOptions, reconstruct

    t0 = time.time()
    shutil.rmtree(out / "sfm", ignore_errors=True)
    try:
        result = reconstruct(out / "images", out / "sfm" / "0", out / "database.db", SfmOptions(threads=threads))
    except SceneError:
        return {"registered": 0, "images": len(true_rec.images), "seconds": time.time() - t0}
    best = result.reconstruction
    res = {k: v for k, v in result.summary().items() if k != "model"}
    # compare with the truth: similarity from projection centres, then pose errors
    sim = pycolmap.align_reconstructions_via_proj_centers(best, true_rec, 0.1)
    if sim is not None:
        best.transform(sim)
        name_to_true = {im.name: im for im in true_rec.images.values()}
        pos_err, rot_err = [], []
        for im in best.images.values():
            if not im.has_pose:
                continue
            gt = name_to_true[im.name]
            pos_err.append(np.linalg.norm(im.projection_center() - gt.projection_center()))
            Rd = im.cam_from_world().rotation.matrix() @ gt.cam_from_world().rotation.matrix().T
            rot_err.append(math.degrees(math.acos(np.clip((np.trace(Rd) - 1) / 2, -1, 1))))
        res.update({"scale": float(sim.scale), "median_position_error_m": float(np.median(pos_err)),
                    "max_position_error_m": float(np.max(pos_err)),
                    "median_rotation_error_deg": float(np.median(rot_err))})
    return res


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------

def parse_args(argv=None) -> argparse.Namespace:
    """Command line; inside Blender (``blender -b --python ... -- args``) only the part after ``--``."""
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, type=Path, help="output dataset folder")
    g = p.add_argument_group("survey")
    g.add_argument("--views", type=int, default=24, help="number of photos")
    g.add_argument("--width", type=int, default=256, help="image width (px)")
    g.add_argument("--height", type=int, default=192, help="image height (px)")
    g.add_argument("--hfov", type=float, default=65.0, help="horizontal field of view (degrees)")
    g.add_argument("--seed", type=int, default=1, help="scene seed (terrain, objects, path jitter, points)")
    g.add_argument("--altitude", type=float, default=2.5, help="camera height above the seabed (m)")
    g.add_argument("--overlap", type=float, default=0.7, help="forward overlap of consecutive views")
    g.add_argument("--sidelap", type=float, default=0.6, help="overlap between neighbouring lines")
    g.add_argument("--pitch", type=float, default=8.0, help="forward pitch of the camera (degrees)")
    g.add_argument("--jitter-deg", type=float, default=1.5, help="random attitude jitter (degrees, std)")
    g.add_argument("--lines", type=int, default=0, help="lawnmower lines (0: about sqrt(views / 3))")
    g.add_argument("--path", choices=("lawnmower", "wander"), default="lawnmower",
                   help="survey lines, or a diver's wandering track that loops back over the seabed")
    g.add_argument("--rocks", type=int, default=7, help="number of rocks")
    g = p.add_argument_group("caustics")
    g.add_argument("--caustic-pattern", choices=CAUSTIC_PATTERNS, default="refraction", help="pattern kind")
    g.add_argument("--caustic-strength", type=float, default=0.45, help="0 = none, 1 = full contrast")
    g.add_argument("--caustic-scale", type=float, default=3.0, help="caustic tile size (m)")
    g.add_argument("--caustic-blur", type=float, default=0.03, help="softening (Gaussian std, m)")
    g.add_argument("--caustic-seed", type=int, default=None, help="pattern seed (default: --seed)")
    g.add_argument("--caustic-dt", type=float, default=1.0, help="seconds between shots")
    g.add_argument("--caustic-motion", choices=("random", "smooth"), default="random",
                   help="random: each shot's pattern at a random offset (photos); smooth: the pattern "
                        "drifts with time (video frames, --caustic-dt apart)")
    g.add_argument("--caustic-drift", default="0.01,0.004", help="smooth motion: drift in tile units per second")
    g.add_argument("--caustic-res", type=int, default=256, help="texture resolution (texels per tile)")
    g = p.add_argument_group("lighting and rendering")
    g.add_argument("--sun-tilt", type=float, default=25.0, help="sun tilt from vertical (degrees)")
    g.add_argument("--sun-azimuth", type=float, default=35.0, help="sun azimuth (degrees from +x)")
    g.add_argument("--sun-strength", type=float, default=2.2, help="sun irradiance (W/m^2)")
    g.add_argument("--ambient-strength", type=float, default=0.6, help="blue-green world light strength")
    g.add_argument("--samples", type=int, default=8, help="Cycles samples per pixel")
    g.add_argument("--bounces", type=int, default=1, help="max diffuse light bounces")
    g.add_argument("--no-denoise", dest="denoise", action="store_false", help="disable OIDN denoising")
    g.add_argument("--denoise-prefilter", choices=("NONE", "FAST", "ACCURATE"), default="FAST",
                   help="OIDN prefilter of the albedo/normal guides")
    g.add_argument("--denoise-quality", choices=("FAST", "BALANCED", "HIGH"), default="BALANCED",
                   help="OIDN quality")
    g.add_argument("--threads", type=int, default=2, help="CPU threads for Cycles and pycolmap")
    g = p.add_argument_group("sparse model and extras")
    g.add_argument("--points", type=int, default=5000, help="target number of sparse points")
    g.add_argument("--object-point-boost", type=float, default=3.0,
                   help="point density on rocks/structure relative to the terrain")
    g.add_argument("--point-noise", type=float, default=0.005, help="std of point position noise (m)")
    g.add_argument("--depth-tol", type=float, default=0.02, help="visibility depth tolerance (m)")
    g.add_argument("--save-depth", action="store_true", help="also write depth/NAME.npy (float32 z)")
    g.add_argument("--save-blend", action="store_true", help="also save scene.blend")
    g.add_argument("--no-clean", dest="clean", action="store_false",
                   help="skip the ground-truth renders (clean/): half the time, for surveys only timed or sized")
    g.add_argument("--sfm", action="store_true", help="also run pycolmap SfM on images/ -> sfm/0")
    a = p.parse_args(argv)
    if a.caustic_seed is None:
        a.caustic_seed = a.seed
    if not 0.0 <= a.caustic_strength <= 1.0:
        p.error("--caustic-strength must be in [0, 1]")
    if a.views < 1 or a.width < 8 or a.height < 8:
        p.error("need at least one view of at least 8 x 8 pixels")
    return a


def prepare_output(out: Path) -> None:
    """Create the dataset folder, removing only outputs this script writes."""
    out.mkdir(parents=True, exist_ok=True)
    for d in ("images", "clean", "sparse", "depth", "sfm"):
        shutil.rmtree(out / d, ignore_errors=True)
    for f in ("survey.json", "frames.json", "README.md", "database.db", "scene.blend"):
        (out / f).unlink(missing_ok=True)
    for d in ("images", "clean", "sparse/0"):
        (out / d).mkdir(parents=True)


def build_scene(args, hf: Heightfield, cams: list[Camera], terrain_size, light_dir):
    """All Blender data: materials, terrain, rocks, structure, lights, caustic rig. Returns (rig, objects, info)."""
    bpy = _bpy()
    rng = np.random.default_rng([args.seed, 3])
    rig = build_caustic_group(light_dir, args.caustic_scale)
    sand = sand_material(rig, args.seed)
    terrain = make_terrain(hf, terrain_size, 0.05, sand)
    centres = np.array([c.center[:2] for c in cams])
    half = 0.35 * 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)   # ~ 0.7 x half footprint
    lo, hi = centres.min(0) - half, centres.max(0) + half                     # area seen by the survey
    struct_xy = lo + (hi - lo) * rng.uniform(0.35, 0.65, 2)
    structure, discs = make_structure(rng, struct_xy, hf, rust_material(rig), concrete_material(rig))
    palettes = [  # (three colours, encrusting growth colour)
        (((0.04, 0.04, 0.04), (0.11, 0.10, 0.09), (0.24, 0.22, 0.19)), (0.60, 0.25, 0.40)),  # basalt
        (((0.25, 0.12, 0.05), (0.45, 0.25, 0.12), (0.62, 0.44, 0.28)), (0.15, 0.30, 0.10)),  # sandstone
        (((0.14, 0.14, 0.14), (0.34, 0.32, 0.29), (0.56, 0.53, 0.48)), (0.45, 0.20, 0.50)),  # granite
        (((0.12, 0.14, 0.06), (0.25, 0.30, 0.12), (0.40, 0.42, 0.25)), (0.80, 0.45, 0.10)),  # mossy
    ]
    rock_mats = [rock_material(rig, f"Rock{i}", pal, crust) for i, (pal, crust) in enumerate(palettes)]
    rocks, placed = [], discs
    for i in range(args.rocks):
        radius = rng.uniform(0.2, 0.5)
        for _ in range(200):  # rejection sampling: keep rocks clear of each other and the structure
            xy = lo + (hi - lo) * rng.uniform(0, 1, 2)
            if np.all(np.hypot(*(placed[:, :2] - xy).T) > placed[:, 2] + radius + 0.2):
                break
        else:
            continue  # no room left (tiny survey): fewer rocks
        placed = np.concatenate([placed, [[xy[0], xy[1], radius]]])
        rocks.append(make_rock(f"Rock_{i:02d}", rng, xy, radius, hf, rock_mats[i % len(rock_mats)]))
    setup_lighting(light_dir, args)
    objects = [terrain] + structure + rocks
    info = [{"name": ob.name, "location": list(ob.matrix_world.translation),
             "material": ob.data.materials[0].name} for ob in objects]
    bpy.context.view_layer.update()
    return rig, objects, info


def _motion_text(args) -> str:
    if args.caustic_motion == "smooth":
        return (f"The pattern drifts smoothly from frame to frame ({args.caustic_dt} s apart, drift "
                f"{args.caustic_drift} tile units per second), as in a video: neighbouring frames share much "
                "of their light.")
    return (f"The pattern changes from shot to shot (time step {args.caustic_dt} s plus a random\n"
            "offset), as in a real survey where each photo is taken at a different instant.")


def dataset_readme(args, n_points: int, denoise: bool) -> str:
    return f"""# Synthetic seafloor survey (RecGS for Blender)

Generated by `tools/make_survey.py` (Blender Cycles, {args.samples} samples{' + OIDN denoiser' if denoise else ''}).

* `images/` - {args.views} views, {args.width}x{args.height}, 8-bit sRGB, **with** water caustics.
* `clean/`  - the same views without caustics: the ground truth for caustic removal.
* `sparse/0/` - COLMAP binary model with the TRUE poses, PINHOLE camera (fx = fy, principal point
  at the image centre) and {n_points} sparse points (seen in >= 2 views, depth-tested, position noise
  std {args.point_noise} m, observations = exact projections of the noise-free points).
* `survey.json` - all parameters, cameras, per-shot caustic phase and measured mean gain.

## Caustic model

Caustics multiply the light reaching the seabed by a gain g(x, y; shot) = 1 + s * (T - 1), where T is
a tileable `{args.caustic_pattern}` pattern with T >= 0 and mean(T) = 1 over a {args.caustic_scale} m tile,
and s = {args.caustic_strength}. g is looked up at each surface point projected along the sun direction
onto z = 0 and multiplies every seabed material's base colour, so in linear light an `images/`
pixel is approximately g times the matching `clean/` pixel. The mean of g is exactly 1: caustics
redistribute light without adding any, so `clean/` (g = 1) is the scene under the caustics' mean
illumination. {_motion_text(args)}
"""


def plan_survey(args) -> tuple[Heightfield, list[Camera], dict, tuple[float, float]]:
    """Seabed height field, survey cameras, path info and a terrain size that covers the survey."""
    hf = Heightfield(np.random.default_rng([args.seed, 1]), (12.0, 10.0))
    cams, path_info = make_cameras(args, hf)
    centres = np.array([c.center for c in cams])
    extent = centres[:, :2].max(0) - centres[:, :2].min(0)
    margin = 2 * path_info["footprint_across_m"] + 2.0
    terrain_size = (max(12.0, extent[0] + margin), max(10.0, extent[1] + margin))
    return hf, cams, path_info, terrain_size


def render_views(args, out: Path, cams: list[Camera], rig: CausticRig, cam_ob, shots: list[dict]):
    """Render every view with and without caustics; write the PNGs. Returns (depths, clean sRGB8 images)."""
    depths, cleans = [], []
    with tempfile.TemporaryDirectory(prefix="make_survey_") as tmp:
        tmp = Path(tmp)
        for j, cam in enumerate(cams):
            t0 = time.time()
            set_camera_pose(cam_ob, cam)
            rig.set_shot(j)
            lin_c, depth = render_exr(tmp, "caustic_")
            if args.clean:
                rig.set_shot(None)
                lin_g, _ = render_exr(tmp, "clean_")
            else:   # no ground truth: the sparse points take their colours from the photos
                lin_g = lin_c
            img_g = linear_to_srgb8(lin_g)
            write_png(out / "images" / cam.name, linear_to_srgb8(lin_c))
            if args.clean:
                write_png(out / "clean" / cam.name, img_g)
            depths.append(depth)
            cleans.append(img_g)
            shots[j]["image"] = cam.name
            shots[j]["linear_mean_ratio"] = float(lin_c.mean() / max(lin_g.mean(), 1e-12))
            if args.save_depth:
                (out / "depth").mkdir(exist_ok=True)
                np.save(out / "depth" / (Path(cam.name).stem + ".npy"), depth)
            log(f"view {j + 1}/{len(cams)} {cam.name} rendered in {time.time() - t0:.1f} s "
                f"(mean caustic/clean {shots[j]['linear_mean_ratio']:.3f})")
    return depths, cleans


def survey_metadata(args, cams, path_info, terrain_size, light_dir, objects, obj_info, shots,
                    sparse, err, denoise) -> dict:
    """Everything needed to reproduce and interpret the dataset (written to survey.json)."""
    bpy = _bpy()
    track_len = sparse["vis"].sum(0)
    c0 = cams[0]
    return {
        "generator": "tools/make_survey.py",
        "blender": bpy.app.version_string,
        "parameters": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "denoiser": "OPENIMAGEDENOISE" if denoise else None,
        "intrinsics": {"model": "PINHOLE", "width": args.width, "height": args.height,
                       "fx": c0.fx, "fy": c0.fy, "cx": c0.cx, "cy": c0.cy},
        "path": path_info,
        "terrain_size_m": list(terrain_size),
        "sun_direction": light_dir.tolist(),
        "objects": obj_info,
        "cameras": [{"name": c.name, "image_id": c.image_id, "R": c.R.tolist(), "t": c.t.tolist(),
                     "center": c.center.tolist(),
                     "blender_matrix_world": blender_matrix_from_pose(c.R, c.t).tolist()} for c in cams],
        "caustics": {"pattern": args.caustic_pattern, "strength": args.caustic_strength,
                     "tile_m": args.caustic_scale, "blur_m": args.caustic_blur, "seed": args.caustic_seed,
                     "resolution": args.caustic_res,
                     "model": "gain = 1 + strength * (T - 1), T >= 0, mean(T) = 1 over the tile; looked up at "
                              "world XY projected along sun_direction onto z = 0, divided by tile_m (repeat)",
                     "shots": shots},
        "sparse": {"points": int(len(sparse["xyz"])), "mean_track_length": float(track_len.mean()),
                   "points_per_object": {objects[k].name: int((sparse["object"] == k).sum())
                                         for k in range(len(objects))},
                   "mean_reprojection_error_px": float(err.mean()),
                   "max_reprojection_error_px": float(err.max())},
    }


def main(argv=None) -> int:
    t_start = time.time()
    args = parse_args(argv)
    try:
        import pycolmap  # noqa: F401  (fail before rendering, not after)
        import OpenImageIO  # noqa: F401
    except ImportError as exc:
        sys.exit(f"make_survey: {exc}. Install pycolmap and OpenImageIO into this Python "
                 "(see docs/dev/import_export.md).")
    out = args.out.resolve()
    bpy = _bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    prepare_output(out)
    log(f"output {out}")

    hf, cams, path_info, terrain_size = plan_survey(args)
    log(f"{len(cams)} views on {path_info['lines']} lines, spacing {path_info['along_spacing_m']:.2f} m "
        f"along / {path_info['line_spacing_m']:.2f} m across, "
        f"terrain {terrain_size[0]:.1f} x {terrain_size[1]:.1f} m")
    drift = tuple(float(v) for v in args.caustic_drift.split(","))
    shots = caustic_shots(len(cams), args.caustic_seed, args.caustic_dt, args.caustic_motion, drift)
    gains = [caustic_gain(args.caustic_pattern, args.caustic_res, s["time_s"], s["offset"],
                          args.caustic_seed, args.caustic_strength, args.caustic_blur / args.caustic_scale)
             for s in shots]

    light_dir = light_direction(args.sun_tilt, args.sun_azimuth)
    rig, objects, obj_info = build_scene(args, hf, cams, terrain_size, light_dir)
    for s, st in zip(shots, add_caustic_images(rig, gains)):
        s.update(st)
    denoise = configure_render(args)
    cam_ob = add_camera(cams[0])
    log(f"scene built in {time.time() - t_start:.1f} s (denoiser: {'OIDN' if denoise else 'off'})")
    if args.save_blend:
        bpy.ops.wm.save_as_mainfile(filepath=str(out / "scene.blend"), check_existing=False)

    t_render = time.time()
    depths, cleans = render_views(args, out, cams, rig, cam_ob, shots)
    t_render = time.time() - t_render
    if not args.clean:
        (out / "clean").rmdir()

    tris, owner = scene_triangles(objects)
    sparse = make_sparse_points(args, cams, depths, cleans, tris, owner, np.random.default_rng([args.seed, 5]))
    rec = write_colmap_model(out / "sparse" / "0", cams, sparse)
    err = reprojection_errors(rec)
    log(f"sparse model: {len(sparse['xyz'])} points, mean track {sparse['vis'].sum(0).mean():.2f}, "
        f"reprojection error mean {err.mean():.4f} px max {err.max():.4f} px (point noise {args.point_noise} m)")

    meta = survey_metadata(args, cams, path_info, terrain_size, light_dir, objects, obj_info, shots,
                           sparse, err, denoise)
    if args.sfm:
        log("running pycolmap SfM on images/ ...")
        res = run_sfm(out, rec, args.threads)
        meta["sfm"] = res
        log(f"SfM registered {res['registered']}/{res['images']} images in {res['seconds']:.1f} s: {res}")
    meta["timing_s"] = {"render": t_render, "total": time.time() - t_start}
    (out / "survey.json").write_text(json.dumps(meta, indent=1))
    if args.caustic_motion == "smooth":   # frames of a video: their times, as a video import writes them
        from recgs_addon.core.io.frames import write_frame_times
        write_frame_times(out, {s["image"]: s["time_s"] for s in shots}, source="tools/make_survey.py",
                          fps=1.0 / args.caustic_dt)
    (out / "README.md").write_text(dataset_readme(args, len(sparse["xyz"]), denoise))
    log(f"done in {time.time() - t_start:.1f} s (render {t_render:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
