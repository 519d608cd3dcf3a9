"""The survey generator's light model (pure numpy, no bpy): the caustic patterns, their gain, how
they move from shot to shot, and the sun direction the gain is projected along.

tools/make_survey.py renders these; the caustic benchmarks (benchmarks/pointwise_bound.py) draw
their gains from here directly.

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

The survey has no water volume: no attenuation or backscatter is modelled. The water is the
blue-green ambient world light of tools/survey_scene.py (:func:`setup_lighting`).
"""
from __future__ import annotations

import math

import numpy as np

CAUSTIC_PATTERNS = ("refraction", "waves", "voronoi")


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


def caustic_shots(n: int, seed: int, dt: float, motion: str = "random", drift=(0.01, 0.004),
                  times=None) -> list[dict]:
    """Per-shot caustic phase: time ``t = i * dt`` (s; or ``times``, n of them) and an offset in
    tile units.

    ``motion="random"``: a random offset per shot, as photos taken at unrelated instants
    (each shot's light independent of the last). ``"smooth"``: as a video, the pattern drifts
    with the waves at ``drift`` tile units per second from one random start, so each frame's
    light is a small step from the last (neighbouring frames share much of their pattern); the
    start depends on ``seed`` alone, so frames at other ``times`` (a video's frames between the
    shots) see the same sea."""
    rng = np.random.default_rng([seed, 7])
    t = np.arange(n) * dt if times is None else np.asarray(times, float)
    if motion == "smooth":
        start = rng.uniform(0, 1, 2)
        offsets = start + np.outer(t, np.asarray(drift, float))
    elif motion == "random":
        offsets = rng.uniform(0, 1, (n, 2))
    else:
        raise ValueError(f"unknown caustic motion {motion!r} (random or smooth)")
    return [{"time_s": float(t[i]), "offset": [float(offsets[i, 0]), float(offsets[i, 1])]} for i in range(n)]


# ---------------------------------------------------------------------------------------------
# Sun direction (the caustic gain is looked up along it)
# ---------------------------------------------------------------------------------------------

def light_direction(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit direction in which sunlight travels (downwards), tilted from vertical."""
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), -math.cos(t)])
