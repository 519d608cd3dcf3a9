"""The survey generator's lamp on the camera (pure numpy, no bpy): a cone of light fixed to the
camera, falling off with range, and vignetting.

tools/make_survey.py renders the seabed under its ordinary light (``clean/``, the truth under
even light); with ``--lamp`` this module relights each photo as a lamp beside the camera lights
it, per pixel, from the true range along each pixel's ray (before the water, which then acts
on the lamp's light as on any other):

    I = J * beam(angle) / d^2 * exp(-c * d) * vignette(x) / (the same at the centre, at r0)

``J`` is the seabed as ``clean/`` holds it, ``d`` the distance from the lamp (``offset`` metres
from the camera centre, in camera axes) to the seabed point, ``angle`` the angle between the
lamp's axis (the camera's, tilted by ``tilt`` degrees down in the image) and the ray from the
lamp to the point, ``beam`` a Gaussian of half-width ``beam`` degrees, ``r0`` the survey's
nominal range (the camera's altitude over its pitch): where the image's centre sees the seabed
at ``r0`` the photo is ``J``, so the truth is the seabed as the lamp lights the centre of the
image at the nominal range, evenly (core/model/lamp.py's convention). ``c`` is the lamp path's attenuation per metre (``--water``'s
direct attenuation, or none), ``vignette`` the lens's fall-off, ``(1 + s rho^2)^-2`` of the
radius ``rho`` from the image centre in half-widths.
"""
from __future__ import annotations

import math

import numpy as np

#: Lamp beside the camera, in camera axes (x right, y down, z forward; metres): 15 cm below.
LAMP_OFFSET = (0.0, 0.15, 0.0)


def lamp_gain(width: int, height: int, fx: float, fy: float, cx: float, cy: float, depth: np.ndarray,
              r0: float, beam_deg: float = 25.0, tilt_deg: float = 8.0, offset=LAMP_OFFSET,
              attenuation=(0.0, 0.0, 0.0), vignette: float = 0.0) -> np.ndarray:
    """(H, W, 3) the lamp's gain on each pixel of a view whose planar ``depth`` (H, W) is
    known (non-finite or <= 0 where no surface: gain 0)."""
    u = (np.arange(width) + 0.5 - cx) / fx
    v = (np.arange(height) + 0.5 - cy) / fy
    rx, ry = np.meshgrid(u, v)
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    t = math.radians(tilt_deg)
    axis = np.array([0.0, math.sin(t), math.cos(t)])
    off = np.asarray(offset, np.float64)

    def light(p):
        """Irradiance (grey, up to a constant) and lamp distance at camera-space points ``p``."""
        to = p - off
        d = np.linalg.norm(to, axis=-1)
        ang = np.degrees(np.arccos(np.clip((to @ axis) / np.maximum(d, 1e-9), -1.0, 1.0)))
        return np.exp(-0.5 * (ang / beam_deg) ** 2) / d ** 2, d

    e, d = light(np.stack([rx * z, ry * z, z], -1))
    e0, _ = light(np.array([0.0, 0.0, r0]))       # the frame's centre at the nominal range: gain 1
    gain = e / e0
    rho2 = ((np.arange(width) + 0.5 - cx)[None, :] ** 2 + (np.arange(height) + 0.5 - cy)[:, None] ** 2) / (0.5 * width) ** 2
    gain = gain * (1.0 + vignette * rho2) ** -2
    att = np.exp(-np.asarray(attenuation, np.float64) * (d[..., None] - r0))
    return np.nan_to_num(gain[..., None] * att, nan=0.0)
