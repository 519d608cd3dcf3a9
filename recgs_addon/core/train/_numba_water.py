"""numba kernels of the water in front of a render (imported by :mod:`.numba_water` only, after
numba's cache has been pointed at RecGS's folder).

The same maths as :meth:`..model.medium.Medium.see` per pixel and channel, with torch's
gradient conventions at the clamps (a clamp passes the gradient where the input lies within
its bounds, ends included; ``where`` passes it to the branch it took):

    x = clamp(s, 0, 1); lin = x / 12.92 if x <= 0.04045 else ((x + 0.055) / 1.055) ** 2.4
    seen = lin exp(-att r) + veil (1 - exp(-back r)); y = clamp(seen, 0, 1)
    out = 12.92 y if y <= 0.0031308 else 1.055 y ** (1 / 2.4) - 0.055

Layout: (H, W, 3) float32 images, (H, W) ranges; every kernel works on a range ``[lo, hi)`` of
rows, serial and without the GIL, so :func:`..render.numba_kernels.run_ranges` can run ranges on
threads. The forward keeps the per-element factors of the chain rule; the backward is then
multiplications and sums.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def forward(lo, hi, surface, rng, att, back, veil, out, parts):
    """``out`` (H, W, 3) and what the backward needs, ``parts`` (5, H, W, 3): the factors that
    take the output's gradient to the seen value's (``dout/dseen``), to the surface's
    (``dseen/ds``), and to each coefficient's (``dseen/datt``, ``dseen/dback``, ``dseen/dveil``)."""
    w = surface.shape[1]
    for i in range(lo, hi):
        for j in range(w):
            r = rng[i, j]
            for c in range(3):
                s = surface[i, j, c]
                x = min(max(s, np.float32(0.0)), np.float32(1.0))
                if x <= np.float32(0.04045):
                    lin = x / np.float32(12.92)
                    dlin = np.float32(1.0 / 12.92)
                else:
                    b = (x + np.float32(0.055)) / np.float32(1.055)
                    lin = b ** np.float32(2.4)
                    dlin = np.float32(2.4 / 1.055) * lin / b
                ea = np.exp(-att[c] * r)            # float32 throughout, as torch computes it
                eb = np.exp(-back[c] * r)
                seen = lin * ea + veil[c] * (np.float32(1.0) - eb)
                y = min(max(seen, np.float32(0.0)), np.float32(1.0))
                if y <= np.float32(0.0031308):
                    o = np.float32(12.92) * y
                    dy = np.float32(12.92)
                else:
                    p = y ** np.float32(1.0 / 2.4)
                    o = np.float32(1.055) * p - np.float32(0.055)
                    dy = np.float32(1.055 / 2.4) * p / y
                out[i, j, c] = o
                parts[0, i, j, c] = dy if np.float32(0.0) <= seen <= np.float32(1.0) else np.float32(0.0)
                parts[1, i, j, c] = ea * dlin if np.float32(0.0) <= s <= np.float32(1.0) else np.float32(0.0)
                parts[2, i, j, c] = -lin * ea * r
                parts[3, i, j, c] = veil[c] * eb * r
                parts[4, i, j, c] = np.float32(1.0) - eb


@numba.njit(nogil=True, cache=True)
def backward(lo, hi, parts, g_out, g_surface, g_coef):
    """``g_surface`` (H, W, 3) and, per row, the coefficients' gradient sums ``g_coef`` (H, 9):
    attenuation, backscatter, veil (float64)."""
    w = g_out.shape[1]
    for i in range(lo, hi):
        for k in range(9):
            g_coef[i, k] = 0.0
        for j in range(w):
            for c in range(3):
                gs = g_out[i, j, c] * parts[0, i, j, c]
                g_surface[i, j, c] = gs * parts[1, i, j, c]
                g_coef[i, c] += gs * parts[2, i, j, c]
                g_coef[i, 3 + c] += gs * parts[3, i, j, c]
                g_coef[i, 6 + c] += gs * parts[4, i, j, c]
