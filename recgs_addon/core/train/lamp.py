"""The lamp in training: the trainer fits the light fixed to the camera (core/model/lamp.py) with
the Gaussians, so that they hold the seabed evenly lit and the lamp is a few numbers beside them.

The job looks at the survey's light before training (core/caustics/light.py) and gives the
trainer what it found (``light``). With ``lamp = "auto"`` (the default) a run models the lamp
where that light varies by :data:`LAMP_FLOOR` or more over the frame (a lamp's cone, its fall-off
with range, vignetting), explains :data:`LAMP_EXPLAINED` of how the frames differ, and varies
more than the light that moves over the seabed (broad caustics'
part the fit between frames cannot tell from a pattern). The lamp is then fitted to the
sparse points' colours in every training view (core/model/lamp.py ``fit_to_points``; the
finding's fit between frames where that fit is no better or its fall-off no lamp's), the
Gaussians start from the points' colours evenly lit under it (:meth:`LampMixin.evened_point_colours`),
and training refines both, each pixel weighed as if the seabed there were evenly lit
(:meth:`LampMixin.lamp_weight`). The water's fit to the sparse points (water.py) then takes
the lamp's light on each point as known, the veil in front of it, so the lamp's fall-off with
range is not taken for the water's attenuation.

:class:`LampMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``data`` and
``device``); the report reads :meth:`LampMixin.lamp_summary`.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

from ..model.lamp import Lamp

#: The light fixed to the camera is modelled (auto) from this spread over the frame (standard
#: deviation of its log, 0.15: about 16 %); a caustic survey's fit reads 0.04-0.08 where there is
#: no lamp, a lamp-lit wreck 0.98 (benchmarks/RESULTS.md#light-finding).
LAMP_FLOOR = 0.15
#: ... where it explains this share of how a seabed point's brightness differs between frames
#: (what the fit is sure of: 0.96-0.996 on lamp-lit surveys, under 0.4 where a few frames'
#: misregistration is all there is to fit).
LAMP_EXPLAINED = 0.5
#: Adam's learning rate for the lamp's terms in training.
LR_LAMP = 0.002
#: Training weighs a pixel by the inverse of what the lamp's light does to its share of the loss
#: (an sRGB level of a seabed lit by ``L`` moves as ``L ** (1 / 2.4)`` with its colour), up to
#: this many times a fully lit pixel's weight: the beam's dark edges teach the Gaussians as much
#: as its centre, where their 8-bit levels still carry the seabed.
LAMP_WEIGHT_CAP = 6.0
#: ... and not at all where the lamp gives less than this (a white seabed there is a few 8-bit
#: levels: the frame's corners outside a narrow beam).
LAMP_DARKEST = 0.01
#: The sparse points' fit of the lamp starts it where its residual spread is at most this share
#: of the frames' fit's on the same points (a narrow beam: 0.051 against 0.107)...
POINTS_BETTER = 0.9
#: ... and its fall-off with range is a lamp's (the inverse square is -2): a forward-looking
#: wreck's points, far off in open water under changing exposure, drove it to -33.
POINTS_FALL = (-4.0, 1.0)
#: Share of the image's width around the principal point whose sparse points give the range the
#: lamp is normalised at (:func:`centre_range`).
CENTRE_SHARE = 0.15


def centre_range(data) -> Optional[float]:
    """The survey's usual range at the image centre (scene units): over the training views, the
    median range of the sparse points that project within :data:`CENTRE_SHARE` of the width of
    the principal point; None without such points."""
    pts = np.asarray(data.scene.points, np.float64)
    if len(pts) > 20000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 20000, replace=False)]
    ranges = []
    for i in data.train_ids:
        cam = data.scene.cameras[i]
        pc = pts @ cam.R.T + cam.t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * pc[:, 0] / z
            v = cam.fy * pc[:, 1] / z
        near = (z > 1e-6) & (np.hypot(u, v) <= CENTRE_SHARE * cam.width)
        if near.any():
            ranges.append(float(np.median(np.linalg.norm(pc[near], axis=1))))
    return float(np.median(ranges)) if ranges else None


def lamp_decision(light: dict) -> tuple[bool, str]:
    """Whether ``auto`` models the lamp for a survey whose light is ``light`` (``LightFinding.
    summary()``), and why not (see the module)."""
    spread = float(light.get("camera", 0.0))
    pct = lambda v: 100 * (math.exp(v) - 1)   # noqa: E731
    if spread < LAMP_FLOOR:
        return False, (f"light fixed to the camera varies by {pct(spread):.0f} % over the frame (a lamp or "
                       f"vignetting is modelled from {pct(LAMP_FLOOR):.0f} %): not modelled")
    explained = float(light.get("explained", 0.0))
    if explained < LAMP_EXPLAINED:
        return False, (f"light fixed to the camera would vary by {pct(spread):.0f} % over the frame, but explains "
                       f"{100 * explained:.0f} % of how the frames differ (a lamp is modelled from "
                       f"{100 * LAMP_EXPLAINED:.0f} %): not modelled")
    moving = float(light.get("moving", 0.0))
    if spread < moving:
        return False, (f"light fixed to the camera varies by {pct(spread):.0f} % over the frame, less than the light "
                       f"that moves over the seabed ({pct(moving):.0f} %), whose broad part the fit cannot tell from "
                       "it: not modelled")
    return True, ""


class LampMixin:
    """The trainer's lamp: set up from the survey's light, applied to renders, fitted (see the module)."""

    def _init_lamp(self, light: Optional[dict]) -> None:
        c = self.cfg
        self.lamp: Optional[Lamp] = None
        self.lamp_optimizer: Optional[torch.optim.Adam] = None
        self.lamp_info: dict = {"mode": c.lamp, "kept": False, "reason": "lamp off"}
        if c.lamp == "off":
            return
        if light is None or not light.get("pattern_coef"):
            self.lamp_info["reason"] = "the survey's light was not compared between frames: no lamp modelled"
            return
        wanted, why = lamp_decision(light)
        if c.lamp == "auto" and not wanted:
            self.lamp_info["reason"] = why
            return
        r0 = centre_range(self.data)
        if r0 is None:
            self.lamp_info["reason"] = "no sparse point near the image centres: no range to normalise a lamp at"
            return
        a, b = (light.get("range_coef") or [0.0, 0.0])[:2]
        self.lamp = Lamp(r0, light["pattern_coef"], a, b, device=self.device)
        self.lamp_info["start_from"] = "frames"
        frames = self.lamp.values()
        fit = self._lamp_from_points(r0, frames)
        if fit is not None:
            self.lamp_info["points_fit"] = {k: round(fit[k], 4) if isinstance(fit[k], float) else fit[k]
                                            for k in ("spread", "start_spread", "observations")}
            # every sparse point's every view: the beam's edges too
            if fit["spread"] > POINTS_BETTER * fit["start_spread"]:
                self.lamp_info["points_fit"]["not_used"] = "it explains the points no better than the frames' fit"
            elif not POINTS_FALL[0] <= fit["fall"] <= POINTS_FALL[1]:
                self.lamp_info["points_fit"]["not_used"] = f"its fall-off with range ({fit['fall']:.1f}) is no lamp's"
            else:
                self.lamp = Lamp(r0, fit["pattern"], fit["fall"], fit["attenuation"], device=self.device)
                self.lamp_info.update(start_from="points", frames_start=frames)
        self.lamp_optimizer = torch.optim.Adam([self.lamp.raw], lr=LR_LAMP, eps=1e-15)
        pct = 100 * (math.exp(float(light.get("camera", 0.0))) - 1)
        self.lamp_info.update(kept=True, r0=r0, start=self.lamp.values(),
                              reason=f"light fixed to the camera (a lamp's cone and fall-off, or vignetting) varies "
                                     f"by {pct:.0f} % over the frame: modelled, the Gaussians hold the seabed evenly "
                                     f"lit as the lamp lights the frame's centre at {r0:.2f} units")

    def evened_point_colours(self, colours: np.ndarray) -> np.ndarray:
        """(M, 3) uint8 the sparse points' ``colours`` as the lamp's model holds the seabed: evenly
        lit as the lamp lights the frame's centre at ``r0``. A point's colour in the photos is its
        seabed times the lamp's light where each view saw it, which under a narrow beam is a
        fraction of the centre's: Gaussians started from it render the frames too dark, and in the
        first hundred steps the lamp (a few numbers every pixel teaches) brightens everywhere but
        at the frame's centre, where it is 1 by definition, faster than the Gaussians catch up;
        it took the rest of a three-minute run to come back. The points' colours are read from
        the photos under the lamp's light (:meth:`~.data.TrainData.point_colours`)."""
        if self.lamp is None:
            return np.asarray(colours)
        lamp = self.lamp

        def light(cam, u, v, rng):
            half = 0.5 * cam.width
            with torch.no_grad():
                return torch.exp(lamp.log_gain_at(*(torch.as_tensor(a, dtype=torch.float32, device=lamp.raw.device)
                                                    for a in ((u - cam.cx) / half, (v - cam.cy) / half, rng))))\
                    .cpu().double().numpy()
        return self.data.point_colours(colours, light)

    def point_observations(self, colours: bool = True) -> dict:
        """The sparse points' observations in the training views (water.py's ``_observations``)
        and with ``colours`` their colours in the photos (``_sample_colours``, read when first
        asked for), made once for the lamp's and the water's fits: a copy each (the water's may
        divide its colours by the lamp)."""
        from . import water
        if getattr(self, "_point_obs", None) is None:
            self._point_obs = water._observations(self.data)
        obs = self._point_obs
        if colours and "colour" not in obs:
            if len(obs["point"]):
                water._sample_colours(self.data, obs)
            else:
                obs["colour"] = np.zeros((0, 3), np.float32)
        return dict(obs, colour=obs["colour"].copy()) if "colour" in obs else dict(obs)

    def _lamp_from_points(self, r0: float, start: dict) -> Optional[dict]:
        """The lamp fitted to the sparse points' colours (core/model/lamp.py ``fit_to_points``;
        ``start``'s spread on the same points beside it), or None where too few are seen."""
        from ..model.colour import srgb_to_linear
        from ..model.lamp import fit_to_points
        from .water import image_positions_of
        obs = self.point_observations()
        if not len(obs["point"]):
            return None
        grey = srgb_to_linear(torch.from_numpy(obs["colour"]).double()).mean(-1).numpy()
        return fit_to_points(obs["point"], *image_positions_of(obs), obs["range"], grey, r0, start=start)

    @staticmethod
    def lamp_weight(log_l: torch.Tensor) -> torch.Tensor:
        """(H, W) each pixel's weight in the loss under the lamp (:data:`LAMP_WEIGHT_CAP`), from
        the lamp's log gain ``log_l`` (H, W) on the view; not differentiated."""
        with torch.no_grad():
            log_l = log_l.detach()
            w = torch.exp(-log_l / 2.4).clamp(max=LAMP_WEIGHT_CAP)
            return torch.where(log_l >= math.log(LAMP_DARKEST), w, torch.zeros_like(w))

    def lamp_log_gain_of(self, cam, rng: torch.Tensor) -> torch.Tensor:
        """(H, W) the lamp's log gain on camera ``cam``'s pixels at range ``rng`` (H, W)."""
        return self.lamp.log_gain(cam.width, cam.height, cam.cx, cam.cy, rng)

    def _lamp_step(self) -> None:
        if self.lamp_optimizer is not None:
            self.lamp_optimizer.step()
            self.lamp_optimizer.zero_grad(set_to_none=True)

    def lamp_summary(self) -> dict:
        info = dict(self.lamp_info)
        if self.lamp is not None:
            info["coefficients"] = self.lamp.values()
        return info

    def _lamp_state(self) -> Optional[dict]:
        if self.lamp is None:
            return None
        return {"lamp": self.lamp.state_dict(), "info": self.lamp_info,
                "optimizer": self.lamp_optimizer.state_dict() if self.lamp_optimizer else None}

    def _load_lamp_state(self, s: Optional[dict]) -> None:
        if s is None:
            return
        self.lamp = Lamp.from_state(s["lamp"], self.device)
        self.lamp_optimizer = torch.optim.Adam([self.lamp.raw], lr=LR_LAMP, eps=1e-15)
        if s.get("optimizer") is not None:
            self.lamp_optimizer.load_state_dict(s["optimizer"])
        self.lamp_info = dict(s.get("info", self.lamp_info))
