"""Image losses and metrics (torch): L1, SSIM (INRIA's definition), PSNR.

Images are (H, W, 3) or (B, 3, H, W) float tensors in [0, 1] (HWC inputs are converted).
SSIM follows INRIA 3DGS / Wang et al. 2004: an 11x11 Gaussian window with sigma 1.5,
C1 = 0.01^2, C2 = 0.03^2, zero padding of 5 px so the map has the image's size, averaged
over pixels and channels.
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
#: Weight of (1 - SSIM) in the training loss (INRIA's lambda_dssim).
LAMBDA_DSSIM = 0.2


def _bchw(img: torch.Tensor) -> torch.Tensor:
    if img.dim() == 3:  # (H, W, C)
        return img.permute(2, 0, 1).unsqueeze(0)
    return img


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float32):
    """(size,) normalised 1D Gaussian, on the CPU (the blur reads its taps as numbers)."""
    x = torch.arange(size, dtype=torch.float64, device="cpu") - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return (g / g.sum()).to(dtype)


def _blur(x: torch.Tensor, w1d: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W) with zero padding (same as INRIA's 2D conv),
    as shifted multiply-adds: on the CPU about twice as fast as a grouped convolution for an
    11-tap window (its depthwise kernel is slow), equal to float32 rounding. Not
    differentiable by itself (:class:`_SymmetricBlur` is)."""
    k = w1d.numel()
    r = k // 2
    h, w = x.shape[-2:]
    taps = [float(v) for v in w1d]
    xp = F.pad(x, (r, r))
    y = xp[..., 0:w] * taps[0]
    for i in range(1, k):
        y.add_(xp[..., i:i + w], alpha=taps[i])
    yp = F.pad(y, (0, 0, r, r))
    z = yp[..., 0:h, :] * taps[0]
    for i in range(1, k):
        z.add_(yp[..., i:i + h, :], alpha=taps[i])
    return z


class _SymmetricBlur(torch.autograd.Function):
    """:func:`_blur` whose backward is the same blur: with a symmetric window and zero
    padding each separable pass is a symmetric banded matrix, so the adjoint of the blur is
    the blur itself (checked with gradcheck in tests/test_losses.py)."""

    @staticmethod
    def forward(ctx, x, w1d):
        ctx.w1d = w1d
        return _blur(x, w1d)

    @staticmethod
    def backward(ctx, g):
        return _blur(g.contiguous(), ctx.w1d), None


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two images (differentiable in both)."""
    return ssim_map(a, b).mean()


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) SSIM of each pixel's window."""
    a, b = _bchw(a), _bchw(b)
    w = gaussian_window(dtype=a.dtype)
    # the blurs work per channel, so a few images blur in one call: one for the three that
    # follow ``a``, one for the two of ``b`` alone (in training the target, constant: no
    # graph, no backward)
    c = a.shape[1]

    def blur(x):
        return _SymmetricBlur.apply(x, w) if torch.is_grad_enabled() and x.requires_grad else _blur(x, w)

    mu_a, e_aa, e_ab = blur(torch.cat([a, a * a, a * b], 1)).split(c, 1)
    mu_b, e_bb = blur(torch.cat([b, b * b], 1)).split(c, 1)
    mu_aa, mu_bb, mu_ab = mu_a * mu_a, mu_b * mu_b, mu_a * mu_b
    var_a = e_aa - mu_aa
    var_b = e_bb - mu_bb
    cov = e_ab - mu_ab
    num = (2 * mu_ab + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_aa + mu_bb + SSIM_C1) * (var_a + var_b + SSIM_C2)
    return num / den


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()


def ssim_term(render: torch.Tensor, target: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The SSIM part of :func:`training_loss`: ``1 - SSIM(render, target)`` (``weight`` None),
    or the weighted mean over pixels of ``1 - S`` (S the per-pixel SSIM, averaged over the
    channels). :func:`.numba_ssim.ssim_term` computes the same through numba's kernels."""
    if weight is None:
        return 1.0 - ssim(render, target)
    smap = ssim_map(render, target).mean(1)[0]   # (H, W)
    return ((1.0 - smap) * weight).sum() / weight.sum().clamp_min(1e-12)


def training_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float = LAMBDA_DSSIM,
                  weight: Optional[torch.Tensor] = None, kind: str = "l1",
                  fast_ssim: Optional[Callable] = None):
    """(1 - lambda) D + lambda (1 - SSIM), with D the mean absolute error (``kind="l1"``, as
    INRIA 3DGS and RecGS), the mean squared error (``"l2"``) or the mean of ``kind(render,
    target)`` (a function giving (H, W, 3): the benchmarks' caustic likelihood,
    benchmarks/caustic_estimators/likelihood.py). ``render``, ``target``: (H, W, 3). ``weight``
    (H, W), optional: how much each pixel counts; both terms become weighted means over the
    pixels (the SSIM term of each pixel's window), so a weight of 1 everywhere gives the plain
    loss. ``fast_ssim``: another implementation of
    :func:`ssim_term` that differentiates the render only (:func:`.numba_ssim.ssim_term`: the
    same numbers to float32 rounding), used where the target and weight need no gradient (a
    learnt target, as the joint baseline's, takes the eager term).

    Where views disagree about a point (moving light), an L1 fit takes the *median* of what
    they show and an L2 fit the *mean*; benchmarks/pointwise_bound.py measures the two."""
    if callable(kind):   # a data term of its own: (render, target) -> (H, W, 3) per pixel and channel
        d = kind(render, target)
    elif kind in ("l1", "l2"):
        d = render - target
        d = d.abs() if kind == "l1" else d * d
    else:
        raise ValueError(f"unknown loss kind {kind!r} (l1, l2 or a function)")
    if weight is None:
        loss = (1.0 - lambda_dssim) * d.mean()
    else:
        loss = (1.0 - lambda_dssim) * (d * weight.unsqueeze(-1)).sum() / (3 * weight.sum().clamp_min(1e-12))
    if not lambda_dssim:
        return loss
    term = ssim_term
    if fast_ssim is not None and not target.requires_grad and not (weight is not None and weight.requires_grad):
        term = fast_ssim
    return loss + lambda_dssim * term(render, target, weight)


def psnr(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR in dB for images (H, W, C) in [0, 1] (inf for identical images), over the pixels
    where ``mask`` (H, W) bool is set (default all)."""
    err = (a.double() - b.double()) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return math.inf
        err = err[mask]
    mse = float(err.mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
