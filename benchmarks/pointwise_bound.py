"""How well can *any* per-point statistic of the photos recover a seabed point's colour?

    .venv/bin/python benchmarks/pointwise_bound.py [--samples 20000] [--noise 0.0,0.05]

A seabed point seen by n photos shows ``A * g_v`` in photo v: its albedo ``A`` (what the ground
truth shows, under the caustics' mean light) times that shot's caustic gain ``g_v`` (mean 1,
moving between shots). A colour estimator that looks at one point at a time (the mean of the
views, which an L2 fit makes; the median, which 3DGS's L1 loss makes; the minimum, the lower
envelope; a soft minimum) sees only the n samples ``g_v``, and a survey-wide gain restore can
fix only a common scale. This script draws the gains from the survey generator's own caustic
patterns (tools/survey_light.py: the three kinds of the caustic benchmark plus the sample's), at
random points and random shots (each shot has its own random offset, as in a survey), applies
each estimator, restores the best common scale (least squares), and prints the relative RMS
error ``rms(est / scale - 1)``: the part of the colour error no per-point method avoids.
``--noise`` adds log-normal photo noise (std in log units) to every sample.

No rendering, no training: a few seconds. The spatial structure of the light is what a
per-point estimator cannot use; benchmarks/RESULTS.md puts these figures beside the trained ones.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from survey_light import caustic_gain  # noqa: E402

#: (name, pattern, strength, tile (m), blur (m)): bench_caustics.py's kinds and the sample's.
PATTERNS = [
    ("networks", "voronoi", 0.9, 3.0, 0.03),
    ("ridges", "waves", 0.7, 3.0, 0.03),
    ("broad", "waves", 1.0, 12.0, 0.3),
    ("sample", "refraction", 0.45, 3.0, 0.03),
    ("weak", "refraction", 0.15, 3.0, 0.03),
]
SHOTS = 40


def estimators(s: np.ndarray) -> dict[str, np.ndarray]:
    """Per-point statistics of samples ``s`` (points, n)."""
    srt = np.sort(s, axis=1)
    w = np.exp(-(np.log(s) - np.log(srt[:, :1])) / 0.1)     # soft minimum, 0.1 log units
    return {"mean": s.mean(1), "median": np.median(s, 1), "min": srt[:, 0],
            "mean of lowest 2": srt[:, :2].mean(1), "soft min": (w * s).sum(1) / w.sum(1)}


def relative_rms(est: np.ndarray) -> float:
    scale = float((est * est).sum() / est.sum())   # the common scale that best maps est to 1
    return float(np.sqrt(np.mean((est / scale - 1.0) ** 2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=20000, help="points per (pattern, n) cell")
    ap.add_argument("--views", default="2,3,4,6", help="photos per point")
    ap.add_argument("--noise", default="0.0", help="photo noise (log std), comma separated")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    views = [int(v) for v in args.views.split(",")]
    print("relative RMS colour error after the best common scale (lower is better)")
    for name, kind, strength, tile, blur in PATTERNS:
        gains = np.stack([caustic_gain(kind, 256, float(i), tuple(rng.uniform(0, 1, 2)), 11, strength, blur / tile)
                          for i in range(SHOTS)]).reshape(SHOTS, -1)
        print(f"\n{name} ({kind}, strength {strength}, tile {tile} m): gain std {gains.std():.3f}")
        for noise in (float(x) for x in args.noise.split(",")):
            for n in views:
                pts = rng.integers(0, gains.shape[1], args.samples)
                shots = np.argsort(rng.random((args.samples, SHOTS)), axis=1)[:, :n]
                s = gains[shots, pts[:, None]] * np.exp(noise * rng.standard_normal((args.samples, n)))
                cells = "  ".join(f"{k} {relative_rms(v):.3f}" for k, v in estimators(s).items())
                print(f"  n={n} noise {noise}: {cells}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
