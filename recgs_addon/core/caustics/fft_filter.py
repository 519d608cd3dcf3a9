"""The 2D FFT low-pass of RecGS (Zhang et al. 2024) and the measures of a caustic estimate, plain functions.

Images are (H, W, C) float tensors (channel last, as the trainer holds them). The low-pass
keeps a ``k x k`` block of frequencies around DC: integer frequencies ``-r..r`` cycles per
image on each axis with ``r = (k - 1) // 2`` (the paper's k = 9 keeps -4..+4), per colour
channel, and returns the real part of the inverse FFT. Where an image has fewer frequencies
than that on an axis (sides up to ``k - 1`` pixels), every frequency of the axis is kept, so
the filter is the identity there: a 1x1 or 2x2 image is returned unchanged.

Frequencies are laid out as in ``torch.fft.fft2``: index ``f mod n`` holds frequency ``f``.
For an even side ``n <= 2r`` the Nyquist index ``n/2`` is kept (it is both ``+n/2`` and
``-n/2``); for ``n > 2r`` it is not. The kept set is symmetric under ``f -> -f``, so a real
input gives a real output up to rounding.
"""
from __future__ import annotations

import math

import torch

#: The paper's block size (9x9 frequencies, DC included).
DEFAULT_K = 9


def check_k(k: int) -> int:
    if int(k) != k or k < 1 or k % 2 == 0:
        raise ValueError(f"caustic filter size k must be a positive odd integer, got {k}")
    return int(k) // 2


def frequency_indices(n: int, r: int, device=None) -> torch.Tensor:
    """FFT indices (into an axis of length ``n``) of the frequencies ``-r..r``, without repeats."""
    if 2 * r + 1 >= n:
        return torch.arange(n, device=device)
    f = torch.arange(-r, r + 1, device=device)
    return torch.remainder(f, n)


def lowpass_mask(height: int, width: int, k: int = DEFAULT_K, device=None) -> torch.Tensor:
    """(H, W) bool mask of the kept FFT coefficients."""
    r = check_k(k)
    mask = torch.zeros(height, width, dtype=torch.bool, device=device)
    rows = frequency_indices(height, r, device)
    cols = frequency_indices(width, r, device)
    mask[rows.unsqueeze(1), cols.unsqueeze(0)] = True
    return mask


def lowpass(image: torch.Tensor, k: int = DEFAULT_K) -> torch.Tensor:
    """Keep the lowest ``k x k`` frequencies of each channel of ``image`` (H, W, C) -> (H, W, C).

    Works in float64 internally for float32 input (the cost is negligible at survey sizes and
    the result is then exact to float32 rounding), returns the input dtype.
    """
    if image.dim() != 3:
        raise ValueError(f"expected an (H, W, C) image, got shape {tuple(image.shape)}")
    h, w, _ = image.shape
    x = image.permute(2, 0, 1).to(torch.float64)
    spec = torch.fft.fft2(x)
    spec = spec * lowpass_mask(h, w, k, image.device)
    out = torch.fft.ifft2(spec).real
    return out.permute(1, 2, 0).to(image.dtype).contiguous()


def filter2d(image: torch.Tensor, k: int = DEFAULT_K) -> torch.Tensor:
    """The ``filter2d`` baseline: ``I - lowpass(I - mean(I))`` per channel, no 3D model."""
    mean = image.mean(dim=(0, 1), keepdim=True)
    return image - lowpass(image - mean, k)


def caustic_change(new: list[torch.Tensor], old: list[torch.Tensor]) -> float:
    """Mean absolute change of C relative to the mean |C| over all images (1.0 from nothing)."""
    num = sum(float((a - b).abs().sum()) for a, b in zip(new, old))
    den = sum(float(a.abs().sum()) for a in new)
    if den == 0.0:
        return 0.0 if num == 0.0 else math.inf
    return num / den


def mean_abs(maps: list[torch.Tensor]) -> float:
    """Mean |value| over all pixels and channels of a list of maps."""
    total = sum(float(m.abs().sum()) for m in maps)
    count = sum(m.numel() for m in maps)
    return total / max(count, 1)


def radial_power(residuals: list[torch.Tensor], r_max: int) -> torch.Tensor:
    """Mean power of the residuals' spectra in square rings ``max(|fy|, |fx|) = r``, r = 0..r_max.

    Each image's spectrum is normalised by its pixel count, so images of different sizes
    weigh the same. Returns (r_max + 1,) float64.
    """
    dev = residuals[0].device if residuals else "cpu"
    acc = torch.zeros(r_max + 1, dtype=torch.float64, device=dev)
    cnt = torch.zeros(r_max + 1, dtype=torch.float64, device=dev)
    for res in residuals:
        h, w, _ = res.shape
        spec = torch.fft.fft2(res.permute(2, 0, 1).to(torch.float64)) / (h * w)
        power = (spec.abs() ** 2).sum(0)
        fy = torch.fft.fftfreq(h, 1.0 / h, device=dev).abs().round().long()
        fx = torch.fft.fftfreq(w, 1.0 / w, device=dev).abs().round().long()
        ring = torch.maximum(fy.unsqueeze(1), fx.unsqueeze(0))
        keep = ring <= r_max
        acc.index_add_(0, ring[keep], power[keep])
        cnt.index_add_(0, ring[keep], torch.ones_like(power[keep]))
    return (acc / cnt.clamp_min(1)).cpu()


def choose_k(residuals: list[torch.Tensor], k_min: int = 5, k_max: int = 25, ratio: float = 4.0) -> int:
    """Pick the block size from the residuals' spectrum: the largest ring radius r whose mean
    power per coefficient is still ``ratio`` times the high-frequency floor (median power of
    the rings between 2 * r_max and 4 * r_max cycles), i.e. where the low-frequency (caustic)
    excess ends. Clamped to [k_min, k_max], odd, and on small frames to a radius of an eighth of
    the smaller side, so that the floor's rings (2 to 4 times the largest radius) lie below the
    frame's Nyquist frequency: measured nearer to it, the floor was the last rings' noise, every
    ring below it counted as excess, and a 48 x 36 frame got k = 25, a "low-pass" filter that
    passes every frequency it has."""
    r_lo, r_hi = check_k(k_min), check_k(k_max)
    smallest = min(min(r.shape[0], r.shape[1]) for r in residuals)
    r_hi = max(r_lo, min(r_hi, smallest // 8))
    r_far = max(r_hi + 1, min(4 * r_hi, smallest // 2))
    power = radial_power(residuals, r_far)
    floor_rings = power[min(2 * r_hi, r_far - 1):r_far + 1]
    floor = float(floor_rings.median()) if floor_rings.numel() else float(power[-1])
    r = r_lo
    for ring in range(1, r_hi + 1):
        if float(power[ring]) >= ratio * floor:
            r = max(r, ring)
    return 2 * min(r, r_hi) + 1
