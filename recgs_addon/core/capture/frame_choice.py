"""Which frames of a video clip become the survey's photos (numpy only; the decoding is in video.py).

The clip is cut into windows; in each window the sharpest frame (the variance of the Laplacian
of its grey image, :func:`sharpness`) is the candidate, and it is kept unless it is a
near-duplicate of the frame kept last (the mean absolute difference of small grey thumbnails,
:func:`thumbnail`, below :data:`DUPLICATE_MAD`: a camera that hovers), or too dark to hold
anything (lights off, a lens cap). :class:`FrameChooser` does this on a stream of frames,
holding only each window's best frame so far, so a clip is decoded once.

Where the windows fall. By default by how far the view has moved (:class:`MotionWindows`): a
window ends once the image has moved :data:`MOTION_STEP` of itself from the window's first
frame (:func:`image_shift`, phase correlation of grey thumbnails), or once it no longer
matches that frame at all (the camera turned, or jumped), or after :data:`MAX_WINDOW_S`
seconds (a camera that hovers). A fast pass thus gets many frames a second and a slow one
few, and consecutive frames always overlap by about the same share, which is what
structure from motion needs. If that gives more than the most frames asked for
(:data:`MAX_FRAMES`), :func:`thin` keeps an even selection. With a fixed spacing in seconds
instead (:class:`TimeWindows`, :func:`window_count`), windows are equal spans of time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

#: Most frames a clip gives by default. A diver or small ROV films the seabed from 1-3 m at
#: 0.3-0.5 m/s; at one frame per :data:`MOTION_STEP` of the image, a minute of footage gives
#: ~100-200 frames, and 300 keep sequential matching and mapping within ~10 minutes on 2 cores.
MAX_FRAMES = 300
#: A window ends once the view has moved this share of the image from its first frame (the
#: share of the image that is new: 1 - (1 - |dx|)(1 - |dy|) for a shift of dx, dy of the
#: image's width and height). The sharpest frame of each window is kept, so consecutive kept
#: frames lie ~0.1 and at most ~0.2 of the image apart: a seabed point stays in ~10 of them
#: along a pass, the views SfM and caustic removal want. Measured (``benchmarks/bench_video.py
#: --soft``, 2026-11-27): 4 frames a second put the soft clip's frames 0.7 of the image apart and
#: registered 17 of 32; steps of 0.12, 0.1 and 0.08 register all (135, 169, 216 frames), the
#: farthest camera centre 0.82, 1.0 and 1.15 % of the extent off (the clip's last frames: drift
#: grows with the number of short steps). On 64 stills 0.12-0.16 apart shown 3 frames each
#: (the test survey ``data/dive``), 0.12 merged close stills and registered 49 of 53; 0.1 57 of
#: 57, 0.08 60 of 60.
MOTION_STEP = 0.1
#: Phase correlation's peak (0-1) below which two thumbnails are taken not to show the same
#: seabed: between unrelated frames of the benchmark clips it is 0.05 (at most 0.074); between
#: frames 0.1 of the image apart, 0.25-0.6.
MOTION_LOST_PEAK = 0.08
#: Long side of the grey thumbnails the motion is measured on (px): a shift of 1 px is 0.8 %
#: of the image, and one correlation costs ~0.1 ms.
MOTION_SIDE = 128
#: A window never spans more than this many seconds (a camera that hovers gives a frame this
#: often, dropped as a near-duplicate while nothing changes).
MAX_WINDOW_S = 2.0
#: With a fixed spacing in seconds: at most this many frames per second of clip unless the
#: spacing asks for more (at 30 fps each window then holds >= 7 frames to choose from).
MAX_FRAMES_PER_SECOND = 4.0
#: Fewest distinct frames a survey is made of: a point needs several views for SfM, and caustic
#: removal compares ~8 views of it.
MIN_FRAMES = 8
#: Frames a clip should give at least: where the motion step gives fewer (a clip of a few
#: seconds), the step is lowered until it gives this many or every distinct frame. A 4-s clip of
#: a wreck that moved 0.7 of the image gave 7 frames at the default step and registered 25 of 25
#: at a step of 0.03 (benchmarks/RESULTS.md#real-clips).
SHORT_CLIP_FRAMES = 24
#: ... but never below this step (shares of the image): closer frames add no baseline for
#: structure from motion and look alike to the frame choice.
MIN_STEP = 0.01
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


def window_count(duration_s: float, frames: int, target: Optional[int] = MAX_FRAMES,
                 every_s: Optional[float] = None) -> int:
    """How many equal windows of time a clip of ``duration_s`` seconds and ``frames`` frames is
    cut into: ``duration_s / every_s`` when a spacing is given, else ``target``, never more
    than :data:`MAX_FRAMES_PER_SECOND` per second; never more than ``frames``."""
    if every_s is not None:
        if every_s <= 0:
            raise ValueError(f"the spacing between frames must be positive, got {every_s} s")
        n = int(math.floor(duration_s / every_s + 1e-9))
    else:
        if target is None or target < 1:
            raise ValueError(f"the number of frames must be at least 1, got {target}")
        n = min(int(target), int(math.floor(duration_s * MAX_FRAMES_PER_SECOND + 1e-9)))
    return max(1, min(n, int(frames)))


def new_share(dx: float, dy: float) -> float:
    """Share of an image that is new after a shift of ``dx``, ``dy`` (shares of its width and
    height): 1 - (1 - |dx|)(1 - |dy|), 1 beyond a whole image."""
    return 1.0 - max(0.0, 1.0 - abs(dx)) * max(0.0, 1.0 - abs(dy))


class ShiftReference:
    """One grey thumbnail's spectrum, against which others' shifts are measured
    (:meth:`shift`): phase correlation with a Hann window (Kuglin and Hines 1975)."""

    def __init__(self, thumb: np.ndarray):
        self.shape = thumb.shape
        self._window = np.outer(np.hanning(thumb.shape[0]), np.hanning(thumb.shape[1])).astype(np.float32)
        self._spec = self._spectrum(thumb)

    def _spectrum(self, thumb: np.ndarray) -> np.ndarray:
        t = np.asarray(thumb, np.float32)
        return np.fft.rfft2((t - t.mean()) * self._window)

    def shift(self, thumb: np.ndarray) -> tuple[float, float, float]:
        """(dx, dy, peak): how far ``thumb``'s content lies from the reference's, in shares of
        the width and height (within half of each), and the correlation peak (1: the same
        image moved; ~0.05: unrelated images). Another size gives (1, 1, 0)."""
        if np.shape(thumb) != self.shape:
            return 1.0, 1.0, 0.0
        cross = np.conj(self._spec) * self._spectrum(thumb)
        cross /= np.abs(cross) + 1e-12
        corr = np.fft.irfft2(cross, s=self.shape)
        iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
        h, w = self.shape
        dy, dx = (iy - h if iy > h // 2 else iy), (ix - w if ix > w // 2 else ix)
        return dx / w, dy / h, float(corr[iy, ix])


def image_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """(dx, dy, peak) of thumbnail ``b`` against ``a`` (:meth:`ShiftReference.shift`)."""
    return ShiftReference(a).shift(b)


class TimeWindows:
    """Windows of time: ``bounds`` (n + 1,) are their edges in seconds; a frame at time t
    belongs to window ``i`` with ``bounds[i] <= t < bounds[i + 1]`` (the last also takes
    ``t == bounds[-1]`` and anything later)."""

    #: Dark frames are given to it: a window of only dark frames is counted as one.
    sees_dark_frames = True

    def __init__(self, bounds: np.ndarray):
        self.bounds = np.asarray(bounds, np.float64)
        self._window = -1

    def window_of(self, time_s: float) -> int:
        i = int(np.searchsorted(self.bounds, time_s, side="right")) - 1
        return min(max(i, 0), len(self.bounds) - 2)

    def starts_window(self, cand: "Candidate") -> bool:
        """Whether ``cand`` (the next frame, in time order) opens a new window."""
        w = self.window_of(cand.time_s)
        new, self._window = w != self._window, w
        return new


class MotionWindows:
    """Windows by how far the view has moved (see the module): a frame opens a new window when
    its :attr:`Candidate.motion` thumbnail has moved ``step`` of the image from the window's
    first frame, no longer matches it (peak below ``lost_peak``) while the window holds two
    frames or more, or lies ``max_s`` seconds after it. A window of one frame stays open when
    only the match fails: a motion-blurred first frame matches its sharp neighbours poorly, and
    would otherwise be kept alone. Dark frames are not given to it."""

    #: Dark frames move nothing: they are not given to it.
    sees_dark_frames = False

    def __init__(self, step: float = MOTION_STEP, lost_peak: float = MOTION_LOST_PEAK,
                 max_s: float = MAX_WINDOW_S):
        if not 0.0 < step < 1.0:
            raise ValueError(f"the step between frames is a share of the image, between 0 and 1 "
                             f"({MOTION_STEP:g} by default), got {step}")
        self.step, self.lost_peak, self.max_s = step, lost_peak, max_s
        self._ref: Optional[ShiftReference] = None
        self._t0 = 0.0
        self._frames = 0
        self._moved = 0.0      # the view's motion over the windows closed so far (shares of the image)
        self._share = 0.0      # ... and within the open one, from its first frame

    @property
    def moved(self) -> float:
        """How far the view has moved over the clip so far, in shares of the image: the new
        share at which each window ended, summed (a window that lost its match counts one
        step). What a smaller step would give: about ``moved / step`` windows."""
        return self._moved + self._share

    def starts_window(self, cand: "Candidate") -> bool:
        if self._ref is not None:
            dx, dy, peak = self._ref.shift(cand.motion)
            share = self.step if peak < self.lost_peak else new_share(dx, dy)
            if cand.time_s - self._t0 < self.max_s and (
                    self._frames < 2 if peak < self.lost_peak else share < self.step):
                self._frames += 1
                self._share = max(self._share, share) if peak >= self.lost_peak else self._share
                return False
            self._moved += share if peak >= self.lost_peak else max(self._share, self.step)
        self._ref, self._t0, self._frames, self._share = ShiftReference(cand.motion), cand.time_s, 1, 0.0
        return True


def thin(count: int, most: int) -> list[int]:
    """Which of ``count`` kept frames (indices, ascending) to keep when at most ``most`` may
    stay: an even selection, the first and last included. Kept frames lie about a motion step
    apart, so even in number is about even along the camera's path."""
    if count <= most:
        return list(range(count))
    if most <= 1:
        return [0][:max(most, 0)]
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, most)})


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
    motion: Optional[np.ndarray] = None   #: :func:`thumbnail` at :data:`MOTION_SIDE` (motion windows)


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

    ``windows`` says where windows start: :class:`TimeWindows`, :class:`MotionWindows`, or an
    array of time edges (a :class:`TimeWindows`). Feed every frame in time order to
    :meth:`add`; it returns the candidates kept by the windows that closed; :meth:`close`
    ends the last one.
    """

    def __init__(self, windows, duplicate_mad: float = DUPLICATE_MAD, dark_level: float = DARK_LEVEL):
        self.windows = windows if hasattr(windows, "starts_window") else TimeWindows(windows)
        self.duplicate_mad = duplicate_mad
        self.dark_level = dark_level
        self.stats = ChoiceStats()
        self._open = False
        self._best: Optional[Candidate] = None
        self._last_kept: Optional[Candidate] = None

    def add(self, cand: Candidate) -> list[Candidate]:
        kept = []
        dark = cand.brightness < self.dark_level
        if (self.windows.sees_dark_frames or not dark) and self.windows.starts_window(cand):
            kept += self._close_window()
            self._open = True
        self.stats.frames_seen += 1
        if dark:
            self.stats.dark_frames += 1
            return kept
        if self._best is None or cand.sharpness > self._best.sharpness:
            self._best = cand
        return kept

    def close(self) -> list[Candidate]:
        return self._close_window()

    def _close_window(self) -> list[Candidate]:
        if not self._open:
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
