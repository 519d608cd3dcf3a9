"""The lamp in training: the trainer fits the light fixed to the camera (core/model/lamp.py) with
the Gaussians, so that they hold the seabed evenly lit and the lamp is a few numbers beside them.

The job looks at the survey's light before training (core/caustics/light.py) and gives the
trainer what it found (``light``). With ``lamp = "auto"`` (the default) a run models the lamp
where that light varies by :data:`LAMP_FLOOR` or more over the frame (a lamp's cone, its fall-off
with range, vignetting), explains :data:`LAMP_EXPLAINED` of how the frames differ, and varies
more than the light that moves over the seabed (broad caustics'
part the fit between frames cannot tell from a pattern); the finding's fit starts the lamp and
training refines it. The water's
fit to the sparse points (water.py) then sees the points' colours with the lamp taken out, so the
lamp's fall-off with range is not taken for the water's attenuation.

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
        self.lamp_optimizer = torch.optim.Adam([self.lamp.raw], lr=LR_LAMP, eps=1e-15)
        pct = 100 * (math.exp(float(light.get("camera", 0.0))) - 1)
        self.lamp_info.update(kept=True, r0=r0, start=self.lamp.values(),
                              reason=f"light fixed to the camera (a lamp's cone and fall-off, or vignetting) varies "
                                     f"by {pct:.0f} % over the frame: modelled, the Gaussians hold the seabed evenly "
                                     f"lit as the lamp lights the frame's centre at {r0:.2f} units")

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
