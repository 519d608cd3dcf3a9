"""The survey generator's water model (pure numpy, no bpy): attenuation and backscatter.

tools/make_survey.py renders the seabed as it would look in air under the (caustic) light, and
this module puts the water between seabed and camera afterwards, per pixel, from the true range
along each pixel's ray (the rendered planar depth times the ray's length per unit depth).

Image formation
---------------
The revised underwater image formation model (Akkaynak and Treibitz, CVPR 2018), per linear
colour channel ``c`` and pixel with range ``r`` (metres from the camera centre to the surface)::

    I_c = J_c * exp(-bD_c * r) + Binf_c * (1 - exp(-bB_c * r))

``J`` is the seabed's radiance at the seabed (what ``clean/`` holds: the true colour under the
caustics' mean light; with caustics on, ``images/`` gets ``g * J`` attenuated, because the caustic
light falls on the seabed before the water between seabed and camera acts on it). ``bD`` is the
direct signal's attenuation, ``bB`` the backscatter's coefficient and ``Binf`` the water's colour
at infinite range (veiling light). Pixels that see no surface get ``Binf``. The model leaves out
forward scattering (a slight blur) and the range and reflectance dependence of ``bD`` in the full
model: it is the model the trainer fits, so the benchmark measures the fit, not the model gap.

Water types
-----------
``--water clear`` and ``--water coastal`` pick coefficients of the order measured in the sea
(Jerlov's clear oceanic type I-II and coastal type 3-5, red attenuated most; the coastal water's
chlorophyll and dissolved matter take blue too, leaving it green), with the veiling light's colour
in the scene's linear units. ``--water-attenuation``, ``--water-backscatter`` and
``--water-colour`` override them.
"""
from __future__ import annotations

import numpy as np

#: name -> (bD per metre, bB per metre, Binf linear RGB)
WATER_TYPES = {
    "clear": ((0.40, 0.085, 0.06), (0.06, 0.08, 0.10), (0.004, 0.045, 0.110)),
    "coastal": ((0.50, 0.22, 0.34), (0.30, 0.34, 0.30), (0.012, 0.085, 0.065)),
}


def water_coefficients(kind: str, attenuation: str = "", backscatter: str = "", colour: str = "") -> dict | None:
    """The water's coefficients: a named type, each part overridable by ``"r,g,b"``; None for no water."""
    if kind == "none" and not (attenuation or backscatter or colour):
        return None
    base = WATER_TYPES.get(kind, WATER_TYPES["coastal"])

    def pick(text: str, default) -> list[float]:
        if not text:
            return [float(v) for v in default]
        vals = [float(v) for v in text.split(",")]
        if len(vals) != 3 or min(vals) < 0:
            raise ValueError(f"expected three non-negative numbers 'r,g,b', got {text!r}")
        return vals

    return {"type": kind, "attenuation_per_m": pick(attenuation, base[0]),
            "backscatter_per_m": pick(backscatter, base[1]), "veiling_light": pick(colour, base[2])}


def ray_lengths(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(H, W) length of each pixel's ray per unit of planar depth: range = depth * this."""
    u = (np.arange(width) + 0.5 - cx) / fx
    v = (np.arange(height) + 0.5 - cy) / fy
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def apply_water(linear: np.ndarray, rng: np.ndarray, water: dict) -> np.ndarray:
    """(H, W, 3) linear radiance at the seabed -> as the camera sees it through ``rng`` (H, W)
    metres of water (``inf`` or non-finite where no surface is hit)."""
    bd = np.asarray(water["attenuation_per_m"], np.float64)
    bb = np.asarray(water["backscatter_per_m"], np.float64)
    binf = np.asarray(water["veiling_light"], np.float64)
    r = np.where(np.isfinite(rng) & (rng > 0), rng, np.inf)[..., None]
    direct = np.where(np.isfinite(r), np.asarray(linear, np.float64) * np.exp(-bd * np.minimum(r, 1e6)), 0.0)
    return direct + binf * (1.0 - np.exp(-bb * r))
