"""What natural water allows: Jerlov's water types seen through a camera's three channels.

Jerlov (Marine Optics, 2nd ed., 1976, Table XXVII) classed the sea's waters by the diffuse
attenuation of downwelling light, wavelength by wavelength: oceanic types I, IA, IB, II and III
(clear to turbid open ocean) and coastal types 1 to 9 (more chlorophyll, dissolved matter and
sediment). Akkaynak et al. (CVPR 2017) showed that a camera's red, green and blue attenuation in
natural waters lie on a narrow locus that these types span: water takes red first everywhere;
oceanic water leaves blue the clearest, coastal water green, and turbid coastal water takes
blue nearly as fast as red. The three channels are therefore not free of each other: two of
them, or one and the survey's units, place the water on the locus and give the third.

A channel's attenuation is the spectrum's seen through that channel over a path of ``r``
metres, ``-log(sum_l S(l) exp(-K(l) r) / sum_l S(l)) / r`` with ``S`` the channel's
sensitivity (a Gaussian for each of a typical camera's channels: red 620 nm, green 540 nm, blue
465 nm, the bands of common Bayer sensors) and ``K`` Jerlov's attenuation: a broad channel
sees the least-attenuated part of its band more as the path grows, so the channel's value falls
slightly with range (Akkaynak et al. 2017); the locus is taken at :data:`REFERENCE_RANGE`.

:func:`place` finds the point of the locus (a continuous type between Jerlov's, and a scale
where the survey's units are not metres) nearest to the channels a survey pins, in units of
their error bars, and :func:`fill` gives the channels it leaves free their value there, with an
error bar that covers the locus's own width (:data:`LOCUS_WIDTH`) and the place's uncertainty.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

#: Wavelengths of Jerlov's table (nm).
WAVELENGTHS = np.arange(400, 701, 25, dtype=np.float64)
#: Jerlov (1976) Table XXVII: diffuse attenuation of downwelling irradiance (per metre) at
#: :data:`WAVELENGTHS`, by water type.
TYPES = ("I", "IA", "IB", "II", "III", "1C", "3C", "5C", "7C", "9C")
KD = np.array([
    [0.028, 0.022, 0.019, 0.018, 0.027, 0.043, 0.063, 0.089, 0.235, 0.305, 0.36, 0.42, 0.56],
    [0.038, 0.031, 0.026, 0.025, 0.032, 0.048, 0.067, 0.094, 0.24, 0.31, 0.37, 0.43, 0.57],
    [0.051, 0.042, 0.036, 0.033, 0.042, 0.054, 0.072, 0.099, 0.245, 0.315, 0.375, 0.435, 0.58],
    [0.096, 0.081, 0.068, 0.062, 0.07, 0.076, 0.089, 0.115, 0.26, 0.335, 0.4, 0.465, 0.61],
    [0.185, 0.16, 0.135, 0.116, 0.115, 0.116, 0.12, 0.148, 0.295, 0.375, 0.445, 0.52, 0.66],
    [0.51, 0.36, 0.25, 0.17, 0.14, 0.13, 0.12, 0.15, 0.3, 0.37, 0.45, 0.51, 0.65],
    [0.78, 0.54, 0.39, 0.29, 0.22, 0.2, 0.19, 0.21, 0.33, 0.4, 0.46, 0.56, 0.71],
    [1.1, 0.78, 0.56, 0.43, 0.36, 0.31, 0.3, 0.33, 0.4, 0.48, 0.54, 0.65, 0.8],
    [1.6, 1.2, 0.89, 0.71, 0.58, 0.49, 0.46, 0.46, 0.48, 0.54, 0.63, 0.78, 0.92],
    [2.4, 1.9, 1.6, 1.23, 0.99, 0.78, 0.63, 0.58, 0.6, 0.65, 0.76, 0.92, 1.1],
])
#: A typical camera's channels: (centre, standard deviation) in nm, red, green, blue.
CHANNELS_NM = ((620.0, 30.0), (540.0, 32.0), (465.0, 28.0))
#: The path (m) the locus is taken over (the middle of a survey's ranges).
REFERENCE_RANGE = 3.0
#: How far (a factor, one standard deviation in logs) a natural water's channel may lie from the
#: locus: the types are classes, not every water; a camera's bands are not the typical one's;
#: the image's attenuation is a beam's, Jerlov's a diffuse light's.
LOCUS_WIDTH = 0.25
#: Types between two of Jerlov's the search tries (a continuous type: log-linear in between).
_SUBSTEPS = 40


def _sensitivity() -> np.ndarray:
    """(3, L) each channel's sensitivity at a 5-nm grid over Jerlov's wavelengths, summing to 1."""
    lam = np.arange(400.0, 700.1, 5.0)
    s = np.stack([np.exp(-0.5 * ((lam - c) / w) ** 2) for c, w in CHANNELS_NM])
    return s / s.sum(1, keepdims=True)


def band_attenuation(kd_row: Sequence[float], r: float = REFERENCE_RANGE) -> np.ndarray:
    """(3,) red, green and blue attenuation (per metre) over a path of ``r`` metres of water whose
    spectral attenuation is ``kd_row`` (at :data:`WAVELENGTHS`)."""
    lam = np.arange(400.0, 700.1, 5.0)
    k = np.interp(lam, WAVELENGTHS, np.asarray(kd_row, np.float64))
    return -np.log(_sensitivity() @ np.exp(-k * r)) / r


def locus(r: float = REFERENCE_RANGE) -> np.ndarray:
    """(len(TYPES), 3) each Jerlov type's red, green and blue attenuation (per metre)."""
    return np.stack([band_attenuation(row, r) for row in KD])


def _dense_locus(r: float = REFERENCE_RANGE) -> tuple[np.ndarray, np.ndarray]:
    """A continuous type ``t`` (0 = type I ... 9 = 9C) at :data:`_SUBSTEPS` per interval and the
    attenuation there (log-linear between Jerlov's types)."""
    pts = np.log(locus(r))
    t = np.linspace(0.0, len(TYPES) - 1.0, (len(TYPES) - 1) * _SUBSTEPS + 1)
    lo = np.minimum(np.floor(t).astype(int), len(TYPES) - 2)
    f = (t - lo)[:, None]
    return t, np.exp((1 - f) * pts[lo] + f * pts[lo + 1])


def type_name(t: float) -> str:
    """The name of a continuous type: Jerlov's nearest, "between" where it lies halfway."""
    lo = int(np.clip(np.floor(t), 0, len(TYPES) - 2))
    f = t - lo
    if f < 0.25:
        return TYPES[lo]
    if f > 0.75:
        return TYPES[lo + 1]
    return f"between {TYPES[lo]} and {TYPES[lo + 1]}"


def place(attenuation: Sequence[float], spread: Sequence[float], use: Sequence[bool],
          metres: bool = False) -> Optional[dict]:
    """The point of the locus nearest to the channels ``use`` marks (their ``attenuation`` and its
    error bar ``spread``, per channel), each channel's misfit in logs over the locus's width and
    the channel's own relative error bar together. ``metres``: the survey's units are metres, so
    the locus is compared as it is (one channel can place it); otherwise at the scale that fits
    best (two channels at least). Returns ``type`` (continuous), ``name``, ``scale`` (1 in
    metres), ``attenuation`` (3,) the locus's values there in the survey's units, ``misfit`` (the
    used channels' root mean square in standard deviations) and ``spread`` (3,): how far the
    locus's value of each channel moves over the places within one standard deviation of the best
    fit, with the locus's width; None where too few channels are used or positive."""
    a = np.asarray(attenuation, np.float64)
    sd = np.asarray(spread, np.float64)
    ok = np.asarray(use, bool) & (a > 0) & np.isfinite(sd)
    if ok.sum() < (1 if metres else 2):
        return None
    t, dense = _dense_locus()
    rel = np.where(ok, sd / np.where(a > 0, a, 1.0), np.inf)
    sigma = np.sqrt(LOCUS_WIDTH ** 2 + rel ** 2)                # per channel, in logs
    w = np.where(ok, 1.0 / sigma ** 2, 0.0)
    la = np.log(np.where(a > 0, a, 1.0))
    ld = np.log(dense)
    if metres:
        log_scale = np.zeros(len(t))
    else:   # the scale that fits each place best (weighted mean log difference)
        log_scale = ((la[None] - ld) * w).sum(1) / w.sum()
    chi2 = (((la[None] - ld - log_scale[:, None]) ** 2) * w).sum(1)
    best = int(np.argmin(chi2))
    near = chi2 <= chi2[best] + 1.0                             # the places within one standard deviation
    values = dense * np.exp(log_scale)[:, None]
    move = 0.5 * (values[near].max(0) - values[near].min(0))
    out_sd = np.hypot(values[best] * LOCUS_WIDTH, move)
    return {"type": float(t[best]), "name": type_name(float(t[best])), "scale": float(np.exp(log_scale[best])),
            "attenuation": values[best].tolist(), "misfit": float(np.sqrt(chi2[best] / ok.sum())),
            "spread": out_sd.tolist()}


def fill(attenuation: Sequence[float], spread: Sequence[float], pinned: Sequence[bool],
         metres: bool = False) -> Optional[dict]:
    """Each channel's attenuation from the photos where they pin it (``pinned``) and from what
    natural water allows where they do not: the locus placed by the pinned channels
    (:func:`place`), combined with the photos' own value in logs, each weighted by the inverse of
    its variance (a channel the photos leave free takes the locus's value; a loose one moves
    towards it). Returns :func:`place`'s dict with ``values`` (3,) the attenuation to use,
    ``values_spread`` (3,) its error bar and ``source`` per channel (``"photos"``, ``"prior"`` or
    ``"photos and prior"``), or None where the pinned channels cannot place the locus."""
    a = np.asarray(attenuation, np.float64)
    sd = np.asarray(spread, np.float64)
    pin = np.asarray(pinned, bool)
    at = place(a, sd, pin, metres=metres)
    if at is None:
        return None
    prior = np.asarray(at["attenuation"])
    prior_rel = np.asarray(at["spread"]) / prior
    values, out_sd, source = a.copy(), sd.copy(), []
    for c in range(3):
        if pin[c]:
            source.append("photos")
            continue
        rel = sd[c] / a[c] if a[c] > 0 and np.isfinite(sd[c]) else np.inf
        if not np.isfinite(rel) or rel > 1.0:   # the photos say nothing of it (or not even its sign)
            values[c], out_sd[c] = prior[c], prior[c] * prior_rel[c]
            source.append("prior")
            continue
        w_data, w_prior = 1.0 / rel ** 2, 1.0 / prior_rel[c] ** 2
        log_v = (w_data * np.log(a[c]) + w_prior * np.log(prior[c])) / (w_data + w_prior)
        values[c] = float(np.exp(log_v))
        out_sd[c] = values[c] / np.sqrt(w_data + w_prior)
        source.append("photos and prior")
    return {**at, "values": values.tolist(), "values_spread": out_sd.tolist(), "source": source}
