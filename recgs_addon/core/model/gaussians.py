"""The Gaussian set: parameters of a 3D Gaussian Splatting model as numpy arrays.

Parameters are stored as the optimiser sees them (INRIA conventions):

* ``means``          (N, 3) float32, world coordinates (metres).
* ``log_scales``     (N, 3) float32, natural log of the standard deviations along the local axes.
* ``quats``          (N, 4) float32, rotation as (w, x, y, z); unit length when created here,
  possibly not normalised when read from a file (renderers normalise).
* ``logit_opacities`` (N,) float32, opacity = sigmoid(logit).
* ``sh``             (N, K, 3) float32, real spherical-harmonic coefficients per colour
  channel, K = (degree + 1)^2, coefficient-major (``sh[:, 0]`` is the DC term).
  Colour = max(0, 0.5 + sum_k sh[:, k] * Y_k(dir)); see :data:`SH_C0`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .knn import knn_distances

#: Degree-0 real SH basis constant, 1 / (2 sqrt(pi)). DC colour c maps to (c - 0.5) / SH_C0.
SH_C0 = 0.28209479177387814
#: Degree-1 constant, sqrt(3) / (2 sqrt(pi)); degree-2 and -3 constants (INRIA's sh_utils.py).
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
#: Every SH constant in one tuple (C0, C1, C2[5], C3[7]): what the rasterizer's kernels read.
SH_CONSTANTS = (SH_C0, SH_C1, *SH_C2, *SH_C3)
#: Initial opacity of Gaussians made from sparse points (INRIA uses 0.1).
INIT_OPACITY = 0.1
#: Neighbours averaged for the initial scale (INRIA: mean squared distance to 3 nearest).
INIT_NEIGHBOURS = 3


def num_sh_coeffs(degree: int) -> int:
    """Number of coefficients per channel for SH ``degree``: (d + 1)^2."""
    return (degree + 1) ** 2


def sh_degree_from_coeffs(k: int) -> int:
    d = int(round(np.sqrt(k))) - 1
    if d < 0 or d > 3 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per channel is not (degree+1)^2 for a degree 0..3")
    return d


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> DC SH coefficient."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """DC SH coefficient -> colour (not clipped)."""
    return np.asarray(dc, dtype=np.float64) * SH_C0 + 0.5


def logit(p):
    p = np.asarray(p, dtype=np.float64)
    return np.log(p) - np.log1p(-p)


def sigmoid(x):
    x = np.asarray(x, dtype=np.float64)
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # stable for large |x|


@dataclass
class GaussianSet:
    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    logit_opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self):
        self.means = np.ascontiguousarray(self.means, dtype=np.float32).reshape(-1, 3)
        n = len(self.means)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32).reshape(n, 3)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32).reshape(n, 4)
        self.logit_opacities = np.ascontiguousarray(self.logit_opacities, dtype=np.float32).reshape(n)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh must have shape (N, K, 3) with N={n}, got {self.sh.shape}")
        sh_degree_from_coeffs(self.sh.shape[1])

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        return sigmoid(self.logit_opacities)

    @property
    def scales(self) -> np.ndarray:
        return np.exp(self.log_scales.astype(np.float64))

    def subset(self, index) -> "GaussianSet":
        """Gaussians selected by a boolean mask or an index array."""
        return GaussianSet(self.means[index], self.log_scales[index], self.quats[index],
                           self.logit_opacities[index], self.sh[index])

    def with_sh_degree(self, degree: int) -> "GaussianSet":
        """Copy with SH truncated or zero-padded to ``degree``."""
        k = num_sh_coeffs(degree)
        sh = np.zeros((len(self), k, 3), np.float32)
        m = min(k, self.sh.shape[1])
        sh[:, :m] = self.sh[:, :m]
        return GaussianSet(self.means, self.log_scales, self.quats, self.logit_opacities, sh)

    def finite_mask(self) -> np.ndarray:
        """(N,) bool: rows whose every parameter is finite."""
        return (np.isfinite(self.means).all(1) & np.isfinite(self.log_scales).all(1)
                & np.isfinite(self.quats).all(1) & np.isfinite(self.logit_opacities)
                & np.isfinite(self.sh).all((1, 2)))

    @classmethod
    def empty(cls, sh_degree: int = 0) -> "GaussianSet":
        k = num_sh_coeffs(sh_degree)
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, k, 3)))


def knn_mean_distance(points: np.ndarray, k: int = INIT_NEIGHBOURS) -> np.ndarray:
    """(N,) mean Euclidean distance of each point to its k nearest other points.

    Exact, with numpy only (``knn.py``: Blender's Python has no scipy); on this machine 200k
    points take about 3 s, against 0.5 s for scipy's cKDTree. Duplicate points give 0, which
    callers floor. With fewer than k+1 points, uses as many as exist.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if n < 2:
        return np.ones(n)
    return knn_distances(pts, min(k, n - 1)).mean(axis=1)


def init_from_points(points: np.ndarray, colors: np.ndarray, sh_degree: int = 0,
                     opacity: float = INIT_OPACITY) -> GaussianSet:
    """Gaussians from sparse points, one per point.

    Args:
        points: (N, 3) positions.
        colors: (N, 3) uint8 RGB, or floats in [0, 1].
        sh_degree: SH degree of the set (higher coefficients start at 0).
        opacity: initial opacity (0.1 as in INRIA 3DGS).
    Scale: isotropic, the mean distance to the 3 nearest neighbours (INRIA takes the root of
    the mean squared distance; the plain mean is less sensitive to one far neighbour),
    floored at 1e-7 so duplicate points do not give log(0).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = np.asarray(colors)
    cols = cols.astype(np.float64) / 255.0 if cols.dtype == np.uint8 else cols.astype(np.float64)
    n = len(pts)
    dist = np.maximum(knn_mean_distance(pts), 1e-7)
    log_scales = np.repeat(np.log(dist)[:, None], 3, axis=1)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    sh = np.zeros((n, num_sh_coeffs(sh_degree), 3))
    sh[:, 0] = rgb_to_sh_dc(cols.reshape(-1, 3))
    return GaussianSet(pts, log_scales, quats, np.full(n, logit(opacity)), sh)
