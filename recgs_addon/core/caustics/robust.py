"""Robust weighting of the loss against moving light, and the survey-wide gain restore.

Caustics add light: where a photo is much brighter than the model's render, the excess is
more likely a caustic line than surface. One-sided hard trimming drops those pixels from the
loss: with ``r = target - render`` averaged over the colour channels and the robust scale
``s = 1.4826 median |r|`` of the view, a pixel counts (weight 1) where ``r <= k s`` and not
(weight 0) where it is brighter (benchmarks/RESULTS.md measures k and the alternatives).

Trimming the bright tail fits a model darker than the mean light that the photos hold (and
that the ground truth shows). ``colour_gain`` measures the survey-wide ratio of photo to
render per channel and ``apply_gain`` scales the model's colours by it.

Shapes: images (H, W, 3) float tensors; weights (H, W).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..model.gaussians import SH_C0
from ..train.objective import FixedTargets

#: Median absolute deviation to standard deviation, for normally distributed residuals.
MAD_TO_SIGMA = 1.4826
#: Smallest robust scale (1/255: one 8-bit grey level), so a model that fits a view almost
#: exactly does not trim half of it.
MIN_SCALE = 1.0 / 255.0


def trim_weights(target: torch.Tensor, render: torch.Tensor, k: float) -> torch.Tensor:
    """(H, W) weights, 1 where ``target - render`` (channel mean) is at most ``k`` robust
    sigmas, else 0 (one-sided: darker pixels always count)."""
    r = (target - render).mean(-1)
    s = (MAD_TO_SIGMA * r.abs().median()).clamp_min(MIN_SCALE)
    return (r <= k * s).to(target.dtype)


class TrimmedTargets(FixedTargets):
    """:class:`FixedTargets` whose pixels much brighter than the render do not count
    (``k`` = 0: all count), fitted with an L1 or L2 data term (``loss_kind``). While it trims
    or fits L2, the loss has no SSIM term."""

    def __init__(self, k: float, reference=None):
        super().__init__(reference)
        self.k = k
        self.loss_kind = "l1"

    @property
    def use_ssim(self) -> bool:
        """SSIM only with the plain L1 fit: its windows carry a trimmed line's light into the
        pixels around it, and it is no part of a mean (L2) fit."""
        return not self.k and self.loss_kind == "l1"

    def target(self, index, image, render):
        t, w = super().target(index, image, render)
        if not self.k:
            return t, w
        keep = trim_weights(t, render, self.k)
        return t, (keep if w is None else w * keep)


@torch.no_grad()
def colour_gain(pairs) -> torch.Tensor:
    """(3,) per-channel ratio sum(photo) / sum(render) over ``pairs`` of (photo, render)."""
    num = torch.zeros(3, dtype=torch.float64, device="cpu")
    den = torch.zeros(3, dtype=torch.float64, device="cpu")
    for photo, render in pairs:
        num += photo.double().sum(dim=(0, 1)).cpu()
        den += render.clamp_min(0).double().sum(dim=(0, 1)).cpu()
    return (num / den.clamp_min(1e-12)).float()


@torch.no_grad()
def apply_gain(params: dict, gain: torch.Tensor) -> None:
    """Scale the colours of the Gaussians (``sh_dc`` (N, 1, 3), ``sh_rest`` (N, K, 3)) by
    ``gain`` (3,): colour = 0.5 + SH, so dc' = g dc + (g - 1) 0.5 / C0 and rest' = g rest."""
    g = gain.to(params["sh_dc"].device)
    params["sh_dc"].mul_(g).add_((g - 1) * 0.5 / SH_C0)
    params["sh_rest"].mul_(g)


def normalised_lowpass(x: torch.Tensor, weight: Optional[torch.Tensor], k: int, lowpass) -> torch.Tensor:
    """Low-pass of ``x`` (H, W, C) over the pixels that count: ``LP(w x) / LP(w)`` (normalised
    convolution), ``LP(x)`` without weights. Where the low-passed weight falls below 0.1 the
    denominator is held at 0.1, so an area with almost nothing that counts stays bounded."""
    if weight is None:
        return lowpass(x, k)
    w = weight.unsqueeze(-1).to(x.dtype)
    den = lowpass(w, k).clamp_min(0.1)
    return lowpass(w * x, k) / den
