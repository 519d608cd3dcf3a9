"""The survey generator's geometry (numpy, no bpy): the seabed height field, the camera path
(lawnmower or a diver's wandering track), the survey cameras, and depth-tested visibility and
surface sampling for the sparse points.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from recgs_addon.core.model.cameras import Camera, project_points  # noqa: E402


# ---------------------------------------------------------------------------------------------
# Terrain, cameras, visibility (numpy)
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
    ``args.altitude`` above the seabed, rising and sinking by ``args.altitude_swing`` metres
    (a sine over ``args.altitude_period`` views) when that is set."""
    fx, fy, cx, cy = intrinsics(args.width, args.height, args.hfov)
    across = 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)   # image width on the ground
    along = across * args.height / args.width
    if args.path == "wander":
        xy, heading, info = wander_layout(args.views, along, across, args.overlap, args.seed)
    else:
        xy, heading, info = lawnmower_layout(args.views, along, across, args.overlap, args.sidelap, args.lines)
    rng = np.random.default_rng([args.seed, 11])
    z = hf.mean_around(xy[:, 0], xy[:, 1], 0.8) + args.altitude + rng.normal(0, 0.05, len(xy))
    swing = getattr(args, "altitude_swing", 0.0)
    if swing:   # a diver rising and sinking: the same seabed seen from several ranges
        period = max(2.0, getattr(args, "altitude_period", 40.0))
        z = z + swing * np.sin(2 * np.pi * np.arange(len(xy)) / period)
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
