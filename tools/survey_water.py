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
``--water-colour`` override them. ``--water green`` is a green coastal water behind a bright,
slowly building veil; ``--water jerlov-TYPE`` (I, III, 1C, 3C, 5C, 7C) follows Jerlov's types
(:func:`_jerlov_types`).
"""
from __future__ import annotations

import numpy as np

#: name -> (bD per metre, bB per metre, Binf linear RGB)
WATER_TYPES = {
    "clear": ((0.40, 0.085, 0.06), (0.06, 0.08, 0.10), (0.004, 0.045, 0.110)),
    "coastal": ((0.50, 0.22, 0.34), (0.30, 0.34, 0.30), (0.012, 0.085, 0.065)),
    # green coastal water with a bright, slowly building veil (the level reef surveys')
    "green": ((0.50, 0.12, 0.18), (0.40, 0.18, 0.22), (0.03, 0.20, 0.22)),
}
#: Jerlov's types the battery of waters spans, with each one's backscatter rate over its
#: attenuation (natural waters do not keep them equal: the battery strays both ways).
JERLOV_BATTERY = {"I": 1.5, "III": 0.7, "1C": 1.2, "3C": 0.8, "5C": 1.4, "7C": 1.0}
#: The veil's brightest channel (linear) in the Jerlov waters, and the depth (m) whose ambient
#: light gives its colour (the light left after that much water, scattered back).
JERLOV_VEIL = (0.12, 4.0)


def _jerlov_types() -> dict:
    """``jerlov-TYPE`` waters: the attenuation of Jerlov's type through a camera's three bands
    (recgs_addon/core/model/jerlov.py), the backscatter rate a multiple of it
    (:data:`JERLOV_BATTERY`, a little more in red and less in blue), and a veil the colour of the
    ambient light at :data:`JERLOV_VEIL`'s depth."""
    import sys
    from pathlib import Path
    root = str(Path(__file__).resolve().parents[1])
    if root not in sys.path:
        sys.path.insert(0, root)
    from recgs_addon.core.model import jerlov
    rows = jerlov.locus()
    out = {}
    for name, ratio in JERLOV_BATTERY.items():
        att = rows[jerlov.TYPES.index(name)]
        ambient = np.exp(-att * JERLOV_VEIL[1])
        out[f"jerlov-{name}"] = (tuple(np.round(att, 4)), tuple(np.round(ratio * att * (1.1, 1.0, 0.9), 4)),
                                 tuple(np.round(JERLOV_VEIL[0] * ambient / ambient.max(), 4)))
    return out


WATER_TYPES.update(_jerlov_types())


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
