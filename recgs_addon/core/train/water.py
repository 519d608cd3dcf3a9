"""The water in training: the trainer fits the medium (core/model/medium.py) with the Gaussians,
so that the Gaussians hold the seabed's true colour and the water is a few numbers beside them.

With ``medium = "auto"`` (the default) a run models the water only where the survey can tell it
from the seabed's colour:

1. **Before training**, from the sparse points seen in the training views: if a point's range
   hardly changes from view to view (the median over points of its farthest over its nearest
   view, below :data:`MIN_RANGE_SPREAD`), water and colour are one per-channel scale and offset
   the photos cannot separate, and the run is plain. Otherwise the water and each point's true
   colour are fitted to the points' colours in the photos (:func:`fit_from_points`,
   core/model/medium_fit.py), and refitted on the points drawn again to measure how well the
   survey pins each coefficient. The water is modelled where the photos show it: the
   attenuation of some channel at least :data:`MIN_Z` of its error bars above 0, the channels'
   attenuations as far apart (water takes red first; a fall-off alike in every channel is the
   light's: a lamp, the exposure), and the fitted water changing the points' colours by
   :data:`MIN_EFFECT` 8-bit levels. A share of the points' colour change would not do: on a
   textured seabed seen from one height the texture's noise is most of it however strong the
   water. The fit starts the water and the Gaussians'
   colours; a channel's attenuation pinned within :data:`PINNED` of its value is kept through
   training (the render's depth runs slightly short of the surface, which training would take
   for stronger water), and its veil where the survey pins that too (:data:`KEEP_VEIL`); the
   rest trains with the Gaussians, from every pixel.
2. **At the end**, if the trained water changes the training views by less than
   :data:`MIN_EFFECT` (mean absolute difference, 8-bit levels) between the seabed seen through
   it and the seabed alone, it is left out of the outputs. The water never costs more than it
   gives: where the true colour it leaves would lie above white over more than
   :data:`MAX_OVER_WHITE` of the seabed seen (clipped in every output), or carry a colour cast
   stronger than :data:`GREY_WORLD` and than the photos' own (the water tints; taking it out
   does not tint more), the water is left out and the Gaussians keep the colour the photos
   show: the water is put into each one's colour at the range the training views see it from
   (:meth:`MediumMixin.keep_as_seen`), and the report says why.

:class:`MediumMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``data``, ``params``
and ``step``); the report reads :meth:`MediumMixin.medium_summary`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from . import numba_water
from ..model.colour import linear_to_srgb, lit_by, srgb_to_linear
from ..model import jerlov, medium_fit
from ..model.gaussians import SH_C0
from ..model.medium import Medium, out_of_water, ray_lengths

#: Median over sparse points of (farthest / nearest training view's range) below which the
#: survey cannot tell water from colour (a survey flown at one height, looking straight down).
MIN_RANGE_SPREAD = 1.05
#: Mean change (8-bit levels) the fitted water must make to the training views to be kept.
MIN_EFFECT = 2.0
#: Training views the end-of-run decision renders, at most.
DECIDE_VIEWS = 8
#: Adam's learning rate for the medium's raw parameters (softplus / logit space) in training.
LR_MEDIUM = 0.01
#: Attenuation over its error bar above which a channel shows water (auto).
MIN_Z = 4.0
#: A coefficient whose error bar is at most this share of its value is pinned by the survey;
#: a pinned attenuation is kept through training.
PINNED = 0.1
#: ... by at most this share, loosely pinned (the report says so).
LOOSE = 0.3
#: Keep the veil (its rate and colour) from the points too, per channel, where the attenuation is
#: pinned and the veil at the median range at least loosely (on a clear-water survey flown at one
#: altitude training moved the green and blue veil at the median range 45-160 % off, where the
#: points had them within 4 %).
KEEP_VEIL = True
#: The seabed's average true colour, brightest over weakest channel (linear), beyond which the
#: report says the colour is strongly tinted (a grey-world cue, not a rule).
GREY_WORLD = 3.0
#: The most of the sparse points the fitted water may leave brighter than white once they are
#: taken out of it (true colour above 1 in a channel, linear): no seabed reflects more light than
#: it is given. Natural fits leave none (a reef in coastal water: 0.74 at the 99th percentile);
#: a lamp's fall-off with range taken for water left 81 % above it, the median at 31.
MAX_OVER_WHITE = 0.1
#: Observations the fit under moving light uses at most (the light's gain is noise a few
#: thousand points' views average out; measured on a level survey under light networks: red
#: attenuation 6 % off from 60,000, 9 % from 12,000).
LIGHT_OBSERVATIONS = 60_000
#: The pinned channels' misfit to the natural waters' locus (root mean square, in standard
#: deviations: the locus's width with the fit's error bars) beyond which the report says the
#: water is unlike the Jerlov types.
LOCUS_MISFIT = 2.0
#: Refits of the points' water on points drawn again (core/model/medium_fit.py).
BOOT_ROUNDS = 8
#: The colour channels, as the reasons and cues name them.
CHANNELS = ("red", "green", "blue")


def _observations(data, max_points: int = 6000) -> dict:
    """Where the sparse points are in the training views: for each (point, view) where the point
    projects inside the view, the range (scene units) and the pixel position. No occlusion
    test (a seabed seen from above); the fit is robust."""
    pts = np.asarray(data.scene.points, np.float64)
    pick = np.arange(len(pts))
    if len(pts) > max_points:
        pick = np.sort(np.random.default_rng(0).choice(len(pts), max_points, replace=False))
    pts = pts[pick]
    views = []
    for i in data.train_ids:
        cam = data.camera(i, 1)
        seen, u, v, rng = cam.in_view(pts)
        if seen.size:
            views.append((i, cam, seen, u, v, rng))
    cat = (lambda k, empty: np.concatenate([w[k] for w in views]) if views else empty)  # noqa: E731
    return {"points": pick, "views": views, "point": cat(2, np.zeros(0, np.int64)), "range": cat(5, np.zeros(0))}


def image_positions_of(obs: dict) -> tuple[np.ndarray, np.ndarray]:
    """(K,) each observation's position in its image, centred on the principal point, in
    half-widths (as core/model/lamp.py takes it)."""
    if not obs["views"]:
        return np.zeros(0), np.zeros(0)
    return (np.concatenate([(u - cam.cx) / (0.5 * cam.width) for _, cam, _, u, _, _ in obs["views"]]),
            np.concatenate([(v - cam.cy) / (0.5 * cam.width) for _, cam, _, _, v, _ in obs["views"]]))


def _sample_colours(data, obs: dict) -> None:
    """Add ``obs["colour"]``: each observation's colour in its photo (sRGB), the mean over the
    same patch of seabed in every view, a box whose side in pixels shrinks with the range
    (about 3 pixels at the far views). A fixed box would average more seabed the farther the
    view, so contrast would fall with range as if the water took it (measured: attenuation
    fitted 10-25 % high with a 3x3 box, within 1 % with the patch). The mean is taken in linear
    light, where the water and the light add and multiply: a mean of sRGB values is darker than
    the patch's light by more where the patch holds more contrast (texture resolved by a near
    view, a caustic network), which biases the fall-off with range."""
    views = obs["views"]
    if not views:
        obs["colour"] = np.zeros((0, 3), np.float32)
        return
    patch = 1.5 * float(np.median([np.percentile(r / cam.fx, 95) for _, cam, _, _, _, r in views]))
    colour = []
    for i, cam, _, u, v, r in views:
        img = srgb_to_linear(data.view(i, 1)[1].cpu().double()).numpy()
        sat = np.zeros((cam.height + 1, cam.width + 1, 3))
        sat[1:, 1:] = img.cumsum(0).cumsum(1)          # summed-area table: any box's mean in O(1)
        half = np.maximum(1.0, patch * cam.fx / r)
        x0 = np.clip(np.floor(u - half + 0.5), 0, cam.width - 1).astype(np.int64)
        x1 = np.clip(np.floor(u + half + 0.5), x0 + 1, cam.width).astype(np.int64)
        y0 = np.clip(np.floor(v - half + 0.5), 0, cam.height - 1).astype(np.int64)
        y1 = np.clip(np.floor(v + half + 0.5), y0 + 1, cam.height).astype(np.int64)
        box = sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]
        colour.append(box / ((x1 - x0) * (y1 - y0))[:, None])
    lin = torch.from_numpy(np.concatenate(colour)).clamp(0.0, 1.0)
    obs["colour"] = linear_to_srgb(lin).numpy().astype(np.float32)


def range_profile(obs: dict) -> dict:
    """The median range (scene units) of the observations and the median over points seen twice
    or more of their farthest over their nearest view's range."""
    r, pt = obs["range"], obs["point"]
    if not r.size:
        return {"median_range": 0.0, "range_spread": 1.0, "range_p5_p95": None}
    n = len(obs["points"])
    near = np.full(n, np.inf)
    far = np.zeros(n)
    np.minimum.at(near, pt, r)
    np.maximum.at(far, pt, r)
    twice = np.isfinite(near) & (far > near)
    return {"median_range": float(np.median(r)),
            "range_spread": float(np.median(far[twice] / near[twice])) if twice.any() else 1.0,
            "range_p5_p95": [float(np.percentile(r, 5)), float(np.percentile(r, 95))]}


def fit_from_points(obs: dict, length: float, max_observations: int = 12_000, rounds: int = BOOT_ROUNDS,
                    device="cpu", moving_light: bool = False, natural_only: bool = False) -> dict:
    """Fit the water and each sparse point's true colour to the points' colours in the photos
    at their ranges (core/model/medium_fit.py: robust, each point's colour eliminated, in linear
    light), and the same points without water (one colour each, their median). Returns the
    fitted :class:`Medium` (its attenuation at least 1e-4 a unit of range), the points' true
    colours (sRGB), both fits' mean error and the water's mean effect in 8-bit sRGB
    levels, the coefficients as fitted (``"fit"``: the attenuation of any sign) and with
    ``rounds`` their spread over refits (``"spread"``). ``moving_light``: the photos hold light
    that moves over the seabed (caustics; core/model/medium_fit.py: the fit under it).
    ``natural_only``: no refits where the fit is unlike any natural water (no ``"spread"``).
    ``obs["lit"]`` (K,), where there: a lamp's known gain on each observation's seabed, the
    veil in front of it (the true colours are the seabed's evenly lit)."""
    point, rng, colour = obs["point"], obs["range"], obs["colour"]
    lit = obs.get("lit")
    if moving_light:   # the light's noise needs more of them; its fit is the faster
        max_observations = max(max_observations, LIGHT_OBSERVATIONS)
    if len(point) > max_observations:
        keep = np.sort(np.random.default_rng(1).choice(len(point), max_observations, replace=False))
        point, rng, colour = point[keep], rng[keep], colour[keep]
        lit = None if lit is None else lit[keep]
    n = len(obs["points"])
    seen = torch.from_numpy(colour).float()
    fit = medium_fit.fit_water(point, n, rng, srgb_to_linear(seen).double().numpy(), length, rounds=rounds,
                               moving_light=moving_light, natural_only=natural_only, lit=lit,
                               tie_free_rates=PINNED)
    # no water: each point's median colour
    order = np.argsort(point, kind="stable")
    bounds = np.flatnonzero(np.diff(point[order])) + 1
    ids = point[order][np.concatenate([[0], bounds])] if len(order) else np.zeros(0, np.int64)
    plain = torch.full((n, 3), 0.5)
    if len(ids):
        groups = np.split(colour[order], bounds)
        plain[torch.from_numpy(ids)] = torch.from_numpy(np.stack([np.median(g, 0) for g in groups])).float()
    medium = Medium.from_values({"attenuation": np.clip(fit["attenuation"], 1e-4, None), "length": length,
                                 "backscatter": fit["backscatter"], "veil": np.clip(fit["veil"], 1e-4, 1 - 1e-4)})
    pt = torch.from_numpy(point)
    r = torch.from_numpy(rng).float()
    with torch.no_grad():
        true_srgb = linear_to_srgb(torch.from_numpy(fit["J"]).float().clamp(0.0, 1.0))
        ones = torch.ones(len(pt))
        shown = true_srgb[pt]
        if lit is not None:   # the seabed as the lamp lit it, in front of the water
            shown = lit_by(shown, torch.from_numpy(lit).float().unsqueeze(-1))
        fitted = medium.see(shown, ones, r, ones)
        err_plain = float((seen - plain[pt]).abs().mean()) * 255
        err_water = float((fitted - seen).abs().mean()) * 255
        effect = float((fitted - shown).abs().mean()) * 255
    medium.raw = torch.nn.Parameter(medium.raw.detach().to(device))
    j_seen = np.asarray(fit["J"])[np.unique(point)]   # the fitted true colours of the points seen
    return {"medium": medium, "true": true_srgb.numpy(), "error_plain": err_plain, "error_water": err_water,
            "effect_levels": effect, "observations": int(len(pt)), "gain": fit["gain"],
            "fit": {k: fit[k] for k in ("attenuation", "backscatter", "veil", "veil_at_length")},
            "J_mean": np.clip(j_seen, 0.0, 1.0).mean(0).tolist() if len(point) else [],
            "over_white": float((j_seen.max(1) > 1.0).mean()) if len(point) else 0.0,
            "spread": fit.get("spread"), "rate_tied": fit.get("rate_tied"),
            "under_light": {k: fit[k] for k in ("under_light", "light_noise", "plain_attenuation") if k in fit} or None}


def cues(fit: dict) -> list[str]:
    """Where the fitted water disagrees with what natural waters and seabeds look like, a
    sentence each (the report shows them; nothing is overruled). In every natural water, from
    clear ocean (Jerlov's type I) to turbid coast (9C), red is taken fastest, and the veil is
    blue-green, brightest in the colour the water takes least; a seabed's average true colour is
    not strongly tinted (the grey-world cue that colour constancy and Sea-thru's illuminant
    estimate rest on)."""
    att, veil = fit["fit"]["attenuation"], fit["fit"]["veil"]
    out = []
    if att[0] < max(att[1], att[2]):
        out.append("the fitted attenuation takes red less than " + ("green" if att[1] > att[2] else "blue")
                   + ", unlike any natural water: the survey's colours may change with range for another reason "
                     "(a lamp, vignetting towards the far edge)")
    names = CHANNELS
    if veil[0] > max(veil[1], veil[2]):
        out.append("the fitted veil is reddest, unlike the blue-green of natural waters")
    elif int(np.argmax(veil)) != int(np.argmin(att)):
        out.append(f"the fitted veil is brightest in {names[int(np.argmax(veil))]} but the water takes "
                   f"{names[int(np.argmin(att))]} least: in natural waters the light scattered back is the colour "
                   "that travels furthest")
    j = np.asarray(fit.get("J_mean") or [], np.float64)
    if j.size == 3 and j.min() > 0:
        ratio = float(j.max() / j.min())
        if ratio > GREY_WORLD:
            name = names[int(j.argmax())]
            out.append(f"the seabed's average true colour comes out {ratio:.1f} times as bright in {name} as in "
                       f"its weakest channel: either the seabed is that colour or the water is not what was fitted")
    return out


def _rgb(v, f="{:.3f}") -> str:
    return " / ".join(f.format(x) for x in v)


def decide(fit: dict, pins: dict) -> tuple[bool, str]:
    """Whether the photos show water (:func:`fit_from_points` with its error bars, their
    :func:`pinning`), and why: some channel's attenuation :data:`MIN_Z` error bars above 0,
    attenuation like a natural water's (none below 0, red above green:
    ``medium_fit.unnatural``), the points' true colours no brighter than white (at most
    :data:`MAX_OVER_WHITE` of them), the channels' as far apart (water takes red first; a fall-off
    alike in every channel is the light's; the difference's error bar the refits' own where they
    give it: under moving light the channels share the light's noise), and a change to the
    points' colours of :data:`MIN_EFFECT` levels."""
    att = np.asarray(fit["fit"]["attenuation"])
    if not fit.get("spread"):   # the fit ended before its refits: no natural water
        return False, (f"the water fitted to the sparse points (attenuation {_rgb(att)} per unit of range) is unlike "
                       f"any natural water ({medium_fit.unnatural(att)}): no measurable water, no water model")
    sd = np.asarray(fit["spread"]["attenuation"])
    z = pins["z"]
    if max(z) < MIN_Z:
        return False, ("the sparse points show no attenuation beyond their noise (per unit of range, red / green / "
                       "blue " + " / ".join(f"{a:.3f} +- {e:.3f}" for a, e in zip(att, sd))
                       + f"; needs {MIN_Z:g} error bars above 0): no measurable water")
    odd = medium_fit.unnatural(att, sd)
    if odd is not None:
        return False, (f"the water fitted to the sparse points (attenuation {_rgb(att)} per unit of range) is unlike "
                       f"any natural water ({odd}): no water model")
    over = float(fit.get("over_white", 0.0))
    if over > MAX_OVER_WHITE:
        return False, (f"the water fitted to the sparse points (attenuation {_rgb(att)} per unit of range) would leave "
                       f"{100 * over:.0f} % of them brighter than white once taken out of it, and no seabed is: their "
                       "colours fall off with range for another reason (a lamp's light, the exposure): no water model")
    hi, lo = int(att.argmax()), int(att.argmin())
    pair = fit["spread"].get("difference")   # the refits' own spread of the difference, where they give it
    sd_pair = (pair[medium_fit.PAIRS.index((min(hi, lo), max(hi, lo)))] if pair is not None and hi != lo
               else float(np.hypot(sd[hi], sd[lo])))
    z_colour = abs(att[hi] - att[lo]) / max(sd_pair, 1e-12)
    if z_colour < MIN_Z:
        return False, (f"the sparse points' colours fall off with range alike in every channel (attenuation "
                       f"{_rgb(att)} per unit of range, the channels {z_colour:.1f} error bars apart, needs "
                       f"{MIN_Z:g}): the light's fall-off (a lamp, the exposure), not the water, which takes red "
                       "first: no measurable water")
    if fit["effect_levels"] < MIN_EFFECT:
        return False, (f"the water fitted to the sparse points (attenuation {_rgb(att)}) changes their colours by "
                       f"{fit['effect_levels']:.1f} levels of 255, below {MIN_EFFECT:g}: too weak to matter, no "
                       "measurable water")
    return True, (f"the sparse points show water: attenuation {_rgb(att)} per unit of range ({_rgb(z, '{:.0f}')} "
                  f"times its error bar), changing their colours by {fit['effect_levels']:.1f} levels of 255")


def pinning(fit: dict) -> dict:
    """How well the survey pins each coefficient (:func:`fit_from_points` with ``rounds``): per
    coefficient and channel ``"pinned"``, ``"loose"`` or ``"free"`` (the refits' spread over the
    value at most :data:`PINNED`, :data:`LOOSE`, or more), and each channel's attenuation over
    its spread (``"z"``)."""
    spread = fit.get("spread")
    if not spread:
        return {}
    out = {}
    for k in ("attenuation", "backscatter", "veil", "veil_at_length"):
        rel = [sd / max(abs(v), 1e-9) for sd, v in zip(spread[k], fit["fit"][k])]
        out[k] = ["pinned" if x <= PINNED else "loose" if x <= LOOSE else "free" for x in rel]
    out["z"] = [v / max(sd, 1e-12) for v, sd in zip(fit["fit"]["attenuation"], spread["attenuation"])]
    return out


class MediumMixin:
    """The trainer's water: set up, applied to renders, fitted, decided on (see the module)."""

    def _init_medium(self) -> None:
        """Decide on the water and fit it to the sparse points (before the Gaussians are made:
        they start from the points' true colours, :meth:`true_point_colours`)."""
        c = self.cfg
        self.medium: Optional[Medium] = None
        self.medium_optimizer: Optional[torch.optim.Adam] = None
        self.medium_info: dict = {"mode": c.medium, "fitted": False, "kept": False, "reason": "medium off"}
        self._ray_len: dict = {}
        self._prefit: Optional[dict] = None
        self._held: Optional[torch.Tensor] = None   # the water's numbers kept from the points
        if c.medium == "off":
            return
        prof = range_profile(self.point_observations(colours=False))
        self.medium_info.update(prof)
        if not prof["median_range"] > 0:
            self.medium_info["reason"] = "no sparse point in view: no range to fit water on"
            return
        if c.medium == "auto" and prof["range_spread"] < MIN_RANGE_SPREAD:
            self.medium_info["reason"] = (f"each seabed point is seen from nearly one range (farthest / nearest "
                                          f"view x{prof['range_spread']:.2f}, below x{MIN_RANGE_SPREAD}): water "
                                          "cannot be told from the seabed's colour")
            return
        obs = self.point_observations()
        # under caustics the fit measures the light's grey gain instead of taking it for noise
        moving = bool((getattr(self, "light", None) or {}).get("caustics"))
        self._unlit(obs, divide=moving)
        fit = fit_from_points(obs, prof["median_range"], device=self.device, moving_light=moving,
                              natural_only=c.medium == "auto")
        pins = pinning(fit)
        if fit.get("rate_tied"):
            self.medium_info["rate_tied"] = fit["rate_tied"]
        self.medium_info.update(prefit={k: round(fit[k], 3) if isinstance(fit[k], float) else fit[k]
                                        for k in ("error_plain", "error_water", "effect_levels", "observations",
                                                  "gain")},
                                prefit_coefficients=fit["medium"].values(), prefit_fit=fit["fit"],
                                prefit_spread=fit["spread"], pinning=pins, cues=cues(fit),
                                prefit_under_light=fit["under_light"])
        shown, why = decide(fit, pins)
        if c.medium == "auto" and not shown:
            self.medium_info["reason"] = why
            return
        self._natural_prior(fit, pins)
        self.medium = fit["medium"]
        self.medium_optimizer = torch.optim.Adam([self.medium.raw], lr=LR_MEDIUM, eps=1e-15)
        self._prefit = {"points": obs["points"], "true": fit["true"]}
        # where caustics were found the points' fit measured the light (6-11 % off where the plain
        # fit read 26-48 %); trained from every pixel instead, the true colour came out 1.3-1.4 dB
        # lower (benchmarks/RESULTS.md#water-one-altitude, #water-under-light)
        # under moving light the loose channels too: training's frames carry the light's own
        # brightness over each frame, which takes the water's fall-off with range where the
        # points' fit measures the light apart (tied rates, green water: 0.49 / 0.14 / 0.20
        # from the points for 0.50 / 0.12 / 0.18, trained from pixels 0.49 / 0.05 / 0.09)
        under = bool((fit.get("under_light") or {}).get("under_light"))
        kept = [p == "pinned" or (under and p == "loose") for p in pins["attenuation"]]
        self.medium_info["attenuation_kept"] = kept
        self.medium_info["attenuation_from_points"] = all(kept)
        # the veil too where the survey pins its value over the ranges seen (its rate may be free:
        # then the ranges seen do not depend on it)
        self.medium_info["veil_kept"] = [KEEP_VEIL and k and p != "free"
                                         for k, p in zip(kept, pins["veil_at_length"])]
        names = [n for n, p in zip(CHANNELS, pins["attenuation"]) if p == "pinned"]
        loose = [n for n, p, k in zip(CHANNELS, pins["attenuation"], kept) if k and p != "pinned"]
        self.medium_info.update(fitted=True, kept=True, reason=(
            f"{why}; the survey pins the attenuation of {', '.join(names) if names else 'no channel'} within "
            f"{100 * PINNED:.0f} %" + (f", and within {100 * LOOSE:.0f} % that of {', '.join(loose)}, kept as "
                                       "the points give it: under moving light training cannot tell the water's "
                                       "fall-off from the light" if loose else "")))
        self._hold_points_water()

    def _natural_prior(self, fit: dict, pins: dict) -> None:
        """Where the survey leaves a channel's attenuation loose or free, start it from what
        natural water allows (core/model/jerlov.py: the Jerlov locus placed by the channels the
        survey pins): ``medium_info["prior"]`` says the type, each channel's source and how far
        the pinned channels lie from the locus (a cue where far: the photos' water is unlike the
        types, or the fit is off)."""
        att, spread = fit["fit"]["attenuation"], (fit.get("spread") or {}).get("attenuation")
        if spread is None:
            return
        got = jerlov.fill(att, spread, [p == "pinned" for p in pins["attenuation"]])
        if got is None:
            self.medium_info["prior"] = {"reason": "fewer than two channels pinned: the locus is not placed"}
            return
        self.medium_info["prior"] = {k: got[k] for k in ("name", "type", "misfit", "source", "values",
                                                          "values_spread", "attenuation")}
        if got["misfit"] > LOCUS_MISFIT:
            self.medium_info.setdefault("cues", []).append(
                f"the attenuation the survey pins lies {got['misfit']:.1f} standard deviations from the nearest "
                f"natural water's (Jerlov's {got['name']}): an unusual water, or a fit the photos mislead")
        if all(src == "photos" for src in got["source"]):
            return
        vals = fit["medium"].values()
        vals["attenuation"] = np.clip(got["values"], 1e-4, None).tolist()
        with torch.no_grad():   # the fitted medium's own parameter, on its device, takes the values
            fit["medium"].raw.copy_(Medium.from_values(vals).raw)

    def _unlit(self, obs: dict, divide: bool = False) -> None:
        """The lamp's light on the observations (where the run models a lamp): its fall-off with
        range is not the water's attenuation. Its gain goes to the fit as each observation's
        known light on the seabed (``obs["lit"]``), the veil in front of it as the camera sees
        it; with ``divide`` (light that moves over the seabed too, which the fit measures) the
        colours are divided by it instead."""
        lamp = getattr(self, "lamp", None)
        if lamp is None or not len(obs["colour"]):
            return
        with torch.no_grad():
            g = torch.exp(lamp.log_gain_at(*(torch.as_tensor(a, dtype=torch.float32, device=lamp.raw.device)
                                             for a in (*image_positions_of(obs), obs["range"]))))
        if not divide:
            obs["lit"] = g.cpu().double().numpy()
            return
        lin = srgb_to_linear(torch.from_numpy(obs["colour"])) / g.cpu().unsqueeze(-1)
        obs["colour"] = linear_to_srgb(lin.clamp(0.0, 1.0)).numpy()

    def true_point_colours(self) -> np.ndarray:
        """(M, 3) uint8 colours of the survey's sparse points without the water and, under a lamp,
        evenly lit (:meth:`~.lamp.LampMixin.evened_point_colours`): those fitted before training
        take their fit, the others are taken out of the water at the median range."""
        colours = np.asarray(self.data.scene.colors)
        if getattr(self, "lamp", None) is not None:
            colours = self.evened_point_colours(colours)
        if self._prefit is None:
            return colours
        vals = self.medium.values()
        lin = srgb_to_linear(torch.from_numpy(colours.astype(np.float32) / 255.0)).numpy()
        true = out_of_water(lin, np.full(len(lin), self.medium.length), vals, max_gain=4.0)
        true = linear_to_srgb(torch.from_numpy(true.astype(np.float32))).numpy()
        true[self._prefit["points"]] = self._prefit["true"]
        return np.round(np.clip(true, 0, 1) * 255).astype(np.uint8)

    def _background(self) -> torch.Tensor:
        """The render's background: black under water (the veil fills what the model leaves)."""
        bg = (0.0, 0.0, 0.0) if self.medium is not None else self.cfg.background
        return torch.tensor(bg, dtype=torch.float32, device=self.device)

    def ray_len(self, cam) -> torch.Tensor:
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
        if key not in self._ray_len:
            self._ray_len[key] = ray_lengths(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, self.device)
        return self._ray_len[key]

    @property
    def forms_image(self) -> bool:
        """The photos are modelled as more than the seabed's colour: through the water, or as a
        lamp on the camera lit them (core/train/lamp.py)."""
        return self.medium is not None or getattr(self, "lamp", None) is not None

    def as_seen(self, out, cam) -> torch.Tensor:
        """The render ``out`` of camera ``cam`` as the camera sees it: lit by the lamp and
        through the water (its ``rgb`` unchanged with neither)."""
        return self.seen_and_lamp(out, cam)[0]

    def seen_and_lamp(self, out, cam) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """:meth:`as_seen` and the lamp's log gain (H, W) on the view it used (``None`` without
        a lamp), so that a training step weighs its pixels without working the lamp out again."""
        lamp = getattr(self, "lamp", None)
        if self.medium is None and lamp is None:
            return out.rgb, None
        rng = Medium.range_of(out.alpha, out.depth, self.ray_len(cam))
        if lamp is not None:   # the lamp's light in linear light, then the water in front of it
            log_l = self.lamp_log_gain_of(cam, rng)
            lit = lit_by(out.rgb, torch.exp(log_l).unsqueeze(-1))
            return (lit if self.medium is None else self.medium.see_at(lit, rng)), log_l
        if (self.compiler.compiled() == "numba" and out.rgb.dtype == torch.float32
                and out.rgb.device.type == "cpu" and numba_water.load() is not None):
            return numba_water.see(out.rgb, rng, *self.medium.coefficients()), None   # numba's threads, one pass
        return self.medium.see_at(out.rgb, rng), None

    def _hold_points_water(self) -> None:
        """Which of the water's raw parameters (rows: attenuation, backscatter, veil; columns:
        channels) training leaves as the points gave them: ``self._held``, ``None`` for none. The
        points measured them better than the render's depth and holes would let training."""
        kept = self.medium_info.get("attenuation_kept")
        if kept is None:   # a checkpoint's older form: all three or none
            kept = [bool(self.medium_info.get("attenuation_from_points"))] * 3
        veil = self.medium_info.get("veil_kept") or [False] * 3
        held = torch.tensor([kept, veil, veil], dtype=torch.bool, device=self.medium.raw.device)
        self._held = held if bool(held.any()) else None

    def _medium_step(self) -> None:
        if self.medium_optimizer is not None:
            if self._held is not None and self.medium.raw.grad is not None:
                self.medium.raw.grad[self._held] = 0.0
            self.medium_optimizer.step()
            self.medium_optimizer.zero_grad(set_to_none=True)

    @torch.no_grad()
    def decide_medium(self) -> None:
        """``auto``: leave the water out when it changes the training views by less than
        :data:`MIN_EFFECT` 8-bit levels (measured on up to :data:`DECIDE_VIEWS` of them), and
        where the true colour it leaves fails :meth:`_judge_true_colour` on them."""
        if self.medium is None:
            return
        ids = self._decide_views()
        diffs = []
        over = covered = 0.0
        true, seen = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
        for i in ids:
            out = self.render_output(i, seen=False)
            cam, _ = self.data.view(i, 1)
            shown = self.as_seen(out, cam).clamp(0, 1)
            diffs.append(float((shown - out.rgb.clamp(0, 1)).abs().mean()) * 255)
            on = out.alpha > 0.5   # the seabed the view covers
            covered += float(on.sum())
            over += float(((out.rgb > 1.0 + 1.0 / 255).any(-1) & on).sum())
            true += srgb_to_linear(out.rgb.clamp(0, 1))[on].double().sum(0).cpu()
            seen += srgb_to_linear(shown)[on].double().sum(0).cpu()
        effect = float(np.mean(diffs))
        self.medium_info["effect_levels"] = effect
        if self.cfg.medium != "auto":
            return
        if effect < MIN_EFFECT:
            self.medium_info.update(kept=False, reason=f"the fitted water changes the photos by {effect:.1f} "
                                                       f"levels of 255 on average, below {MIN_EFFECT}: left out")
            self.medium = None
            self.medium_optimizer = None
        elif covered > 0:
            self._judge_true_colour(over / covered, true, seen)

    def _decide_views(self) -> list[int]:
        """The training views the end-of-run decision renders: up to :data:`DECIDE_VIEWS`,
        spread through the survey."""
        ids = self.data.train_ids
        return ids[:: max(1, len(ids) // DECIDE_VIEWS)][:DECIDE_VIEWS]

    def _judge_true_colour(self, share: float, true: torch.Tensor, seen: torch.Tensor) -> None:
        """The true colour the trained water leaves on the views :meth:`decide_medium` rendered:
        ``share`` of the seabed they cover above white in some channel, and its cast (the
        brightest over the weakest channel's mean, linear, of ``true``) against the render's as
        the photos see it (``seen``); where it fails (the module), :meth:`keep_as_seen`."""
        cast = float(true.max() / true.min().clamp_min(1e-6))
        cast_seen = float(seen.max() / seen.min().clamp_min(1e-6))
        self.medium_info.update(true_over_white=round(share, 4), true_cast=round(cast, 3),
                                seen_cast=round(cast_seen, 3))
        if share > MAX_OVER_WHITE:
            self.keep_as_seen(f"the true colour the water leaves lies above white on {100 * share:.0f} % of the "
                              f"seabed seen (at most {100 * MAX_OVER_WHITE:.0f} %; every output would clip it)")
        elif cast > max(GREY_WORLD, cast_seen):
            self.keep_as_seen(f"the true colour the water leaves is tinted {cast:.1f} times brighter in one channel "
                              f"than another, more than the photos through the water ({cast_seen:.1f}) and than "
                              f"{GREY_WORLD:g}: taking the water out tinted the seabed")

    @torch.no_grad()
    def keep_as_seen(self, why: str) -> None:
        """Leave the water out and give the Gaussians the colour the photos show: each one's
        colour (its SH, to first order beyond the constant term) put through the water
        (:meth:`Medium.see_at`) at the range the decision's views see it from (:meth:`gaussian_ranges`)."""
        rng = self.gaussian_ranges(self._decide_views())   # (N,): each colour (N, 3) seen as a pixel at that range
        see = self.medium.see_at
        dc, rest = self.params["sh_dc"], self.params["sh_rest"]
        colour = dc[:, 0] * SH_C0 + 0.5
        eps = 1e-3
        slope = (see(colour + eps, rng) - see(colour - eps, rng)) / (2 * eps)
        dc[:, 0] = (see(colour, rng) - 0.5) / SH_C0
        rest.mul_(slope.unsqueeze(1))
        values = self.medium.values()
        self.medium, self.medium_optimizer, self._held = None, None, None
        self.medium_info.update(kept=False, as_seen=True, coefficients_left_out=values, reason=(
            f"{why}: the water is left out and the Gaussians keep the colour the photos show"))

    def gaussian_ranges(self, ids: list[int]) -> torch.Tensor:
        """(N,) each Gaussian's range: its distance from the camera centre, averaged over the
        training views ``ids`` whose frame holds it in front of the camera (``Camera.project``;
        the survey's median range where none does)."""
        means = self.params["means"].detach().cpu().double().numpy()
        total, count = np.zeros(len(means)), np.zeros(len(means))
        for i in ids:
            cam = self.data.scene.cameras[i]
            uv, z = cam.project(means)
            seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            total += np.where(seen, np.linalg.norm(means - cam.center, axis=1), 0.0)
            count += seen
        rng = np.where(count > 0, total / np.maximum(count, 1), float(self.medium.length))
        return torch.as_tensor(rng, dtype=self.params["means"].dtype, device=self.params["means"].device)

    def medium_summary(self) -> dict:
        """What the report and medium.json say: the decision, why, and the coefficients."""
        info = dict(self.medium_info)
        if self.medium is not None:
            info["coefficients"] = self.medium.values()
        return info

    # --- state ------------------------------------------------------------------------------
    def _medium_state(self) -> Optional[dict]:
        if self.medium is None:
            return None
        return {"medium": self.medium.state_dict(), "info": self.medium_info,
                "optimizer": self.medium_optimizer.state_dict() if self.medium_optimizer else None}

    def _load_medium_state(self, s: Optional[dict]) -> None:
        if s is None:
            if self.medium is not None and self.step > 0:   # saved after the water was left out
                self.medium, self.medium_optimizer = None, None
            return
        self.medium = Medium.from_state(s["medium"], self.device)
        self.medium_optimizer = torch.optim.Adam([self.medium.raw], lr=LR_MEDIUM, eps=1e-15)
        if s.get("optimizer") is not None:
            self.medium_optimizer.load_state_dict(s["optimizer"])
        self.medium_info = dict(s["info"])
        self._hold_points_water()

