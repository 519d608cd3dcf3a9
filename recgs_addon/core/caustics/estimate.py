"""The caustic estimate of one view from its photo and a render, and its removal (plain
functions; images are (H, W, 3) tensors in [0, 1] intensity).

* additive (the paper): ``C = lowpass(I - render)``, caustic-free ``I - C``;
* multiplicative: caustics modulate the light, so the estimate is a log-gain
  ``L = lowpass(log(I + e) - log(render + e))`` and the caustic-free image ``(I + e) exp(-L) - e``.

Without the DC term (``dc=False``), ``C`` has zero mean per view and channel: caustics move
light without adding any, and a DC term would carry the model's brightness error.
"""
from __future__ import annotations

from typing import Optional

import torch

from .fft_filter import lowpass
from .robust import normalised_lowpass

#: Offset (in [0, 1] intensity) inside the logarithms of the multiplicative model.
LOG_EPS = 0.02


def estimate_caustics(image: torch.Tensor, render: torch.Tensor, k: int, model: str = "additive",
                      dc: bool = False, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Caustic estimate (H, W, 3) of a view: the ``k x k`` low-pass of its residual, taken over
    the pixels that count where ``weight`` (H, W) is given (normalised convolution)."""
    if model == "multiplicative":
        resid = torch.log(image + LOG_EPS) - torch.log(render.clamp_min(0) + LOG_EPS)
    else:
        resid = image - render
    est = normalised_lowpass(resid, weight, k, lowpass)
    if not dc:
        est = est - est.mean(dim=(0, 1), keepdim=True)
    return est


def remove_caustics(image: torch.Tensor, cmap: torch.Tensor, model: str = "additive") -> torch.Tensor:
    """The caustic-free image (not clipped) for a caustic estimate of ``model``."""
    if model == "multiplicative":
        return (image + LOG_EPS) * torch.exp(-cmap) - LOG_EPS
    return image - cmap


def compensate_caustics(image: torch.Tensor, render: torch.Tensor, k: int, model: str = "additive",
                        dc: bool = False, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``image`` with the caustics its residual against ``render`` shows taken out: what a
    held-out render is scored against once caustics are estimated (``remove_caustics`` of
    ``estimate_caustics``)."""
    return remove_caustics(image, estimate_caustics(image, render, k, model, dc, weight), model)
