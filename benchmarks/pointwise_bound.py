"""How well can *any* per-point statistic of the photos recover a seabed point's colour?

    .venv/bin/python benchmarks/pointwise_bound.py [--samples 20000] [--noise 0.0,0.05]
        [--views 2,3,4,6] [--patterns video] [--known-light] [--psnr-survey SURVEY]

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
sys.path.insert(0, str(ROOT))

from survey_light import caustic_gain  # noqa: E402

#: (name, pattern, strength, tile (m), blur (m)): bench_caustics.py's kinds and the sample's.
PATTERNS = [
    ("networks", "voronoi", 0.9, 3.0, 0.03),
    ("ridges", "waves", 0.7, 3.0, 0.03),
    ("broad", "waves", 1.0, 12.0, 0.3),
    ("sample", "refraction", 0.45, 3.0, 0.03),
    ("weak", "refraction", 0.15, 3.0, 0.03),
    ("video", "refraction", 0.8, 3.0, 0.03),    # bench_caustics' rows-video
]
SHOTS = 40
#: Bins of the light's log density that the ``known light`` estimator reads.
DENSITY_BINS = 400
#: Candidate levels a point's posterior is taken over.
LEVELS = 300


def estimators(s: np.ndarray, gains: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-point statistics of samples ``s`` (points, n); with ``gains`` (the light's own
    samples) also ``known light``, the best any per-point statistic can do (:func:`known_light`)."""
    srt = np.sort(s, axis=1)
    w = np.exp(-(np.log(s) - np.log(srt[:, :1])) / 0.1)     # soft minimum, 0.1 log units
    out = {"mean": s.mean(1), "median": np.median(s, 1), "min": srt[:, 0],
           "mean of lowest 2": srt[:, :2].mean(1), "soft min": (w * s).sum(1) / w.sum(1)}
    if gains is not None:
        out["known light"] = known_light(s, gains)
    return out


def known_light(s: np.ndarray, gains: np.ndarray, chunk: int = 2000) -> np.ndarray:
    """The posterior mean of each point's level given its samples ``s`` (points, n) and the
    light's exact distribution (a histogram of ``log gains``), under a flat prior on the log
    level: the photos are ``level * g`` with ``g`` drawn from that distribution, so in log units
    the level is a location parameter, and this estimator (Pitman's) has the least squared error
    of any that knows the light's distribution but not its value at the point."""
    lg = np.log(np.maximum(gains.ravel(), 1e-6))
    hist, edges = np.histogram(lg, bins=DENSITY_BINS)
    width = edges[1] - edges[0]
    logf = np.log(np.maximum(hist / (hist.sum() * width), 1e-12))
    x = np.log(s)
    out = np.empty(len(s))
    u = np.linspace(edges[0], edges[-1], LEVELS)        # log g of the lowest sample, candidates
    for a in range(0, len(s), chunk):
        xc = x[a:a + chunk]
        theta = xc.min(1, keepdims=True) - u[None, :]     # (points, levels) candidate log levels
        lgk = xc[:, :, None] - theta[:, None, :]          # (points, n, levels) each sample's log g
        b = np.clip(((lgk - edges[0]) / width).astype(int), 0, DENSITY_BINS - 1)
        ll = np.where((lgk >= edges[0]) & (lgk <= edges[-1]), logf[b], -np.inf).sum(1)
        ll -= ll.max(1, keepdims=True)
        p = np.exp(ll)
        out[a:a + chunk] = (p * np.exp(theta)).sum(1) / p.sum(1)
    return out


def relative_rms(est: np.ndarray) -> float:
    scale = float((est * est).sum() / est.sum())   # the common scale that best maps est to 1
    return float(np.sqrt(np.mean((est / scale - 1.0) ** 2)))


def psnr_per_error(survey: Path) -> float:
    """PSNR (dB) of ``survey``'s clean/ photos when every pixel's linear colour is off by a
    relative error of RMS 1 (the error then adds ``-20 log10(rms)``): what a relative colour
    error costs in sRGB on that seabed."""
    import torch

    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear

    sq = []
    for f in sorted((survey / "clean").glob("*.png")):
        lin = srgb_to_linear(torch.from_numpy(read_image(f)).double())
        # the sRGB change of a small relative change of the linear level, per unit of it
        e = 1e-4
        change = (linear_to_srgb(lin * (1 + e)) - linear_to_srgb(lin * (1 - e))) / (2 * e)
        sq.append(float((change ** 2).mean()))
    return float(-10 * np.log10(np.mean(sq)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=20000, help="points per (pattern, n) cell")
    ap.add_argument("--views", default="2,3,4,6", help="photos per point (independent looks at the light)")
    ap.add_argument("--noise", default="0.0", help="photo noise (log std), comma separated")
    ap.add_argument("--patterns", default=",".join(p[0] for p in PATTERNS), help="which patterns")
    ap.add_argument("--known-light", action="store_true",
                    help="add the best estimator that knows the light's distribution (slower)")
    ap.add_argument("--psnr-survey", type=Path, default=None,
                    help="a generated survey: also print each error as PSNR on its clean/ photos")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    views = [int(v) for v in args.views.split(",")]
    shots_n = max(SHOTS, max(views))
    base = psnr_per_error(args.psnr_survey) if args.psnr_survey else None
    print("relative RMS colour error after the best common scale (lower is better)"
          + (f"; [dB]: as PSNR on {args.psnr_survey.name}'s clean photos" if base is not None else ""))
    for name, kind, strength, tile, blur in PATTERNS:
        if name not in args.patterns.split(","):
            continue
        gains = np.stack([caustic_gain(kind, 256, float(i), tuple(rng.uniform(0, 1, 2)), 11, strength, blur / tile)
                          for i in range(shots_n)]).reshape(shots_n, -1)
        print(f"\n{name} ({kind}, strength {strength}, tile {tile} m): gain std {gains.std():.3f}")
        for noise in (float(x) for x in args.noise.split(",")):
            noisy = gains * np.exp(noise * rng.standard_normal(gains.shape)) if args.known_light else None
            for n in views:
                pts = rng.integers(0, gains.shape[1], args.samples)
                shots = np.argsort(rng.random((args.samples, shots_n)), axis=1)[:, :n]
                s = gains[shots, pts[:, None]] * np.exp(noise * rng.standard_normal((args.samples, n)))
                cells = []
                for k, v in estimators(s, noisy).items():
                    e = relative_rms(v)
                    cells.append(f"{k} {e:.3f}" + (f" [{base - 20 * np.log10(e):.1f}]" if base is not None else ""))
                print(f"  n={n} noise {noise}: " + "  ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
