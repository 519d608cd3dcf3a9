"""Burned-in overlays: pixels that stay put while the scene moves (a time stamp, a logo, a
housing's dark corners, an undistorted frame's blank margins), found once a survey and left out
of training, the light finding, the caustic estimates and the scores.

Over frames in their order (names sort in time for clips and numbered photos), a scene pixel
changes from one frame to the next as the camera moves; an overlay's does not. A pixel is an
overlay where its median change over consecutive frames is below :data:`STATIC_RATIO` of the
frame's typical change, as it is for most of its 3x3 neighbourhood, and it is either textured
(text, a logo: the median frame's gradient at least :data:`CONTRAST`) or dark (below
:data:`DARK`: corners and margins no light reaches). The
found pixels grow by :data:`MARGIN` of the width, which covers a time stamp's changing digits
beside its steady ones. Where the frames hardly change (a camera at rest), or the static part
is more than :data:`MAX_SHARE` of the frame, nothing is masked and the finding says why.

Shapes: grey frames (H, W) float32 in [0, 1]; the mask (H, W) bool, True on the overlay.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

#: Long side (pixels) frames are compared at: a time stamp's characters stay a few pixels tall.
OVERLAY_SIDE = 640
#: Consecutive pairs compared at most (spread over the survey).
MAX_PAIRS = 60
#: Frames needed to say anything.
MIN_FRAMES = 5
#: A pixel whose median change is below this share of the frame's median change stays put.
STATIC_RATIO = 0.1
#: ... and below this the frames hardly change at all (grey levels of 1): nothing to tell.
MIN_CHANGE = 0.01
#: Gradient of the median frame (grey levels of 1 a pixel) from which a static pixel is text.
CONTRAST = 0.05
#: Grey level below which a static pixel is a dark corner or margin.
DARK = 0.04
#: The found pixels grow by this share of the width.
MARGIN = 0.02
#: The most of a frame an overlay may take; more and the scene is taken to be at rest.
MAX_SHARE = 0.25


@dataclass
class Overlay:
    """What :func:`find_overlay` found."""

    mask: Optional[torch.Tensor]   # (h, w) bool at OVERLAY_SIDE, True on the overlay; None: none masked
    share: float                   # share of the frame masked
    frames: int                    # frames compared
    reason: str

    def summary(self) -> dict:
        return {"share": round(self.share, 4), "frames": self.frames, "reason": self.reason}


def find_overlay(frames: Sequence[torch.Tensor]) -> Overlay:
    """The overlay of grey ``frames`` (each (h, w), in their order, consecutive where they
    come in pairs: ``frames[2k]`` and ``frames[2k + 1]`` are neighbours in time)."""
    n = len(frames) // 2
    if 2 * n < MIN_FRAMES:
        return Overlay(None, 0.0, len(frames), "too few frames to look for a burned-in overlay")
    g = torch.stack(list(frames)).float()
    change = (g[1::2] - g[0::2]).abs().median(0).values
    typical = float(change.median())
    if typical < MIN_CHANGE:
        return Overlay(None, 0.0, len(frames), "the frames hardly change: no overlay looked for")
    still = g.median(0).values
    gy, gx = torch.gradient(still)
    still_px = (change < STATIC_RATIO * typical).float()
    # most of its 3x3 neighbourhood still too: a lone pixel of a fine moving texture can change
    # little by chance
    still_px = F.avg_pool2d(still_px[None, None], 3, stride=1, padding=1, count_include_pad=False)[0, 0] >= 0.6
    static = still_px & (change < STATIC_RATIO * typical) & ((torch.sqrt(gx * gx + gy * gy) > CONTRAST) | (still < DARK))
    if not bool(static.any()):
        return Overlay(None, 0.0, len(frames), "no burned-in overlay found")
    r = max(1, round(MARGIN * still.shape[1]))
    mask = F.max_pool2d(static.float()[None, None], 2 * r + 1, stride=1, padding=r)[0, 0] > 0
    share = float(mask.float().mean())
    if share > MAX_SHARE:
        return Overlay(None, share, len(frames), f"{100 * share:.0f} % of the frame stays put: the scene is taken "
                                                 "to be at rest, nothing masked")
    return Overlay(mask, share, len(frames), f"a burned-in overlay (pixels that stay put while the scene moves: a "
                                             f"time stamp, a logo, dark corners) on {100 * share:.1f} % of the frame, "
                                             "left out of training, the light finding and the scores")


def mask_at(overlay: Overlay, height: int, width: int) -> Optional[torch.Tensor]:
    """(height, width) bool: True where a pixel of that size counts (off the overlay), or None
    where nothing is masked."""
    if overlay.mask is None:
        return None
    m = F.interpolate(overlay.mask.float()[None, None], size=(height, width), mode="bilinear",
                      align_corners=False)[0, 0]
    return m <= 0.0
