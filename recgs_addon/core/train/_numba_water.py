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


#: Steps of the tables: the decoding curve over [0, 1], the encoding curve over the square
#: root of [0, 1] (its power is steep near 0), and exp(-t) per 1/64 up to t = 32 (then 0 to float32).
DECODE_STEPS, ENCODE_STEPS, EXP_PER_UNIT, EXP_MAX = 16384, 4096, 64, 32


def tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float32 tables for :func:`forward`, from float64: the sRGB decoding curve at
    ``k / DECODE_STEPS``, the encoding curve's power branch at ``(k / ENCODE_STEPS) ** 2`` and
    ``exp(-k / EXP_PER_UNIT)``, each with one step past its end (the last step's upper end)."""
    x = np.arange(DECODE_STEPS + 2) / DECODE_STEPS
    dec = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    s = np.arange(ENCODE_STEPS + 2) / ENCODE_STEPS
    enc = 1.055 * s ** (5 / 6) - 0.055
    ex = np.exp(-np.arange(EXP_MAX * EXP_PER_UNIT + 2) / EXP_PER_UNIT)
    return dec.astype(np.float32), enc.astype(np.float32), ex.astype(np.float32)


@numba.njit(nogil=True, cache=True, inline="always")
def _exp_neg(t, ex):
    """exp(-t) for t >= 0: the table's step below t times a cubic for the rest (under 1/64,
    where the cubic's error is below 3e-9)."""
    u = min(max(t, np.float32(0.0)), np.float32(EXP_MAX)) * np.float32(EXP_PER_UNIT)
    k = np.int64(u)
    f = (u - np.float32(k)) * np.float32(1.0 / EXP_PER_UNIT)
    one = np.float32(1.0)
    return ex[k] * (one - f * (one - f * (np.float32(0.5) - f * np.float32(1.0 / 6.0))))


@numba.njit(nogil=True, cache=True)
def forward(lo, hi, surface, rng, att, back, veil, dec, enc, ex, out, parts):
    """``out`` (H, W, 3) and what the backward needs, ``parts`` (5, H, W, 3): the factors that
    take the output's gradient to the seen value's (``dout/dseen``), to the surface's
    (``dseen/ds``), and to each coefficient's (``dseen/datt``, ``dseen/dback``, ``dseen/dveil``).
    The curves and exponentials come from :func:`tables` (linear between steps): four
    transcendental calls per value cost twice the rest of the kernel, and the tables keep the
    result within float32's rounding of the float64 formula (3e-7 measured, as the calls did)."""
    w = surface.shape[1]
    nd = np.float32(dec.shape[0] - 2)
    ne = np.float32(enc.shape[0] - 2)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for i in range(lo, hi):
        for j in range(w):
            r = rng[i, j]
            for c in range(3):
                s = surface[i, j, c]
                x = min(max(s, zero), one)
                t = x * nd
                k = np.int64(t)
                lin = dec[k] + (t - np.float32(k)) * (dec[k + 1] - dec[k])
                if x <= np.float32(0.04045):
                    dlin = np.float32(1.0 / 12.92)
                else:                                       # d/dx ((x + a) / (1 + a)) ** 2.4
                    dlin = np.float32(2.4) * lin / (x + np.float32(0.055))
                ea = _exp_neg(att[c] * r, ex)
                eb = _exp_neg(back[c] * r, ex)
                seen = lin * ea + veil[c] * (one - eb)
                y = min(max(seen, zero), one)
                if y <= np.float32(0.0031308):
                    o = np.float32(12.92) * y
                    dy = np.float32(12.92)
                else:
                    q = np.sqrt(y) * ne
                    kq = np.int64(q)
                    o = enc[kq] + (q - np.float32(kq)) * (enc[kq + 1] - enc[kq])
                    dy = np.float32(1.0 / 2.4) * (o + np.float32(0.055)) / y   # d/dy 1.055 y^(1/2.4)
                out[i, j, c] = o
                parts[0, i, j, c] = dy if zero <= seen <= one else zero
                parts[1, i, j, c] = ea * dlin if zero <= s <= one else zero
                parts[2, i, j, c] = -lin * ea * r
                parts[3, i, j, c] = veil[c] * eb * r
                parts[4, i, j, c] = one - eb


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
