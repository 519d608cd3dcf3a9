"""The sRGB transfer curves (IEC 61966-2-1), in torch and differentiable: photos and Gaussian
colours are sRGB-encoded, light adds and multiplies in linear light (caustics, the water).

Both curves take values below 0 as 0 and extend their top branch above 1; a caller that wants
[0, 1] clamps first (the water model does)."""
from __future__ import annotations

import torch


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """The sRGB decoding curve."""
    x = x.clamp_min(0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB encoding curve (the power's slope stays finite: its branch is not taken near 0)."""
    x = x.clamp_min(0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def lit_by(x: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """sRGB colours ``x`` (..., 3) lit by a grey ``gain`` (..., 3 or broadcastable) in linear
    light, both ends clamped to [0, 1]."""
    return linear_to_srgb((srgb_to_linear(x.clamp(0.0, 1.0)) * gain).clamp(0.0, 1.0))
