"""The water measured from points seen at several ranges: a fit with each point's colour
eliminated, and how well the survey pins each coefficient.

Every observation ``k`` is one point ``p`` seen at range ``r_k`` with linear colour ``y_k``; per
colour channel (core/model/medium.py)::

    y_k = J_p * exp(-attenuation * r_k) + V(r_k),    V(r) = veil * (1 - exp(-backscatter * r))

For given water the best ``J_p`` of every point is a weighted least-squares mean in closed form,
so the fit searches the three water numbers of a channel only (variable projection: Golub and
Pereyra, 1973), in float64 with L-BFGS, and converges whatever the number of points. Texture,
occlusion and misregistration make heavy-tailed errors: the squares are reweighted as Huber's
loss (iteratively reweighted least squares, the scale from the residuals' median absolute
deviation). The veil is searched as its value at the survey's median range ``length`` and its
rate, which a survey flown at one height pins very differently (the first well, the rate hardly).

Under light that moves over the seabed (sunlight caustics) every observation's seabed part is
multiplied by a gain of mean 1 that changes from view to view, ``y_k = g_k J_p exp(-attenuation
r_k) + V(r_k)``, and the fit above is biased for such errors, robust or not: with each point's
colour projected out, the noise the projection leaves depends on the attenuation (on generated
surveys under caustics a channel read up to 88 % too high). :func:`fit_under_light` uses the
light instead. The gain is grey (the same in every channel, in linear light), so the log ratio
of two channels' seabed parts
``log((y_c - V_c) / (y_g - V_g)) = log(J_c / J_g) - (attenuation_c - attenuation_g) r`` holds no
light at all: wrong veils make it change with the gain within a point, which pins the veil, and its
slope with range is the channels' difference in attenuation. The attenuation common to all
channels comes from green's log slope, ``log(y_g - V_g) = log J_g - attenuation_g r + log g``,
where the light adds the same noise at every range. The veil's rate starts equal to each channel's
attenuation (the single-coefficient model of the water) and is then searched too.

The attenuation is searched over all real numbers: a survey without water gets a value near 0,
either sign, and its spread says whether the photos show any (``z``, the attenuation over its
spread). The spreads come from refitting on the points drawn again with replacement (the
bootstrap, Efron 1979): the points, not the observations, are the independent draws.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

#: Huber's tuning constant (95 % efficiency under Gaussian noise), in robust standard deviations.
HUBER_K = 1.345
#: Tukey's biweight constant (95 % efficiency under Gaussian noise).
TUKEY_C = 4.685
#: Reweighting rounds of the robust fit (the first half Huber's, the rest the biweight).
IRLS_ROUNDS = 4
#: The backscatter's rate searched, times the median range (its curve is a line below, a step above).
RATE_RANGE = (0.02, 8.0)
#: How far a natural water's backscatter rate may lie from its attenuation (a factor either
#: way): the width the error bars of a rate tied to it cover (:func:`tie_free_rates_of`).
RATE_PRIOR_WIDTH = 2.0
#: Backscatter rates (times the median range) a cold fit starts from.
COLD_RATES = (0.1, 0.5, 2.0)
#: Under moving light: the seabed's part of a colour is compared in logs above this share of
#: the channel's median colour (a darker one is mostly noise and veil).
LOG_FLOOR = 0.05
#: ... rounds with the veil's rate tied to the attenuation, then with it searched.
TIED_ROUNDS = 3
FREE_ROUNDS = 2
#: ... rounds with the rate tied where the survey leaves it free (:func:`tie_rates_under_light`),
#: ended sooner where every attenuation moves by less than :data:`SETTLED` of the largest.
TIED_ONLY_ROUNDS = 12
SETTLED = 1e-3
#: ... Levenberg-Marquardt's steps in each reweighting round of the log ratios' fit.
LM_STEPS = 30
#: ... the channel whose log slope gives the attenuation common to all (green: the brightest
#: under water, and the one the veil's colour and the light's gain are measured against).
REFERENCE = 1
#: The light's spread from view to view over the photos' noise from which the fit under light
#: is used (on points under a skewed light of mean 1: at 1.2 times the noise it read red 18 %
#: off where the plain fit read 1.5 %; at 2.6 both within 3-7 %; at 5 and above it was the
#: closer, and the surveys under caustic networks here measure 35-64).
LIGHT_OVER_NOISE = 3.0
#: ... and where every channel's veil ends below this share of its bound (the darker colours
#: seen): a survey under caustics without water drove its veils to 0.90-1.00 of the bound and
#: read a grey attenuation of 0.3 a unit where there was none; behind water they ended at
#: 0.19-0.64.
VEIL_BOUND = 0.9
#: Where the light moves, the plain fit (the start, and the fit kept where the light is too
#: weak) and every refit use this many of the observations; the fit under light uses them all.
LIGHT_SUBSET = 12_000
#: Quantile of a channel's observed colours the veil in front of them stays below (high enough
#: that the noise of the darkest colours does not pull the bound under the veil).
DARKEST = 0.25


def _veil_curve(rate: torch.Tensor, r: torch.Tensor, length: float) -> torch.Tensor:
    """(1 - exp(-rate r)) / (1 - exp(-rate length)): the veil's growth with range, 1 at ``length``."""
    return torch.expm1(-rate * r) / torch.expm1(-rate * length)


def _point_colours(pt, n, a, z, w):
    """Each point's least-squares colour ``J`` for ``z ~ J a`` with weights ``w`` (0 where unseen)."""
    num = torch.zeros(n, dtype=a.dtype).index_add_(0, pt, w * a * z)
    den = torch.zeros(n, dtype=a.dtype).index_add_(0, pt, w * a * a)
    return num / den.clamp_min(1e-12)


def _huber_weights(res: torch.Tensor, scale) -> torch.Tensor:
    return (HUBER_K * scale / res.abs().clamp_min(1e-12)).clamp(max=1.0)


def _tukey_weights(res: torch.Tensor, scale: float) -> torch.Tensor:
    """Tukey's biweight: observations beyond :data:`TUKEY_C` robust deviations weigh nothing."""
    return (1 - (res / (TUKEY_C * scale)) ** 2).clamp_min(0.0) ** 2


def _robust_scale(res: torch.Tensor, w: torch.Tensor) -> float:
    used = res[w > 0]
    return max(float(1.4826 * used.abs().median()), 1e-6) if used.numel() else 1e-6


def fit_channel(pt: torch.Tensor, n: int, r: torch.Tensor, y: torch.Tensor, length: float,
                w: torch.Tensor | None = None, start=(0.1, 0.3, 0.0), warm: bool = False,
                errors: bool = True, lit: torch.Tensor | None = None, tied: Optional[float] = None) -> dict:
    """One channel's water from observations ``pt`` (K,) point ids below ``n``, ranges ``r`` and
    linear colours ``y`` (K,), observation weights ``w``; ``start``: (attenuation, backscatter
    rate, veil at ``length``), ``warm``: the start is a fit's (else the rate starts at each of
    :data:`COLD_RATES` and the veil halfway to its bound). Returns the three, each point's
    colour ``J`` (n,), the robust loss with the water and without it (``J`` alone), the Huber
    scale both are measured in, and with ``errors`` the three's Gauss-Newton variances.
    ``lit`` (K,): a known gain on each observation's seabed part (a lamp on the camera:
    ``y = lit J exp(-attenuation r) + V(r)``, the veil in front of the lit seabed), 1 without."""
    r, y = r.double(), y.double()
    w = torch.ones_like(y) if w is None else w.double()
    lit = torch.ones_like(y) if lit is None else lit.double()
    # without water: each point's robust mean; its residuals set the scale both losses use
    h = torch.ones_like(y)
    for _ in range(IRLS_ROUNDS):
        j0 = _point_colours(pt, n, lit, y, w * h)
        res0 = y - j0[pt] * lit
        scale = _robust_scale(res0, w)
        h = _huber_weights(res0, scale)
    # the veil at the median range lies between 0 and the darker colours seen (no colour is
    # below the veil in front of it): where the range hardly changes, nothing else bounds it
    cap = max(float(torch.quantile(y[w > 0], DARKEST)), 1e-6)
    lo, hi = np.log(RATE_RANGE[0] / length), np.log(RATE_RANGE[1] / length)

    def raw(att, rate, v_len):
        v = min(max(v_len / cap, 1e-3), 1 - 1e-3)
        q = min(max((np.log(rate) - lo) / (hi - lo), 1e-3), 1 - 1e-3)
        return torch.tensor([att, float(np.log(q / (1 - q))), float(np.log(v / (1 - v)))], dtype=torch.float64)

    def rate_of(t):
        if tied is not None:   # the veil builds up at (a multiple of) the rate the water takes the light
            return (tied * t[0]).clamp(RATE_RANGE[0] / length, RATE_RANGE[1] / length)
        return torch.exp(lo + (hi - lo) * torch.sigmoid(t[1]))

    def parts(t):
        att, rate, v_len = t[0], rate_of(t), cap * torch.sigmoid(t[2])
        a = lit * torch.exp(-att * r)
        z = y - v_len * _veil_curve(rate, r, length)
        return a, z

    def residuals(t, wh):
        """Each observation's error with every point's colour projected out, and the colours."""
        a, z = parts(t)
        j = _point_colours(pt, n, a, z, wh)
        return z - j[pt] * a, j

    def loss_of(t, wh):
        return (wh * residuals(t, wh)[0] ** 2).sum() / wh.sum().clamp_min(1e-12) / scale ** 2

    def minimise(theta, wh, iterations):
        theta = theta.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([theta], lr=1, max_iter=iterations, tolerance_grad=1e-10, tolerance_change=1e-12,
                                line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = loss_of(theta, wh)
            loss.backward()
            return loss
        opt.step(closure)
        with torch.no_grad():
            return theta.detach(), float(loss_of(theta, wh))

    # the veil's rate is weakly pinned and its loss has more than one valley: a cold start tries
    # several rates (a warm start, from a fit on the same survey, one)
    starts = [raw(*start)] if warm or tied is not None else [raw(start[0], k / length, 0.5 * cap) for k in COLD_RATES]
    # the no-water fit's weights to start: an observation far from its point's robust colour is
    # an outlier whatever the water (which changes a point's colour smoothly with range)
    h = _huber_weights(res0, scale)
    theta = min((minimise(t, w * h, 100) for t in starts), key=lambda tl: tl[1])[0]
    for k in range(IRLS_ROUNDS):
        with torch.no_grad():
            res = residuals(theta, w * h)[0]
            # Huber's convex loss first, then the biweight from there: far errors (occlusion,
            # a misplaced point) are left out rather than only bounded
            h = _huber_weights(res, scale) if k < IRLS_ROUNDS // 2 else _tukey_weights(res, _robust_scale(res, w))
        theta = minimise(theta, w * h, 40)[0]
    with torch.no_grad():
        res, j = residuals(theta, w * h)
    att, rate, v_len = float(theta[0]), float(rate_of(theta)), cap * float(torch.sigmoid(theta[2]))
    return {"attenuation": att, "backscatter": rate, "veil_at_length": v_len,
            "J": j.float(), "loss_water": _huber_loss(res, scale, w), "loss_plain": _huber_loss(res0, scale, w),
            "scale": scale,
            "variance": _variances(pt, n, r, y, length, w * h, res, (att, rate, v_len), lit, tied) if errors else None}


def _variances(pt, n, r, y, length, wh, res, values, lit, tied: Optional[float] = None) -> np.ndarray:
    """(3,) Gauss-Newton variances of (attenuation, backscatter rate, veil at ``length``) at the
    fit, each point's colour projected out (variable projection's Jacobian): the residual
    variance over the information J^T W J. Where the observations do not pin a number (a point
    seen from one range pins no attenuation), its variance is infinite. ``tied``: the rate is
    this multiple of the attenuation (one number: the rate's variance follows the attenuation's)."""
    def residuals(t):
        a = lit * torch.exp(-t[0] * r)
        z = y - t[2] * _veil_curve(t[1] if tied is None else tied * t[0], r, length)
        j = _point_colours(pt, n, a, z, wh)
        return wh.sqrt() * (z - j[pt] * a)
    jac = torch.func.jacfwd(residuals)(torch.tensor(values, dtype=torch.float64))
    if tied is not None:   # the rate's column is empty; the attenuation's carries both
        jac[:, 1] = 0.0
    info = (jac.T @ jac).numpy()
    if tied is not None:
        info[1, 1] = 1.0
    dof = max(float(wh.sum()) - float((torch.bincount(pt, minlength=n) > 0).sum()) - 3, 1.0)
    var = float((wh * res ** 2).sum()) / dof
    # each number's variance with the other two free (its information's Schur complement, the
    # others' block pseudo-inverted: a rate the survey leaves free does not free the attenuation)
    out = np.empty(3)
    for i in range(3):
        rest = [k for k in range(3) if k != i]
        left = info[i, i] - info[i, rest] @ np.linalg.pinv(info[np.ix_(rest, rest)], rcond=1e-10) @ info[rest, i]
        out[i] = var / left if left > 1e-9 * max(info[i, i], 1e-300) else np.inf
    if tied is not None:
        out[1] = tied * tied * out[0]
    return out


def _huber_loss(res: torch.Tensor, scale: float, w: torch.Tensor) -> float:
    x = (res / scale).abs()
    rho = torch.where(x <= HUBER_K, 0.5 * x * x, HUBER_K * (x - 0.5 * HUBER_K))
    return float((w * rho).sum() / w.sum().clamp_min(1e-12))


def veil_from(backscatter: float, veil_at_length: float, length: float) -> float:
    """The veil at infinite range from its value at ``length`` and its rate."""
    return veil_at_length / max(-np.expm1(-backscatter * length), 1e-12)


def _levenberg_marquardt(residuals, theta: torch.Tensor, iterations: int) -> torch.Tensor:
    """Least squares of ``residuals(theta)`` (a vector) over a few parameters by Levenberg and
    Marquardt's damped Gauss-Newton steps (the Jacobian by forward differentiation): the
    parameters here differ in scale by orders, where a quasi-Newton search crawls."""
    theta = theta.detach().clone()
    res = residuals(theta)
    loss = float(res @ res)
    damping = 1e-3
    for _ in range(iterations):
        jac = torch.func.jacfwd(residuals)(theta)
        jtj, jtr = jac.T @ jac, jac.T @ res
        diag = torch.diag(jtj).clamp_min(1e-12)
        while True:
            step = torch.linalg.solve(jtj + damping * torch.diag(diag), -jtr)
            trial = theta + step
            r_trial = residuals(trial)
            new = float(r_trial @ r_trial)
            if np.isfinite(new) and new <= loss:
                break
            damping *= 4.0
            if damping > 1e8:
                return theta
        improvement = (loss - new) / max(loss, 1e-300)
        theta, res, loss = trial, r_trial, new
        damping = max(damping / 4.0, 1e-9)
        if improvement < 1e-9:
            break
    return theta


def _point_mean(pt, n, x, w):
    """Each point's weighted mean of ``x`` (K,) with weights ``w``."""
    return _point_colours(pt, n, torch.ones_like(x), x, w)


class _LightFit:
    """:func:`fit_under_light`'s parts over one set of observations (float64)."""

    def __init__(self, pt, n, r, y, length, w):
        self.pt, self.n, self.r, self.y, self.length, self.w = pt, n, r, y, length, w
        used = w > 0
        self.eps = LOG_FLOOR * y[used].median(0).values.clamp_min(1e-6)
        self.cap = torch.quantile(y[used], DARKEST, dim=0).clamp_min(1e-6)
        self.lo, self.hi = np.log(RATE_RANGE[0] / length), np.log(RATE_RANGE[1] / length)
        self.others = [c for c in range(3) if c != REFERENCE]

    def seabed(self, v_len, rate):
        """(K, 3) each observation's colour less the veil in front of it."""
        return self.y - v_len * _veil_curve(rate, self.r[:, None], self.length)

    def chroma(self, v_len, diff, rate, h):
        """(K, 2) each observation's log ratio of a channel's seabed part to the reference's, its
        slope with range taken out and each point's mean projected out, in units of the colours'
        noise (the delta method's standard error: a log ratio of dark colours is noisy; it moves
        with the veil searched, which keeps a brighter veil from making every ratio one)."""
        zc = self.seabed(v_len, rate).clamp_min(self.eps)
        lz = torch.log(zc)
        out = []
        for j, c in enumerate(self.others):
            q = lz[:, c] - lz[:, REFERENCE] + diff[j] * self.r
            se = torch.sqrt(zc[:, c] ** -2 + zc[:, REFERENCE] ** -2)
            out.append((q - _point_mean(self.pt, self.n, q, h[:, j])[self.pt]) / se)
        return torch.stack(out, 1)

    def unpack(self, t, rate):
        v_len = self.cap * torch.sigmoid(t[:3])
        if t.numel() > 5:
            rate = torch.exp(self.lo + (self.hi - self.lo) * torch.sigmoid(t[5:8]))
        return v_len, t[3:5], rate

    def pack(self, v_len, diff, rate, free):
        v = (v_len / self.cap).clamp(1e-4, 1 - 1e-4)
        parts = [torch.log(v / (1 - v)), diff]
        if free:
            q = ((torch.log(rate) - self.lo) / (self.hi - self.lo)).clamp(1e-4, 1 - 1e-4)
            parts.append(torch.log(q / (1 - q)))
        return torch.cat(parts).double()

    def fit_chroma(self, v_len, diff, rate, free: bool, rounds: int = 3):
        """The veil (and with ``free`` its rate) and the channels' differences in attenuation
        from the log ratios (Huber's weights, reweighted ``rounds`` times)."""
        theta = self.pack(v_len, diff, rate, free)
        h = self.w[:, None].expand(-1, 2).clone()
        for _ in range(rounds):
            theta = _levenberg_marquardt(lambda t: (h.sqrt() * self.chroma(*self.unpack(t, rate), h)).reshape(-1),
                                         theta, LM_STEPS)
            with torch.no_grad():
                res = self.chroma(*self.unpack(theta, rate), h)
                scale = torch.stack([torch.tensor(_robust_scale(res[:, j], self.w)) for j in range(2)]).double()
                h = self.w[:, None] * _huber_weights(res, scale)
        return self.unpack(theta, rate)

    def log_slope(self, v_len, rate) -> float:
        """The reference channel's attenuation from its seabed part's log slope with range (each
        point's mean projected out; Huber's weights), given the veil."""
        c = REFERENCE
        z = self.seabed(v_len, rate)[:, c]
        ok = self.w * (z > self.eps[c]).double()
        lz = torch.log(z.clamp_min(self.eps[c]))
        h = ok.clone()
        att = 0.0
        for _ in range(IRLS_ROUNDS + 2):
            rd = self.r - _point_mean(self.pt, self.n, self.r, h)[self.pt]
            ld = lz - _point_mean(self.pt, self.n, lz, h)[self.pt]
            att = float(-(h * rd * ld).sum() / (h * rd * rd).sum().clamp_min(1e-12))
            res = ld + att * rd
            h = ok * _huber_weights(res, _robust_scale(res, ok))
        return att

    @torch.no_grad()
    def light_and_noise(self, att, v_len, rate) -> tuple[float, float]:
        """The light's spread from view to view (log units: the robust spread of each point's
        seabed part in the reference channel, its range taken out, less the photos' own noise)
        and that noise (the log ratios' spread, one channel's share)."""
        z = self.seabed(v_len, rate)
        lz = torch.log(z.clamp_min(self.eps)) + att * self.r[:, None]
        keep = self.w * (z > self.eps).all(1).double()
        grey = lz[:, REFERENCE] - _point_mean(self.pt, self.n, lz[:, REFERENCE], keep)[self.pt]
        ratios = [lz[:, c] - lz[:, REFERENCE] for c in self.others]
        chroma = torch.cat([q - _point_mean(self.pt, self.n, q, keep)[self.pt] for q in ratios])
        noise = _robust_scale(chroma, keep.repeat(2)) / np.sqrt(2.0)
        total = _robust_scale(grey, keep)
        return float(np.sqrt(max(total ** 2 - noise ** 2, 0.0))), float(noise)

    def run(self, attenuation, v_len, rate=None, tied: int = TIED_ROUNDS, free: int = FREE_ROUNDS,
            factor: float = 1.0):
        """``tied`` rounds with the veil's rate ``factor`` times the attenuation (fewer where the
        attenuation has settled), then ``free`` with it searched."""
        att = torch.as_tensor(attenuation, dtype=torch.float64)
        v_len = torch.minimum(torch.as_tensor(v_len, dtype=torch.float64).clamp_min(1e-6), 0.99 * self.cap)
        bounds = (RATE_RANGE[0] / self.length, RATE_RANGE[1] / self.length)
        k = 0
        while k < tied + free:
            if k < tied or rate is None:
                rate = (factor * att).clamp(*bounds)
            diff = att[self.others] - att[REFERENCE]
            v_len, diff, rate = self.fit_chroma(v_len, diff, rate, free=k >= tied)
            ref = self.log_slope(v_len, rate)
            last, att = att, torch.empty(3, dtype=torch.float64)
            att[REFERENCE] = ref
            att[self.others] = diff + ref
            k += 1
            if k < tied and float((att - last).abs().max()) <= SETTLED * float(att.abs().max()):
                k = tied
        return att, v_len, rate


def fit_under_light(point, n: int, rng, colour_lin, length: float, start: dict, w=None,
                    tied: int = TIED_ROUNDS, free: int = FREE_ROUNDS, factor: float = 1.0) -> dict:
    """The water under light that moves over the seabed (module docstring), from the fit
    ``start`` (:func:`fit_water`'s: attenuation, backscatter, veil_at_length per channel), with
    ``tied`` rounds of the veil's rate ``factor`` times the attenuation and ``free`` rounds of
    it searched (:meth:`_LightFit.run`). Returns per channel ``attenuation``, ``backscatter``
    (the veil's rate), ``veil_at_length`` and ``veil``, and ``J`` (n, 3) each point's linear
    colour under the light's mean."""
    pt = torch.as_tensor(np.asarray(point, np.int64))
    r = torch.as_tensor(np.asarray(rng, np.float64))
    y = torch.as_tensor(np.asarray(colour_lin, np.float64))
    w = torch.ones(len(r), dtype=torch.float64) if w is None else torch.as_tensor(w, dtype=torch.float64)
    lf = _LightFit(pt, n, r, y, length, w)
    rate0 = None if tied else torch.as_tensor(start["backscatter"], dtype=torch.float64)
    att, v_len, rate = lf.run(start["attenuation"], start["veil_at_length"], rate0, tied, free, factor)
    with torch.no_grad():   # the colours under the light's mean: least squares with the water fixed
        a = torch.exp(-att * r[:, None])
        z = lf.seabed(v_len, rate)
        j = torch.stack([_point_colours(pt, n, a[:, c], z[:, c], w) for c in range(3)], 1)
    light, noise = lf.light_and_noise(att, v_len, rate)
    return {"attenuation": att.tolist(), "backscatter": rate.tolist(), "veil_at_length": v_len.tolist(),
            "veil": [veil_from(b, v, length) for b, v in zip(rate.tolist(), v_len.tolist())], "J": j.numpy(),
            "light_noise": [light, noise], "veil_bound": (v_len / lf.cap).tolist()}


def _light_shows(fit: dict) -> bool:
    """Whether a fit under light is to be used (:func:`fit_water`): the light's spread from view
    to view at least :data:`LIGHT_OVER_NOISE` times the photos' noise and every channel's veil
    below :data:`VEIL_BOUND` of its bound."""
    return fit["light_noise"][0] >= LIGHT_OVER_NOISE * fit["light_noise"][1] and max(fit["veil_bound"]) < VEIL_BOUND


def unnatural(attenuation, spread=None) -> Optional[str]:
    """Why attenuation per channel (red, green, blue) is unlike any natural water, or None. In
    every Jerlov type, from clear ocean to turbid coast, each channel is attenuated (above 0)
    and red more than green (pure water absorbs red strongly; Akkaynak et al. 2017). With
    ``spread`` (each channel's error bar) a value counts only beyond one error bar; without it,
    only red at or below 0 or below green (red is the channel natural water takes most)."""
    att = np.asarray(attenuation, np.float64)
    if spread is None:
        if att[0] <= 0:
            return f"red's attenuation {att[0]:.3f} is not above 0"
        if att[0] < att[1]:
            return f"red's attenuation {att[0]:.3f} is below green's {att[1]:.3f}"
        return None
    sd = np.asarray(spread, np.float64)
    low = [c for c in range(3) if att[c] < -sd[c]]
    if low:
        names = ", ".join(("red", "green", "blue")[c] for c in low)
        return f"the attenuation of {names} is below 0 beyond its error bar"
    if att[0] < att[1] - float(np.hypot(sd[0], sd[1])):
        return f"red's attenuation {att[0]:.3f} is below green's {att[1]:.3f} beyond their error bars"
    return None


def fit_water(point: np.ndarray, n: int, rng: np.ndarray, colour_lin: np.ndarray, length: float,
              rounds: int = 0, seed: int = 0, moving_light: bool = False, natural_only: bool = False,
              lit: Optional[np.ndarray] = None, tie_free_rates: Optional[float] = None) -> dict:
    """The water of every channel from observations (``point`` (K,) ids below ``n``, ``rng``
    (K,), ``colour_lin`` (K, 3) linear colours) and, with ``rounds`` > 0, how well they pin it.

    Returns per channel (lists of three): ``attenuation`` (any sign), ``backscatter``, ``veil``
    and ``veil_at_length``; ``J`` (n, 3) the points' linear colours; ``gain`` the share of the
    points' robust colour change from view to view the water takes away; with ``rounds``:
    ``spread`` (per coefficient and channel, the standard deviation of the refits or the
    Gauss-Newton standard error, whichever is larger; absolute).

    ``moving_light``: the photos hold light that moves over the seabed. The fit above then
    starts :func:`fit_under_light`, which is returned where the light's spread from view to
    view is at least :data:`LIGHT_OVER_NOISE` times the photos' own noise (the light is what
    pins its veil; ``"light_noise"`` both spreads) and no channel's veil ends near its bound
    (:data:`VEIL_BOUND`, ``"veil_bound"``: the fit found no veil there); ``"under_light"``
    says whether. The plain fit and the refits then use :data:`LIGHT_SUBSET` of the
    observations (the fit under light's spread scaled to all of them). ``natural_only``: where the
    fit is unlike any natural water (:func:`unnatural` without error bars) there are no refits
    and no ``spread`` (a run that models only natural water needs none). ``lit`` (K,): a known
    grey gain on each observation's seabed part (a lamp's light; :func:`fit_channel`), not
    with ``moving_light``.

    ``tie_free_rates`` (with ``rounds``): a channel whose backscatter rate the refits leave looser
    than this (their spread over its value) is fitted again with the rate tied to its attenuation
    (:func:`tie_free_rates_of`; under moving light every channel's, :func:`tie_rates_under_light`);
    ``"rate_tied"`` says which."""
    if lit is not None and moving_light:
        raise ValueError("a known gain on the seabed and light that moves over it are not fitted together")
    pt = torch.from_numpy(np.asarray(point, np.int64))
    r = torch.from_numpy(np.asarray(rng, np.float64))
    y = torch.from_numpy(np.asarray(colour_lin, np.float64))
    g = None if lit is None else torch.from_numpy(np.asarray(lit, np.float64))
    sub = torch.arange(len(pt))
    if moving_light and len(pt) > LIGHT_SUBSET:
        sub = torch.sort(torch.randperm(len(pt), generator=torch.Generator().manual_seed(seed + 1))
                         [:LIGHT_SUBSET]).values
    gs = None if g is None else g[sub]
    fits = [fit_channel(pt[sub], n, r[sub], y[sub, c], length, lit=gs) for c in range(3)]
    out = _collect(fits, length)
    out["J"] = torch.stack([f["J"] for f in fits], 1).numpy()
    light = None
    if moving_light:
        light = fit_under_light(pt, n, r, y, length, out)
        shown = _light_shows(light)
        out.update({"under_light": shown, "light_noise": light["light_noise"], "veil_bound": light["veil_bound"],
                    "plain_attenuation": list(out["attenuation"])})
        if shown:
            out.update(light)
        else:
            light = None
    if rounds <= 0 or (natural_only and unnatural(out["attenuation"]) is not None):   # no error bars needed
        return out
    if light is not None:
        # refitted on the subset, the spread scaled to every observation the fit used (a
        # standard error falls as one over the root of the observations): its error bars
        # decide what training keeps
        boot = _bootstrap(lambda w: fit_under_light(pt[sub], n, r[sub], y[sub], length, light, w, tied=0, free=1),
                          pt[sub], n, rounds, seed)
        out["spread"] = {k: (v * np.sqrt(len(sub) / len(pt))).tolist() for k, v in boot.items()}
        if tie_free_rates is not None:
            tie_rates_under_light(out, pt, n, r, y, length, tie_free_rates, sub, rounds, seed)
    else:
        boot = _bootstrap(lambda w: _collect([fit_channel(pt[sub], n, r[sub], y[sub, c], length, w,
                                                          start=(f["attenuation"], f["backscatter"],
                                                                 f["veil_at_length"]),
                                                          warm=True, errors=False, lit=gs)
                                              for c, f in enumerate(fits)], length), pt[sub], n, rounds, seed)
        # refits started from the fit cannot leave a flat valley: the spread is at least the
        # Gauss-Newton standard error (infinite where nothing pins a number)
        gn = _gauss_newton_spread(fits, length)
        out["spread"] = {k: np.maximum(boot[k], gn[k]).tolist() for k in gn}
        if tie_free_rates is not None:
            tie_free_rates_of(out, pt[sub], n, r[sub], y[sub], length, tie_free_rates, gs)
    out["rounds"] = rounds
    return out


def tie_free_rates_of(out: dict, pt, n: int, r, y, length: float, loose: float, lit=None) -> None:
    """Where the refits leave a channel's backscatter rate unpinned (its spread over its value
    above ``loose``), fit that channel again with the rate tied to its attenuation, in place in
    :func:`fit_water`'s ``out`` (its coefficients and ``J``; ``"rate_tied"`` per channel). A
    survey flown at one range pins the veil's value and its growth with range only together
    (each point's colour against its range pins the attenuation and ``attenuation V(r) +
    V'(r)``): the rate picks the veil along that line, and free, it went where the loss's
    shallow valley led (the generator's coastal water, 2.4-3.3 m: rates 1.07-1.18 for
    0.30-0.34, the green and blue veil 40 % high; a green water's bright veil, rate 1.36 +- 0.33
    for 0.18, the veil at the median range 2.4 times the truth: the refits, started from the fit,
    stay in its valley, so a rate they call loose is no surer). Tied, the water is the single-coefficient
    model of the textbook image formation (Jaffe and McGlamery; Schechner and Karpel): the
    light scattered back builds up at the rate the beam is attenuated. Natural waters stray
    from it (Akkaynak and Treibitz measured the two rates apart): the tied channel's error bars
    cover the fits with the rate :data:`RATE_PRIOR_WIDTH` times and a fraction of it, beside the
    tied fit's own Gauss-Newton errors."""
    tied = []
    for c, free in enumerate(_loose_rates(out, loose)):
        if not free:
            tied.append(False)
            continue
        start = (out["attenuation"][c], out["attenuation"][c], out["veil_at_length"][c])
        g = fit_channel(pt, n, r, y[:, c], length, start=start, lit=lit, tied=1.0)
        gn = _gauss_newton_spread([g], length)
        ends = [fit_channel(pt, n, r, y[:, c], length, start=start, lit=lit, tied=k, errors=False)
                for k in (RATE_PRIOR_WIDTH, 1.0 / RATE_PRIOR_WIDTH)]
        for k in ("attenuation", "backscatter", "veil_at_length"):
            out[k][c] = g[k]
        out["veil"][c] = veil_from(g["backscatter"], g["veil_at_length"], length)
        out["J"][:, c] = g["J"].numpy()
        half = {k: 0.5 * abs(ends[0][k] - ends[1][k]) for k in ("attenuation", "backscatter", "veil_at_length")}
        half["veil"] = 0.5 * abs(veil_from(ends[0]["backscatter"], ends[0]["veil_at_length"], length)
                                 - veil_from(ends[1]["backscatter"], ends[1]["veil_at_length"], length))
        sp = out["spread"]
        sp["attenuation"][c] = max(sp["attenuation"][c], float(gn["attenuation"][0]), half["attenuation"])
        for k in ("backscatter", "veil_at_length", "veil"):
            sp[k][c] = float(np.hypot(gn[k][0], half[k]))
        tied.append(True)
    out["rate_tied"] = tied


def _loose_rates(out: dict, loose: float) -> list[bool]:
    """Per channel, whether the refits leave the backscatter rate looser than ``loose`` (their
    spread over its value)."""
    return [sd > loose * max(abs(v), 1e-9) for sd, v in zip(out["spread"]["backscatter"], out["backscatter"])]


def tie_rates_under_light(out: dict, pt, n: int, r, y, length: float, loose: float, sub, rounds: int,
                          seed: int) -> None:
    """:func:`tie_free_rates_of` for the fit under light, in place in :func:`fit_water`'s ``out``
    (the fit under light's, with its ``spread``): where the refits leave any channel's rate
    looser than ``loose``, every channel is fitted again with its rate equal to its attenuation
    until the attenuation settles (the channels are fitted together: their log ratios pin the
    veils). At one altitude the veil's growth with range and the seabed's fall-off trade off
    here as without the light: searched, the rates ran to their bounds (a coastal water's red
    and green at the lowest, the veil growing as a line) or drifted with the veil (a green
    water's green and blue attenuation read 57 and 54 % low, its rates twice the truth); tied
    and settled, those waters read -16 / -14 / -17 % and -2 / +15 / +9 %. The error bars are
    the tied fit's refits (on the same subset and scaled as the fit's) with the fits at the
    rate :data:`RATE_PRIOR_WIDTH` times and a fraction of the attenuation. Where the tied fit
    fails the fit under light's own checks (the light over the noise, the veil below its
    bound) the free fit stays."""
    out["rate_tied"] = [False] * 3
    if not any(_loose_rates(out, loose)):
        return

    def fit(start, w=None, tied=TIED_ONLY_ROUNDS, factor=1.0, on=slice(None)):
        return fit_under_light(pt[on], n, r[on], y[on], length, start, w, tied=tied, free=0, factor=factor)

    tied = fit(out)
    if not _light_shows(tied):
        return
    ends = [fit(tied, factor=k, on=sub) for k in (RATE_PRIOR_WIDTH, 1.0 / RATE_PRIOR_WIDTH)]
    boot = _bootstrap(lambda w: fit(tied, w, tied=1, on=sub), pt[sub], n, rounds, seed)
    scale = np.sqrt(len(sub) / len(pt))
    out.update({k: tied[k] for k in ("attenuation", "backscatter", "veil_at_length", "veil", "J", "light_noise",
                                     "veil_bound")})
    for e in ends:
        e["difference"] = differences(e["attenuation"])
    out["spread"] = {k: np.hypot(boot[k] * scale,
                                 0.5 * np.abs(np.asarray(ends[0][k]) - np.asarray(ends[1][k]))).tolist()
                     for k in boot}
    out["rate_tied"] = [True] * 3


#: The pairs of channels whose difference in attenuation the refits' ``"difference"`` gives.
PAIRS = ((0, 1), (0, 2), (1, 2))


def differences(attenuation) -> list[float]:
    """The channels' differences in attenuation, red - green, red - blue, green - blue."""
    return [float(attenuation[a]) - float(attenuation[b]) for a, b in PAIRS]


def _bootstrap(refit, pt: torch.Tensor, n: int, rounds: int, seed: int) -> dict:
    """The standard deviation of ``refit(w)``'s coefficients over ``rounds`` draws of the points
    with replacement (``w``: each observation's weight, its point's count in the draw; the
    points, not the observations, are the independent draws), and of the channels'
    differences in attenuation (``"difference"``, :data:`PAIRS`: under moving light the channels
    share the light's noise, and their differences are surer than each)."""
    gen = torch.Generator().manual_seed(seed)
    used = torch.unique(pt)
    draws = {k: [] for k in ("attenuation", "backscatter", "veil", "veil_at_length", "difference")}
    for _ in range(rounds):
        pick = used[torch.randint(len(used), (len(used),), generator=gen)]
        count = torch.zeros(n, dtype=torch.float64).index_add_(0, pick, torch.ones(len(pick), dtype=torch.float64))
        refitted = refit(count[pt])
        refitted["difference"] = differences(refitted["attenuation"])
        for k in draws:
            draws[k].append(refitted[k])
    return {k: np.std(np.asarray(v, np.float64), axis=0, ddof=1) for k, v in draws.items()}


def _gauss_newton_spread(fits: list[dict], length: float) -> dict:
    """Each coefficient's Gauss-Newton standard error from :func:`fit_channel`'s variances."""
    sd = np.sqrt(np.array([f["variance"] for f in fits]))          # (channel, [att, rate, veil at length])
    e = np.array([-np.expm1(-f["backscatter"] * length) for f in fits])
    veil_sd = np.hypot(sd[:, 2] / e, np.array([f["veil_at_length"] * length * (1 - ei) / ei ** 2
                                               for f, ei in zip(fits, e)]) * sd[:, 1])
    return {"attenuation": sd[:, 0], "backscatter": sd[:, 1], "veil_at_length": sd[:, 2], "veil": veil_sd}


def _collect(fits: list[dict], length: float) -> dict:
    plain = sum(f["loss_plain"] for f in fits)
    return {"attenuation": [f["attenuation"] for f in fits], "backscatter": [f["backscatter"] for f in fits],
            "veil_at_length": [f["veil_at_length"] for f in fits],
            "veil": [veil_from(f["backscatter"], f["veil_at_length"], length) for f in fits],
            "gain": 1.0 - sum(f["loss_water"] for f in fits) / max(plain, 1e-12)}
