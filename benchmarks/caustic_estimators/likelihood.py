"""Caustics as the noise of a survey: fit each seabed point to the light its views most likely saw.

A seabed point of colour ``G`` (under the caustics' mean light) shows ``g_v G`` in view ``v``,
``g_v`` the caustic gain there and then (grey: it scales every channel alike; mean 1: caustics
move light, they add none). Plain 3DGS fits each point to the *median* of what its views show
(an L1 loss), RecGS's low-pass takes out only the broad part of ``g``. But the gains of a survey
follow one distribution, and the photos show it: the log ratio ``r = log(I) - log(render)`` (in
linear light) over all training pixels is ``log g`` blurred by what the model does not yet
fit. With ``p`` that distribution, shifted so that ``E[g] = 1``, the most likely colour of a
point seen by several views maximises ``sum_v log p(r_v)``: where the light is sharp bright
lines over a dim floor (light networks), ``p`` is steep below its floor and flat above, and the
estimate follows the views that caught the point between lines (about the lower envelope,
brought back to the mean light); where the light is broad waves, ``p`` is near symmetric and
the estimate is about the mean. benchmarks/pointwise_bound.py measures it against the mean,
the median and the minimum for every pattern of the survey generator.

:class:`GainLikelihood` is ``rho = -log p`` as a table over ``r``, fitted to the residuals of a
model (:meth:`GainLikelihood.fit`); training on ``rho(r)`` instead of ``|I - render|`` is the
maximum-likelihood fit of every point at once. Refitting ``p`` as the model improves is the
recurrence (``recgs.py``): the residuals narrow to the light alone.

The light of a view is then ``I / render`` (grey, in linear light), smoothed over a pixel or two
(the light is smooth at the scale the generator's and the sea's blur give it; the model's own
texture errors are finer): :func:`light_map`. The caustic-free photo is ``I`` divided by it
(:func:`remove_light`), keeping the photo's own detail.

Shapes: images (H, W, 3) float tensors, sRGB in [0, 1]; log-ratios (H, W, 3) or (H, W); light
maps (H, W) log gains.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
from recgs_addon.core.train.objective import Objective

#: Offset inside the logarithms, in linear light (an 8-bit sRGB level of about 25: the log of
#: darker pixels would be mostly sensor and 8-bit noise).
LIN_EPS = 0.01
#: Offset of the grey light (the sum of three linear channels) in a view's light map: small,
#: since the map divides whole colours, and its blur averages the noise of dark pixels.
LIGHT_EPS = 0.003
#: Residuals are tabulated over [-R_MAX, R_MAX] (log units: a gain from 1/20 to 20).
R_MAX = 3.0
#: Table bins (0.025 log units each).
BINS = 241
#: The histogram is smoothed by a Gaussian of this many bins before taking its log.
SMOOTH_BINS = 2.0
#: Density floor, relative to the peak, where no residual fell.
FLOOR = 1e-4
#: Slope (rho per log unit) the table's ends extend with, at the least.
MIN_TAIL_SLOPE = 1.0


def log_ratio(image: torch.Tensor, render: torch.Tensor, eps: float = LIN_EPS) -> torch.Tensor:
    """``log(linear(image) + e) - log(linear(render) + e)`` per pixel and channel (differentiable
    in ``render``, which is clamped at 0 as the display is)."""
    return torch.log(srgb_to_linear(image) + eps) - torch.log(srgb_to_linear(render.clamp_min(0)) + eps)


@dataclass
class GainLikelihood:
    """``rho(r) = -log p(r)`` (minimum 0) on the grid ``r0 + i * dr``, i = 0..len(rho)-1,
    extended beyond it by straight lines of slope ``slope_lo`` (below, negative) and
    ``slope_hi`` (above). ``shift`` is the log mean gain of the residuals it was fitted to
    (``log E[exp r]``): the render's light against the photos'."""

    r0: float
    dr: float
    rho: torch.Tensor
    slope_lo: float
    slope_hi: float
    shift: float = 0.0

    @classmethod
    def fit(cls, residuals: torch.Tensor, weights: Optional[torch.Tensor] = None, bins: int = BINS,
            r_max: float = R_MAX, smooth_bins: float = SMOOTH_BINS) -> "GainLikelihood":
        """Fit to residuals ``r`` (any shape; ``weights`` alike, optional). The histogram is
        shifted so that ``E[exp r] = 1`` under it (the gains' mean light), smoothed, turned into
        ``-log p`` and made unimodal (non-increasing up to its minimum, non-decreasing after):
        a sample is never pulled away from the most likely gain."""
        r = residuals.detach().reshape(-1).double().cpu()
        w = torch.ones_like(r) if weights is None else weights.detach().reshape(-1).double().cpu()
        ok = torch.isfinite(r) & (w > 0)
        r, w = r[ok], w[ok]
        if r.numel() == 0:
            raise ValueError("no residuals to fit the gain likelihood to")
        shift = float(torch.log((w * torch.exp(r.clamp(-r_max, r_max))).sum() / w.sum()))
        r = r - shift
        dr = 2 * r_max / (bins - 1)
        idx = ((r + r_max) / dr).round().clamp(0, bins - 1).long()
        hist = torch.zeros(bins, dtype=torch.float64, device="cpu").index_add_(0, idx, w)   # the fit runs on the CPU
        if smooth_bins > 0:
            half = int(math.ceil(4 * smooth_bins))
            x = torch.arange(-half, half + 1, dtype=torch.float64, device="cpu")
            kern = torch.exp(-0.5 * (x / smooth_bins) ** 2)
            hist = torch.nn.functional.conv1d(hist.view(1, 1, -1), (kern / kern.sum()).view(1, 1, -1),
                                              padding=half).view(-1)
        p = hist / hist.max()
        rho = -torch.log(p + FLOOR)
        mode = int(torch.argmin(rho))
        # unimodal: rho never falls moving away from the mode
        left = torch.flip(torch.cummax(torch.flip(rho[:mode + 1], [0]), 0).values, [0])
        right = torch.cummax(rho[mode:], 0).values
        rho = torch.cat([left, right[1:]])
        rho = rho - rho.min()
        populated = torch.nonzero(p > 10 * FLOOR).squeeze(1)
        lo, hi = int(populated.min()), int(populated.max())
        # each tail continues with the mean slope from the mode to its end of the data: steep
        # below a floor of dim light, gentle above it where bright lines spread
        slope_lo = min(-MIN_TAIL_SLOPE, float(rho[lo] - rho[mode]) / (min(lo - mode, -1) * dr))
        slope_hi = max(MIN_TAIL_SLOPE, float(rho[hi] - rho[mode]) / (max(hi - mode, 1) * dr))
        # beyond the populated range the table continues with the tail slopes
        i = torch.arange(bins, dtype=torch.float64, device="cpu")
        rho = torch.where(i < lo, rho[lo] + slope_lo * (i - lo) * dr, rho)
        rho = torch.where(i > hi, rho[hi] + slope_hi * (i - hi) * dr, rho)
        return cls(-r_max, dr, rho.float(), slope_lo, slope_hi, shift)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """``rho(r)``, piecewise linear between the grid points (differentiable in ``r``)."""
        table = self.rho.to(r.device)
        n = table.shape[0]
        x = (r - self.r0) / self.dr
        xc = x.clamp(0, n - 1)
        i0 = xc.floor().long().clamp(0, n - 2)
        frac = xc - i0
        val = table[i0] * (1 - frac) + table[i0 + 1] * frac
        below = (x < 0).to(r.dtype)
        above = (x > n - 1).to(r.dtype)
        return (val + below * self.slope_lo * (x - 0) * self.dr
                + above * self.slope_hi * (x - (n - 1)) * self.dr)

    def density(self) -> torch.Tensor:
        """The distribution ``p`` on the grid, normalised to sum 1."""
        p = torch.exp(-self.rho.double())
        return p / p.sum()

    def distance(self, other: "GainLikelihood") -> float:
        """Total variation distance between the two distributions of the gain (0: the same, 1:
        disjoint; both tables are in gain units, their mean light at 1): how much a refit
        changed what the model is fitted to."""
        if other.rho.shape != self.rho.shape or other.dr != self.dr or other.r0 != self.r0:
            return 1.0
        return float(0.5 * (self.density() - other.density()).abs().sum())

    def mode(self) -> float:
        """The most likely log gain (the floor of the light, under sparse bright caustics)."""
        return self.r0 + self.dr * int(torch.argmin(self.rho))

    def state_dict(self) -> dict:
        return {"r0": self.r0, "dr": self.dr, "rho": self.rho.cpu(), "slope_lo": self.slope_lo,
                "slope_hi": self.slope_hi, "shift": self.shift}

    @classmethod
    def from_state(cls, s: dict) -> "GainLikelihood":
        return cls(**s)


def light_map(image: torch.Tensor, render: torch.Tensor, sigma: float = 1.0,
              alpha: Optional[torch.Tensor] = None, eps: float = LIGHT_EPS) -> torch.Tensor:
    """(H, W) log light of a view against the model's render: the log ratio of their grey
    linear light (the channels' sum: caustic light scales them alike), smoothed by a Gaussian of
    ``sigma`` pixels (0: none). Where ``alpha`` (H, W) is given, pixels the model does not cover
    (alpha below 0.5) take no light (log gain 0)."""
    grey = lambda x: srgb_to_linear(x.clamp_min(0)).sum(-1)  # noqa: E731
    q = torch.log(grey(image) + eps) - torch.log(grey(render) + eps)
    if alpha is not None:
        q = torch.where(alpha > 0.5, q, torch.zeros_like(q))
    if sigma > 0:
        q = gaussian_blur(q, sigma)
    return q


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W) separable Gaussian blur with reflected edges."""
    half = max(1, int(math.ceil(3 * sigma)))
    t = torch.arange(-half, half + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    y = x.view(1, 1, *x.shape)
    y = torch.nn.functional.pad(y, (half, half, 0, 0), mode="reflect")
    y = torch.nn.functional.conv2d(y, k.view(1, 1, 1, -1))
    y = torch.nn.functional.pad(y, (0, 0, half, half), mode="reflect")
    y = torch.nn.functional.conv2d(y, k.view(1, 1, -1, 1))
    return y.view(*x.shape)


def remove_light(image: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
    """The photo under the mean light: its linear light divided by the gain ``exp(L)``, in sRGB."""
    return linear_to_srgb(srgb_to_linear(image) * torch.exp(-light).unsqueeze(-1))


class LikelihoodObjective(Objective):
    """What a view is fitted to once the gain likelihood is known: the data term
    ``w * rho(log I - log render)`` (the most likely colour of every point, ``w`` the render's
    sRGB brightness, detached: each point keeps its maximum-likelihood colour, while bright
    pixels weigh as they do in an sRGB loss and the noisy logs of dark ones do not dominate),
    and the SSIM term against the photo with its light taken out (:func:`remove_light` of
    :func:`light_map` against the step's render): structure from the photo, not its caustics.

    ``gain`` is the fitted :class:`GainLikelihood`; ``sigma(image)`` the light's blur in pixels;
    ``reference`` what held-out renders are scored against (as :class:`FixedTargets`)."""

    use_ssim = True

    def __init__(self, gain: GainLikelihood, sigma, reference=None):
        self.gain, self.sigma, self._reference = gain, sigma, reference
        self._photo: Optional[torch.Tensor] = None

    def target(self, index, image, render):
        self._photo = image
        return remove_light(image, light_map(image, render, self.sigma(image))), None

    def loss_kind(self, render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        photo = self._photo
        w = render.detach().clamp(0.02, 1.0)
        return w * self.gain(log_ratio(photo, render)) / w.mean()

    def reference(self, index, image, render):
        return image if self._reference is None else self._reference(index, image, render)
