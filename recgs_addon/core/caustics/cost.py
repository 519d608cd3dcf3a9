"""What the caustic work will cost, said before a run starts: the pass estimator's seconds and
memory at the survey's size on this machine (the job's plan shows them, and the job trains plain
where they do not fit its time limit or its memory).

The pass estimator's work is image work (the plane sweep, warps, box filters) over every pixel
of every frame it reads, so its time is the survey's pixels times a constant measured here in
units of a short probe of the same kind of work (:func:`probe_seconds`: a warp and a windowed
correlation on a small image, timed on the machine that runs the job), which carries the
figure from the machine the constant was measured on to this one::

    seconds = probe * UNITS_PER_MEGAPIXEL * megapixels
    bytes   = BYTES_PER_PIXEL * pixels

Measured (the estimator run whole after a short warm-up, ``benchmarks/bench_pass_cost.py``):
1,099-1,218 probe units a megapixel and 295-434 bytes a pixel at its peak over what the job held
before, on the README's dive survey (64 frames, 256x192; on one thread and on two), a tiled pool
(36 photos, 640x342) and a reef clip (29 frames, 640x360); the constants are the largest,
rounded up. The probe is large enough to use the machine's threads as the estimator does (a
small one ran faster on one thread than on two, and told the time of neither).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from .geometry import zncc

#: The probe's image (pixels), and how many times its work is repeated (the fastest counts).
PROBE_SIZE = (480, 640)
PROBE_REPEATS = 5
#: Probe units a megapixel of the frames the estimator reads (training and held-out).
UNITS_PER_MEGAPIXEL = 1_300
#: Peak memory a pixel of those frames (photos, depths, the sweep's scores, the gathered
#: samples, each frame's statistics and estimates).
BYTES_PER_PIXEL = 460

_PROBE: dict = {}


def probe_seconds() -> float:
    """Seconds this machine takes for one piece of the pass estimator's work (a bilinear warp of
    a small image and its windowed correlation with the original), the fastest of a few runs,
    measured once a process."""
    if "s" not in _PROBE:
        g = torch.Generator().manual_seed(0)
        h, w = PROBE_SIZE
        a = torch.rand(1, h, w, generator=g)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        grid = torch.stack([xs + 0.01, ys - 0.01], -1).unsqueeze(0)
        best = float("inf")
        for _ in range(PROBE_REPEATS):
            t = time.perf_counter()
            b = F.grid_sample(a.unsqueeze(0), grid, mode="bilinear", align_corners=False)[0]
            zncc(a, b)
            best = min(best, time.perf_counter() - t)
        _PROBE["s"] = best
    return _PROBE["s"]


#: A look frame's cost, in units of a keyframe's of its size: it is read, placed, checked and
#: gathered from, but neither swept nor gathered for (146 look frames at 320x240 took 33 s beside
#: 64 keyframes' 51 s, planned at 65: 0.29 of a keyframe's planned cost each); its photo, depth
#: and mask stay in memory.
LOOK_SECONDS_SHARE = 0.3
LOOK_BYTES_PER_PIXEL = 40


@dataclass
class PassCost:
    """The pass estimator's expected cost on a survey."""

    seconds: float
    bytes: int
    megapixels: float      # every frame's pixels the estimator reads, in millions
    looks: int = 0         # ... of which look frames (core/io/looks.py)

    def summary(self) -> dict:
        return {"seconds": round(self.seconds, 1), "bytes": int(self.bytes), "megapixels": round(self.megapixels, 2),
                "looks": self.looks}


def pass_cost(sizes: list[tuple[int, int]], probe: Optional[float] = None, looks: int = 0,
              look_size: Optional[tuple[int, int]] = None) -> PassCost:
    """:class:`PassCost` of the frames of ``sizes`` ((width, height) each: every keyframe the
    estimator reads) and ``looks`` look frames of ``look_size``; ``probe``: :func:`probe_seconds`
    (measured here if not given)."""
    pixels = sum(w * h for w, h in sizes)
    look_px = looks * (look_size[0] * look_size[1] if look_size else 0)
    p = probe_seconds() if probe is None else probe
    return PassCost(p * UNITS_PER_MEGAPIXEL * (pixels + LOOK_SECONDS_SHARE * look_px) / 1e6,
                    int(BYTES_PER_PIXEL * pixels + LOOK_BYTES_PER_PIXEL * look_px), (pixels + look_px) / 1e6, looks)
