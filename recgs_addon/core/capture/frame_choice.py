"""Which frames of a video clip become the survey's photos (numpy only; the decoding is in video.py).

The clip is cut into equal windows of time; in each window the sharpest frame (the variance
of the Laplacian of its grey image, :func:`sharpness`) is the candidate, and it is kept unless
it is a near-duplicate of the frame kept last (the mean absolute difference of small grey
thumbnails, :func:`thumbnail`, below :data:`DUPLICATE_MAD`: a camera that hovers), or too dark
to hold anything (lights off, a lens cap). :class:`FrameChooser` does this on a stream of
frames, holding only each window's best frame so far, so a clip is decoded once.

How many windows (:func:`window_count`): a target count (:data:`DEFAULT_FRAMES`) or a fixed
spacing in seconds, never more than :data:`MAX_FRAMES_PER_SECOND` of clip nor more than the
clip's frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

#: Frames a clip is cut into by default. A diver or small ROV films the seabed from 1-3 m at
#: 0.3-0.5 m/s, so a few minutes of footage cover the survey in a few passes; ~180 frames then
#: lie ~10 % of the image's height apart along a pass, which gives a point about 8 views in one
#: pass (the median of >= 8 views a point that SfM and caustic removal want), while sequential
#: matching and mapping stay within minutes on 2 cores. A spacing in seconds replaces it.
DEFAULT_FRAMES = 180
#: At most this many frames per second of clip: at 30 fps each window then holds >= 7 frames to
#: choose the sharpest from, and frames closer in time add little parallax.
MAX_FRAMES_PER_SECOND = 4.0
#: Fewest distinct frames a survey is made of: a point needs several views for SfM, and caustic
#: removal compares ~8 views of it.
MIN_FRAMES = 8
#: Frames are judged at this long side in pixels (smaller clips at their own size): the grey
#: image and its Laplacian then cost a few ms a frame, and motion blur of 2 px or more at 1080p
#: still shows.
ANALYSIS_SIDE = 960
#: Long side of the grey thumbnails compared to find near-duplicates (px).
THUMB_SIDE = 64
#: Mean absolute difference of two thumbnails (grey in [0, 1]) below which a frame is a
#: near-duplicate of the last kept one. Noise and compression differ by < 0.005; a shift of the
#: view by 0.5 % of its width already differs by 0.02 on the generated seabed
#: (tools/make_survey.py, 64-px thumbnails): only a camera that is practically still is dropped.
DUPLICATE_MAD = 0.012
#: A frame whose mean grey level (0-1) is below this is too dark to be a photo of the seabed.
DARK_LEVEL = 0.04


def grey_levels(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels 0-255 (Rec. 601 luma) of an (H, W, 3) uint8 RGB image."""
    return rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of an (H, W) grey image (levels 0-255): high for
    fine detail in focus, low for blurred or flat frames (Pech-Pacheco et al. 2000)."""
    g = np.asarray(grey, np.float32)
    if g.shape[0] < 3 or g.shape[1] < 3:
        return 0.0
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def thumbnail(grey: np.ndarray, side: int = THUMB_SIDE) -> np.ndarray:
    """Box-filtered (h, w) float32 thumbnail in [0, 1], long side ``side`` px, of an (H, W)
    grey image with levels 0-255."""
    g = np.asarray(grey, np.float32)
    h, w = g.shape
    scale = side / max(h, w)
    th, tw = max(1, min(h, round(h * scale))), max(1, min(w, round(w * scale)))
    rows = np.linspace(0, h, th + 1).astype(int)
    cols = np.linspace(0, w, tw + 1).astype(int)
    sums = np.add.reduceat(np.add.reduceat(g, rows[:-1], axis=0), cols[:-1], axis=1)
    return sums / np.outer(np.diff(rows), np.diff(cols)).astype(np.float32) / 255.0


def window_count(duration_s: float, frames: int, target: Optional[int] = DEFAULT_FRAMES,
                 every_s: Optional[float] = None) -> int:
    """How many windows a clip of ``duration_s`` seconds and ``frames`` frames is cut into:
    ``duration_s / every_s`` when a spacing is given, else ``target``; never more than
    :data:`MAX_FRAMES_PER_SECOND` per second (unless a spacing asks for it) nor more than
    ``frames``."""
    if every_s is not None:
        if every_s <= 0:
            raise ValueError(f"the spacing between frames must be positive, got {every_s} s")
        n = int(math.floor(duration_s / every_s + 1e-9))
    else:
        if target is None or target < 1:
            raise ValueError(f"the number of frames must be at least 1, got {target}")
        n = min(int(target), int(math.floor(duration_s * MAX_FRAMES_PER_SECOND + 1e-9)))
    return max(1, min(n, int(frames)))


@dataclass
class Candidate:
    """One decoded frame as the chooser sees it. ``payload`` is what the caller needs to write
    the frame if it is kept (a decoded frame); the chooser never looks into it."""

    index: int                 #: frame index in the clip (0-based, presentation order)
    time_s: float              #: presentation time (s from the clip's start)
    sharpness: float           #: :func:`sharpness` at the analysis size
    brightness: float          #: mean grey level, 0-1
    thumb: np.ndarray          #: :func:`thumbnail`
    payload: Any = None


@dataclass
class ChoiceStats:
    windows: int = 0           #: windows closed so far
    kept: int = 0
    duplicates: int = 0        #: windows whose best frame was a near-duplicate of the last kept
    dark: int = 0              #: windows with no frame bright enough
    frames_seen: int = 0
    dark_frames: int = 0


class FrameChooser:
    """Chooses frames from a stream, one window at a time.

    ``bounds`` (n + 1,) are the windows' edges in seconds; a frame at time t belongs to the
    window ``i`` with ``bounds[i] <= t < bounds[i + 1]`` (the last window also takes
    ``t == bounds[-1]`` and anything later). Feed every frame in time order to :meth:`add`;
    it returns the candidates kept by the windows that closed; :meth:`close` ends the last
    one.
    """

    def __init__(self, bounds: np.ndarray, duplicate_mad: float = DUPLICATE_MAD,
                 dark_level: float = DARK_LEVEL):
        self.bounds = np.asarray(bounds, np.float64)
        self.duplicate_mad = duplicate_mad
        self.dark_level = dark_level
        self.stats = ChoiceStats()
        self._window = -1
        self._best: Optional[Candidate] = None
        self._last_kept: Optional[Candidate] = None

    def window_of(self, time_s: float) -> int:
        i = int(np.searchsorted(self.bounds, time_s, side="right")) - 1
        return min(max(i, 0), len(self.bounds) - 2)

    def add(self, cand: Candidate) -> list[Candidate]:
        kept = []
        w = self.window_of(cand.time_s)
        if w != self._window:
            kept += self._close_window()
            self._window = w
        self.stats.frames_seen += 1
        if cand.brightness < self.dark_level:
            self.stats.dark_frames += 1
            return kept
        if self._best is None or cand.sharpness > self._best.sharpness:
            self._best = cand
        return kept

    def close(self) -> list[Candidate]:
        return self._close_window()

    def _close_window(self) -> list[Candidate]:
        if self._window < 0:
            return []
        self.stats.windows += 1
        best, self._best = self._best, None
        if best is None:
            self.stats.dark += 1
            return []
        if self._last_kept is not None and mean_abs_diff(best.thumb, self._last_kept.thumb) < self.duplicate_mad:
            self.stats.duplicates += 1
            return []
        self._last_kept = best
        self.stats.kept += 1
        return [best]


def mean_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two thumbnails; infinite when their shapes differ."""
    if a.shape != b.shape:
        return math.inf
    return float(np.abs(a - b).mean())
