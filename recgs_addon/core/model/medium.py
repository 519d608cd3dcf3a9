"""The water between the seabed and the camera: attenuation and backscatter.

The revised underwater image formation model (Akkaynak and Treibitz, CVPR 2018), per linear
colour channel, for a pixel whose ray meets the seabed at range ``r``::

    seen = J * exp(-attenuation * r) + veil * (1 - exp(-backscatter * r))

``J`` is the seabed's true colour (what the Gaussians hold), ``attenuation`` takes the direct
signal (red first), ``backscatter`` is how fast the veil of light scattered towards the camera
builds up, and ``veil`` is the water's colour at infinite range. With the rendered surface
colour ``S = sum_i c_i alpha_i T_i`` (no background)::

    seen = S * exp(-attenuation * r) + veil * (1 - exp(-backscatter * r))

A survey looks at the seabed, so every pixel's ray ends on it: where the model leaves a hole
(accumulated opacity ``alpha`` < 1) the render is a black surface at the pixel's range, not open
water. Open water would fill a hole with the veil, which is what a far, dim stretch of seabed
looks like too, and the photos would never ask the model to close it: its true colour would then
show the hole (measured: dark patches on held-out views of a coastal-water survey).

The model holds in linear light and photos are sRGB-encoded (8-bit PNG or JPEG), so the render
is decoded before the water is put in front of it and the result encoded again (the plain sRGB
curve, IEC 61966-2-1); the Gaussians keep sRGB colours like any 3DGS model.

The range comes from the render's expected depth (``depth / alpha``, times the ray's length per
unit of depth): the water is applied once a pixel, as WaterSplatting does, and the depth is not
differentiated through, so the water never moves the geometry. Coefficients are per scene unit
(metres where the survey's poses are in metres); :class:`Medium` learns them per
``length`` (the survey's median range) so that a survey's scale does not change how they train.
"""
from __future__ import annotations

import numpy as np
import torch

from .colour import linear_to_srgb, srgb_to_linear

#: Accumulated opacity a pixel's expected depth is divided by at the least (its range, in holes).
_MIN_ALPHA = 1e-4


def _raw(attenuation, backscatter, veil, length: float) -> torch.Tensor:
    """(3, 3) float32 raw parameters for coefficients per scene unit (three per row): softplus^-1
    of each coefficient times ``length`` (at least 1e-6), and the logit of the veil (within
    1e-4 of 0 and 1)."""
    rows = []
    for coef in (attenuation, backscatter):
        x = (torch.as_tensor(coef, dtype=torch.float64) * length).clamp_min(1e-6)
        rows.append(x + torch.log(-torch.expm1(-x)))          # softplus^-1, stable
    v = torch.as_tensor(veil, dtype=torch.float64).clamp(1e-4, 1 - 1e-4)
    rows.append(torch.log(v / (1 - v)))
    return torch.stack(rows).float()


def ray_lengths(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                device="cpu") -> torch.Tensor:
    """(H, W) length of each pixel's ray per unit of camera-space depth (range = depth x this)."""
    u = (torch.arange(width, dtype=torch.float32, device=device) + 0.5 - cx) / fx
    v = (torch.arange(height, dtype=torch.float32, device=device) + 0.5 - cy) / fy
    return torch.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


class Medium:
    """Three coefficients per colour channel, learned with the Gaussians (see the module)."""

    def __init__(self, length: float, veil=(0.05, 0.1, 0.1), attenuation: float = 0.05,
                 backscatter: float = 0.05, device="cpu"):
        #: scene units the coefficients are learned per (the survey's median range)
        self.length = float(length)
        self.raw = torch.nn.Parameter(_raw([attenuation] * 3, [backscatter] * 3, [float(v) for v in veil],
                                           self.length).to(device))

    def coefficients(self, raw: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(attenuation, backscatter per scene unit, veil colour), each (3,)."""
        raw = self.raw if raw is None else raw
        scale = torch.nn.functional.softplus(raw[:2]) / self.length
        return scale[0], scale[1], torch.sigmoid(raw[2])

    def see(self, surface: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor,
            ray_len: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) what the camera sees (sRGB): ``surface`` (the render without background,
        sRGB), its ``alpha`` and unnormalised expected ``depth`` (H, W), through the water."""
        return self.see_at(surface, self.range_of(alpha, depth, ray_len))

    @staticmethod
    def range_of(alpha: torch.Tensor, depth: torch.Tensor, ray_len: torch.Tensor) -> torch.Tensor:
        """(H, W) each pixel's range (scene units) from a render's ``alpha`` and unnormalised
        expected ``depth``, not differentiated."""
        return (depth.detach() / alpha.detach().clamp_min(_MIN_ALPHA) * ray_len).clamp_min(0.0)

    def see_at(self, surface: torch.Tensor, rng: torch.Tensor) -> torch.Tensor:
        """:meth:`see` given each pixel's range ``rng`` (H, W)."""
        r = rng.unsqueeze(-1)
        att, back, veil = self.coefficients()
        seen = srgb_to_linear(surface.clamp(0.0, 1.0)) * torch.exp(-att * r) + veil * (1.0 - torch.exp(-back * r))
        return linear_to_srgb(seen.clamp(0.0, 1.0))

    # --- plain numbers (reports, exports) ---------------------------------------------------
    def values(self) -> dict:
        """The coefficients as lists of floats (per scene unit) and the length they train per."""
        att, back, veil = (t.detach().cpu().double().tolist() for t in self.coefficients())
        return {"attenuation": att, "backscatter": back, "veil": veil, "length": self.length}

    def state_dict(self) -> dict:
        return {"length": self.length, "raw": self.raw.detach().cpu().clone()}

    @classmethod
    def from_values(cls, values: dict, device="cpu") -> "Medium":
        """The medium with given coefficients (:meth:`values`' layout; ``length`` defaults to 1)."""
        m = cls(values.get("length", 1.0), device=device)
        with torch.no_grad():
            m.raw.copy_(_raw(values["attenuation"], values["backscatter"], values["veil"], m.length))
        return m

    @classmethod
    def from_state(cls, state: dict, device="cpu") -> "Medium":
        m = cls(state["length"], device=device)
        with torch.no_grad():
            m.raw.copy_(state["raw"].to(device))
        return m


def through_water(true_rgb: np.ndarray, rng: np.ndarray, values: dict) -> np.ndarray:
    """(H, W, 3) linear true colour (linear light) seen through ``rng`` (H, W) scene units of water
    (:meth:`Medium.values`); numpy, for outputs."""
    att, back, veil = (np.asarray(values[k], np.float64) for k in ("attenuation", "backscatter", "veil"))
    r = np.asarray(rng, np.float64)[..., None]
    return np.asarray(true_rgb, np.float64) * np.exp(-att * r) + veil * (1.0 - np.exp(-back * r))


def out_of_water(seen_rgb: np.ndarray, rng: np.ndarray, values: dict, max_gain: float = 20.0) -> np.ndarray:
    """The inverse of :func:`through_water`: a photo's true colour from its range, the direct
    signal's gain capped at ``max_gain`` (where the water took nearly all of a channel, the
    photo's noise would be amplified without bound)."""
    att, back, veil = (np.asarray(values[k], np.float64) for k in ("attenuation", "backscatter", "veil"))
    r = np.asarray(rng, np.float64)[..., None]
    direct = np.asarray(seen_rgb, np.float64) - veil * (1.0 - np.exp(-back * r))
    return direct * np.minimum(np.exp(att * r), max_gain)
