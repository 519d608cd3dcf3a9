"""Per-view light fields: caustics as light *added over a floor*, found as coherent structure.

Caustics focus sunlight into bright lines over a dimmer floor, and move between shots: at a
seabed point, the photos that catch it between lines agree on a low value, the others are
brighter by a varying amount. The light field of view ``v`` relative to the model's render is
the grey log-ratio ``q = mean_c log((I + e) / (render + e))``. Its estimate is

    L = lowpass_k(q) - mean  +  max(0, TV_lam(q - lowpass_k(q) + mean) - tau)

* the low band (two-sided, mean-free: RecGS's own estimate, in log light) takes broad light
  that every view sees differently;
* the rest is *one-sided*: only light the photo holds above the model counts as caustic
  (a photo darker than the model is evidence that the model is too bright, never light to
  take out), and only where it forms coherent structure: total-variation denoising
  (``tv.py``) keeps long lines and cells of high contrast, flattens pixel noise and the small
  texture errors of a model still learning, and ``tau`` leaves a dead band for what remains.

Trained against ``(I + e) exp(-L) - e`` in turn with re-estimating ``L`` (the recurrence of
RecGS), the model settles near the *floor* of the light its views saw at each point: the
lower envelope, which under sparse bright caustics holds far less of them than the mean does
(benchmarks/RESULTS.md measures it). That model is darker than the mean light the ground truth
shows; the photos hold the mean (caustics move light, they add none), so the survey-wide
ratio of photo to render, in linear light, restores it (:func:`linear_gain`,
:func:`apply_linear_gain`).

Shapes: images (H, W, 3) float tensors in [0, 1] sRGB; light fields (H, W) or (B, H, W).
"""
from __future__ import annotations

from typing import Iterable

import torch

from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
from recgs_addon.core.model.gaussians import SH_C0
from recgs_addon.core.caustics import fft_filter
from recgs_addon.core.caustics.robust import colour_gain
from recgs_addon.core.caustics.tv import tv_denoise

#: Offset (in [0, 1] intensity) inside the logarithms (as estimate.LOG_EPS).
LOG_EPS = 0.02


def grey_log_ratio(image: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
    """(H, W) channel mean of ``log(image + e) - log(render + e)``: caustic light is grey (it
    scales all three channels alike), so the channels' mean is its estimate with a third of
    the noise."""
    return (torch.log(image + LOG_EPS) - torch.log(render.clamp_min(0) + LOG_EPS)).mean(-1)


def light_fields(q: torch.Tensor, k: int, lam: float, tau: float = 0.0, iters: int = 100) -> torch.Tensor:
    """(B, H, W) log light fields ``L`` from grey log-ratios ``q`` (B, H, W) (module docstring):
    low band of size ``k`` (0: none), TV weight ``lam`` (log units per pixel of edge), dead
    band ``tau`` (log units)."""
    if k:
        low = torch.stack([fft_filter.lowpass(x.unsqueeze(-1), k)[..., 0] for x in q])
        low = low - low.mean(dim=(1, 2), keepdim=True)
    else:
        low = torch.zeros_like(q)
    high = tv_denoise(q - low, lam, iters=iters) if lam > 0 else q - low
    return low + (high - tau).clamp_min(0)


def remove_light(image: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """``(image + e) exp(-L) - e`` for a light field ``L`` (H, W): the photo under the floor light."""
    return (image + LOG_EPS) * torch.exp(-field).unsqueeze(-1) - LOG_EPS


@torch.no_grad()
def linear_gain(pairs: Iterable) -> torch.Tensor:
    """(3,) per-channel ratio sum(photo) / sum(render) in *linear* light over ``pairs`` of
    (photo, render) sRGB images: caustics scale linear light, so their mean is 1 there
    (:func:`robust.colour_gain` on the linearised pairs)."""
    return colour_gain((srgb_to_linear(photo), srgb_to_linear(render)) for photo, render in pairs)


def scale_linear(image: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """The sRGB ``image`` (H, W, 3) with its linear light scaled by ``gain`` (3,)."""
    return linear_to_srgb(srgb_to_linear(image) * gain.to(image.device))


@torch.no_grad()
def apply_linear_gain(params: dict, gain: torch.Tensor) -> None:
    """Scale the linear light of the Gaussians' colours by ``gain`` (3,): the base colour
    ``c = 0.5 + C0 dc`` becomes ``srgb(gain * linear(c))``; the higher SH coefficients scale
    by the same factor as ``c`` (the view-dependent part keeps its share of the colour)."""
    dc = params["sh_dc"]
    c = 0.5 + SH_C0 * dc
    c_new = linear_to_srgb(srgb_to_linear(c) * gain.to(dc.device))
    ratio = torch.where(c > 1e-3, c_new / c.clamp_min(1e-3), torch.ones_like(c))
    dc.copy_((c_new - 0.5) / SH_C0)
    params["sh_rest"].mul_(ratio)
