"""Light fixed to the camera: a lamp's cone and its fall-off with range, and the lens's vignetting.

A lamp or strobe on the camera lights each seabed point by where the point lies in the image
and how far it is, the same in every frame. Per pixel, in linear light::

    seen = J * L(x, r),   log L(x, r) = F(x) + a log(r / r0) + b (r - r0)

``x`` is the pixel's position (centred on the principal point, in half-widths of the image),
``r`` its range along the ray (scene units), ``F`` a smooth pattern over the image (the
polynomial terms x^i y^j, 1 <= i + j <= 4: a cone, vignetting), ``a`` the fall-off with range
(-2 for a bare lamp's inverse square) and ``b`` what the water takes on the lamp's path (per
scene unit). ``F(0) = 0`` and the range terms vanish at ``r0``: where the lamp lights the centre
of the frame at the survey's usual range (the median range at the image centre), ``seen = J``.
The Gaussians then hold the seabed under that light, evenly; the lamp is sixteen numbers beside
them (:data:`TERMS` pattern terms and two for the range), grey (a lamp's colour is the seabed's
colour under it).

Like the water (medium.py), the gain is applied once a pixel to the render in linear light,
with the range from the render's expected depth, not differentiated; the pattern's terms are
those core/caustics/light.py fits between frames before training, which starts it.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from .colour import linear_to_srgb

#: Degree of the pattern's polynomial over the image.
DEGREE = 4
#: Its terms, (i, j) for x^i y^j: 1 <= i + j <= DEGREE.
POWERS = tuple((d - b, b) for d in range(1, DEGREE + 1) for b in range(d + 1))
TERMS = len(POWERS)
#: The gain is kept within these (log units): far outside, a pixel says nothing of the seabed.
LOG_GAIN_RANGE = (-5.0, 3.0)


def pattern_terms(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(..., TERMS) the polynomial terms at centred positions ``x``, ``y`` (half-widths)."""
    return torch.stack([x ** i * y ** j for i, j in POWERS], -1)


def image_positions(width: int, height: int, cx: float, cy: float, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W) centred positions of the pixel centres, in half-widths of the image."""
    half = 0.5 * width
    u = (torch.arange(width, dtype=torch.float32, device=device) + 0.5 - cx) / half
    v = (torch.arange(height, dtype=torch.float32, device=device) + 0.5 - cy) / half
    return u[None, :].expand(height, width), v[:, None].expand(height, width)


class Lamp:
    """The light fixed to the camera (see the module): ``raw`` holds the pattern's
    :data:`TERMS` coefficients, then ``a`` and ``b`` (``b`` per ``r0``, so the survey's scale
    does not change how it trains)."""

    def __init__(self, r0: float, pattern: Optional[Sequence[float]] = None, fall: float = 0.0,
                 attenuation: float = 0.0, device="cpu"):
        #: the range (scene units) at which the range terms vanish
        self.r0 = float(r0)
        coef = list(pattern) if pattern is not None else [0.0] * TERMS
        if len(coef) != TERMS:
            raise ValueError(f"a lamp's pattern has {TERMS} terms, got {len(coef)}")
        self.raw = torch.nn.Parameter(torch.tensor(coef + [float(fall), float(attenuation) * self.r0],
                                                   dtype=torch.float32, device=device))
        self._terms: dict = {}

    def _pattern_terms(self, width: int, height: int, cx: float, cy: float) -> torch.Tensor:
        key = (width, height, cx, cy, self.raw.device)
        if key not in self._terms:
            x, y = image_positions(width, height, cx, cy, self.raw.device)
            self._terms[key] = pattern_terms(x, y)
        return self._terms[key]

    def _log_gain(self, terms: torch.Tensor, rng: torch.Tensor) -> torch.Tensor:
        coef, a, b = self.raw[:TERMS], self.raw[TERMS], self.raw[TERMS + 1] / self.r0
        r = rng.detach().clamp_min(1e-3 * self.r0)
        return (terms @ coef + a * torch.log(r / self.r0) + b * (r - self.r0)).clamp(*LOG_GAIN_RANGE)

    def log_gain(self, width: int, height: int, cx: float, cy: float, rng: torch.Tensor) -> torch.Tensor:
        """(H, W) ``log L`` of a view whose pixels lie at range ``rng`` (H, W), differentiable in
        :attr:`raw` (not in the range)."""
        return self._log_gain(self._pattern_terms(width, height, cx, cy), rng)

    def log_gain_at(self, x: torch.Tensor, y: torch.Tensor, rng: torch.Tensor) -> torch.Tensor:
        """``log L`` at centred image positions ``x``, ``y`` (half-widths) and ranges ``rng``
        (any shape, the same for all three)."""
        return self._log_gain(pattern_terms(x, y), rng)

    def gain(self, width: int, height: int, cx: float, cy: float, rng: torch.Tensor) -> torch.Tensor:
        """(H, W) the lamp's gain ``L`` (see the module)."""
        return torch.exp(self.log_gain(width, height, cx, cy, rng))

    # --- plain numbers (reports, checkpoints) ---------------------------------------------
    def values(self) -> dict:
        raw = self.raw.detach().cpu().double()
        return {"pattern": raw[:TERMS].tolist(), "fall": float(raw[TERMS]),
                "attenuation": float(raw[TERMS + 1]) / self.r0, "r0": self.r0}

    def state_dict(self) -> dict:
        return {"r0": self.r0, "raw": self.raw.detach().cpu().clone()}

    @classmethod
    def from_state(cls, state: dict, device="cpu") -> "Lamp":
        lamp = cls(state["r0"], device=device)
        with torch.no_grad():
            lamp.raw.copy_(state["raw"].to(device))
        return lamp

    def spread(self, width: int, height: int, cx: float, cy: float, rng: torch.Tensor) -> float:
        """The standard deviation of ``log L`` over a view (how uneven the lamp lights it)."""
        with torch.no_grad():
            return float(self.log_gain(width, height, cx, cy, rng).std())


#: Observations darker than this (linear grey) say nothing of the lamp (8-bit black, shadow).
FIT_DARK = 1e-3
#: Huber's threshold (log units) and the reweighting rounds of :func:`fit_to_points`.
FIT_HUBER = 0.1
FIT_ROUNDS = 6
#: The ridge on the lamp's terms (per unit of weight): terms the points do not pin stay small.
FIT_RIDGE = 1e-6
#: Least observations (in points seen at least twice) for :func:`fit_to_points` to answer.
FIT_MIN_OBSERVATIONS = 500


def _within_points(A, g, pid, noise_w, ridge, rounds):
    """Robust weighted least squares of ``g`` on the columns ``A`` with each point's own level
    (``pid``) eliminated: coefficients and residuals."""
    w = noise_w.copy()
    coef = np.zeros(A.shape[1])
    res = g - g.mean()
    for _ in range(rounds):
        wsum = np.bincount(pid, weights=w).clip(1e-12)
        sums = [np.bincount(pid, weights=w * A[:, c]) for c in range(A.shape[1])]
        Ac = A - ((np.stack(sums, -1) if sums else np.zeros((len(wsum), 0))) / wsum[:, None])[pid]
        gc = g - (np.bincount(pid, weights=w * g) / wsum)[pid]
        Aw = Ac * w[:, None]
        coef = np.linalg.solve(Aw.T @ Ac + np.diag(ridge * w.sum()), Aw.T @ gc)
        res = gc - Ac @ coef
        w = noise_w * np.minimum(1.0, FIT_HUBER / np.maximum(np.abs(res), 1e-12))
    return coef, res


def fit_to_points(point, x, y, rng, grey, r0: float, start: Optional[dict] = None,
                  rounds: int = FIT_ROUNDS) -> Optional[dict]:
    """The lamp (its pattern terms, ``fall`` and ``attenuation``, as :class:`Lamp` takes them)
    from sparse points seen in several views: observation ``k`` of point ``point[k]`` at
    centred image position (``x[k]``, ``y[k]``) (half-widths), range ``rng[k]`` and linear
    grey level ``grey[k]`` obeys ``log grey = log J_p + log L(x, r)`` (no exposure per view:
    it would take up the range's fall-off between views). Every point's own level is
    eliminated (each point's weighted mean taken out of both sides, which gives the exact
    least squares of the common terms), the fit is robust (Huber's weights over ``rounds``),
    weighted by the 8-bit noise of a log (an sRGB level ``s`` carries log noise as 1/s, so
    dark observations count less), and the lamp's terms are kept small where the points do
    not pin them (a ridge, :data:`FIT_RIDGE`). Every observation of every view enters, into
    the frame's dark edges, so a narrow beam is fitted where the frames' pairs see too little
    of it. Returns ``pattern``, ``fall``, ``attenuation``, ``spread`` (the residuals' robust
    standard deviation, log units: the points' noise and what the lamp's terms cannot
    follow), ``observations``, and with ``start`` (another lamp's values) ``start_spread``:
    the same spread of that lamp's; None where fewer than
    :data:`FIT_MIN_OBSERVATIONS` are usable."""
    point = np.asarray(point, np.int64)
    grey = np.asarray(grey, np.float64)
    r = np.asarray(rng, np.float64)
    ok = (grey > FIT_DARK) & np.isfinite(r) & (r > 1e-3 * r0)
    if ok.any():   # points seen once carry no ratio
        counts = np.bincount(point[ok], minlength=int(point.max()) + 1)
        ok &= counts[point] >= 2
    if int(ok.sum()) < FIT_MIN_OBSERVATIONS:
        return None
    point, grey, r = point[ok], grey[ok], r[ok]
    xs, ys = np.asarray(x, np.float64)[ok], np.asarray(y, np.float64)[ok]
    _, pid = np.unique(point, return_inverse=True)
    lamp_cols = np.concatenate([np.stack([xs ** i * ys ** j for i, j in POWERS], -1),
                                np.stack([np.log(r / r0), r - r0], -1)], -1)
    g = np.log(grey)
    s = linear_to_srgb(torch.from_numpy(grey)).numpy()   # the sRGB level
    noise_w = np.minimum(1.0, (s / np.median(s)) ** 2)
    coef, res = _within_points(lamp_cols, g, pid, noise_w, np.full(TERMS + 2, FIT_RIDGE), rounds)
    out = {"pattern": coef[:TERMS].tolist(), "fall": float(coef[TERMS]), "attenuation": float(coef[TERMS + 1]),
           "spread": float(1.4826 * np.median(np.abs(res))), "observations": int(len(g))}
    if start is not None:
        c0 = np.array(list(start["pattern"]) + [start["fall"], start["attenuation"]], np.float64)
        _, res0 = _within_points(np.zeros((len(g), 0)), g - lamp_cols @ c0, pid, noise_w, np.zeros(0), rounds)
        out["start_spread"] = float(1.4826 * np.median(np.abs(res0)))
    return out
