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

The attenuation is searched over all real numbers: a survey without water gets a value near 0,
either sign, and its spread says whether the photos show any (``z``, the attenuation over its
spread). The spreads come from refitting on the points drawn again with replacement (the
bootstrap, Efron 1979): the points, not the observations, are the independent draws.
"""
from __future__ import annotations

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
#: Backscatter rates (times the median range) a cold fit starts from.
COLD_RATES = (0.1, 0.5, 2.0)
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


def _huber_weights(res: torch.Tensor, scale: float) -> torch.Tensor:
    return (HUBER_K * scale / res.abs().clamp_min(1e-12)).clamp(max=1.0)


def _tukey_weights(res: torch.Tensor, scale: float) -> torch.Tensor:
    """Tukey's biweight: observations beyond :data:`TUKEY_C` robust deviations weigh nothing."""
    return (1 - (res / (TUKEY_C * scale)) ** 2).clamp_min(0.0) ** 2


def _robust_scale(res: torch.Tensor, w: torch.Tensor) -> float:
    used = res[w > 0]
    return max(float(1.4826 * used.abs().median()), 1e-6) if used.numel() else 1e-6


def fit_channel(pt: torch.Tensor, n: int, r: torch.Tensor, y: torch.Tensor, length: float,
                w: torch.Tensor | None = None, start=(0.1, 0.3, 0.0), warm: bool = False,
                errors: bool = True) -> dict:
    """One channel's water from observations ``pt`` (K,) point ids below ``n``, ranges ``r`` and
    linear colours ``y`` (K,), observation weights ``w``; ``start``: (attenuation, backscatter
    rate, veil at ``length``), ``warm``: the start is a fit's (else the rate starts at each of
    :data:`COLD_RATES` and the veil halfway to its bound). Returns the three, each point's
    colour ``J`` (n,), the robust loss with the water and without it (``J`` alone), the Huber
    scale both are measured in, and with ``errors`` the three's Gauss-Newton variances."""
    r, y = r.double(), y.double()
    w = torch.ones_like(y) if w is None else w.double()
    # without water: each point's robust mean; its residuals set the scale both losses use
    h = torch.ones_like(y)
    for _ in range(IRLS_ROUNDS):
        j0 = _point_colours(pt, n, torch.ones_like(y), y, w * h)
        res0 = y - j0[pt]
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

    def parts(t):
        att, rate, v_len = t[0], torch.exp(lo + (hi - lo) * torch.sigmoid(t[1])), cap * torch.sigmoid(t[2])
        a = torch.exp(-att * r)
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
    starts = [raw(*start)] if warm else [raw(start[0], k / length, 0.5 * cap) for k in COLD_RATES]
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
    att, rate, v_len = float(theta[0]), float(np.exp(lo + (hi - lo) * torch.sigmoid(theta[1]))), \
        cap * float(torch.sigmoid(theta[2]))
    return {"attenuation": att, "backscatter": rate, "veil_at_length": v_len,
            "J": j.float(), "loss_water": _huber_loss(res, scale, w), "loss_plain": _huber_loss(res0, scale, w),
            "scale": scale,
            "variance": _variances(pt, n, r, y, length, w * h, res, (att, rate, v_len)) if errors else None}


def _variances(pt, n, r, y, length, wh, res, values) -> np.ndarray:
    """(3,) Gauss-Newton variances of (attenuation, backscatter rate, veil at ``length``) at the
    fit, each point's colour projected out (variable projection's Jacobian): the residual
    variance over the information J^T W J. Where the observations do not pin a number (a point
    seen from one range pins no attenuation), its variance is infinite."""
    def residuals(t):
        a = torch.exp(-t[0] * r)
        z = y - t[2] * _veil_curve(t[1], r, length)
        j = _point_colours(pt, n, a, z, wh)
        return wh.sqrt() * (z - j[pt] * a)
    jac = torch.func.jacfwd(residuals)(torch.tensor(values, dtype=torch.float64))
    info = (jac.T @ jac).numpy()
    dof = max(float(wh.sum()) - float((torch.bincount(pt, minlength=n) > 0).sum()) - 3, 1.0)
    var = float((wh * res ** 2).sum()) / dof
    # each number's variance with the other two free (its information's Schur complement, the
    # others' block pseudo-inverted: a rate the survey leaves free does not free the attenuation)
    out = np.empty(3)
    for i in range(3):
        rest = [k for k in range(3) if k != i]
        left = info[i, i] - info[i, rest] @ np.linalg.pinv(info[np.ix_(rest, rest)], rcond=1e-10) @ info[rest, i]
        out[i] = var / left if left > 1e-9 * max(info[i, i], 1e-300) else np.inf
    return out


def _huber_loss(res: torch.Tensor, scale: float, w: torch.Tensor) -> float:
    x = (res / scale).abs()
    rho = torch.where(x <= HUBER_K, 0.5 * x * x, HUBER_K * (x - 0.5 * HUBER_K))
    return float((w * rho).sum() / w.sum().clamp_min(1e-12))


def veil_from(backscatter: float, veil_at_length: float, length: float) -> float:
    """The veil at infinite range from its value at ``length`` and its rate."""
    return veil_at_length / max(-np.expm1(-backscatter * length), 1e-12)


def fit_water(point: np.ndarray, n: int, rng: np.ndarray, colour_lin: np.ndarray, length: float,
              rounds: int = 0, seed: int = 0) -> dict:
    """The water of every channel from observations (``point`` (K,) ids below ``n``, ``rng``
    (K,), ``colour_lin`` (K, 3) linear colours) and, with ``rounds`` > 0, how well they pin it.

    Returns per channel (lists of three): ``attenuation`` (any sign), ``backscatter``, ``veil``
    and ``veil_at_length``; ``J`` (n, 3) the points' linear colours; ``gain`` the share of the
    points' robust colour change from view to view the water takes away; with ``rounds``:
    ``spread`` (per coefficient and channel, the standard deviation of the refits or the
    Gauss-Newton standard error, whichever is larger; absolute)."""
    pt = torch.from_numpy(np.asarray(point, np.int64))
    r = torch.from_numpy(np.asarray(rng, np.float64))
    y = torch.from_numpy(np.asarray(colour_lin, np.float64))
    fits = [fit_channel(pt, n, r, y[:, c], length) for c in range(3)]
    out = _collect(fits, length)
    out["J"] = torch.stack([f["J"] for f in fits], 1).numpy()
    if rounds > 0:
        gen = torch.Generator().manual_seed(seed)
        used = torch.unique(pt)
        draws = {k: [] for k in ("attenuation", "backscatter", "veil", "veil_at_length")}
        for _ in range(rounds):
            pick = used[torch.randint(len(used), (len(used),), generator=gen)]
            count = torch.zeros(n, dtype=torch.float64).index_add_(0, pick, torch.ones(len(pick), dtype=torch.float64))
            w = count[pt]
            refit = _collect([fit_channel(pt, n, r, y[:, c], length, w,
                                          start=(f["attenuation"], f["backscatter"], f["veil_at_length"]), warm=True,
                                          errors=False)
                              for c, f in enumerate(fits)], length)
            for k in draws:
                draws[k].append(refit[k])
        boot = {k: np.std(np.asarray(v, np.float64), axis=0, ddof=1) for k, v in draws.items()}
        # refits started from the fit cannot leave a flat valley: the spread is at least the
        # Gauss-Newton standard error (infinite where nothing pins a number)
        sd = np.sqrt(np.array([f["variance"] for f in fits]))          # (channel, [att, rate, veil at length])
        e = np.array([-np.expm1(-f["backscatter"] * length) for f in fits])
        veil_sd = np.hypot(sd[:, 2] / e, np.array([f["veil_at_length"] * length * (1 - ei) / ei ** 2
                                                   for f, ei in zip(fits, e)]) * sd[:, 1])
        gn = {"attenuation": sd[:, 0], "backscatter": sd[:, 1], "veil_at_length": sd[:, 2], "veil": veil_sd}
        out["spread"] = {k: np.maximum(boot[k], gn[k]).tolist() for k in boot}
        out["rounds"] = rounds
    return out


def _collect(fits: list[dict], length: float) -> dict:
    plain = sum(f["loss_plain"] for f in fits)
    return {"attenuation": [f["attenuation"] for f in fits], "backscatter": [f["backscatter"] for f in fits],
            "veil_at_length": [f["veil_at_length"] for f in fits],
            "veil": [veil_from(f["backscatter"], f["veil_at_length"], length) for f in fits],
            "gain": 1.0 - sum(f["loss_water"] for f in fits) / max(plain, 1e-12)}
