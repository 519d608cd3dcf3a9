"""Caustic-removal benchmark: generate surveys with ground truth, run every method through the
job runner, write one table and one PSNR-against-time plot per survey.

    .venv/bin/python benchmarks/bench_caustics.py --out out/bench [--quick] [--surveys sample,large]

Surveys (generated once with tools/make_survey.py into OUT/surveys, reused afterwards):

* ``sample``: the bundled data/sample (24 views, 256x192, refraction caustics, strength 0.45);
* ``networks``: 32 views at 320x240, sharp light networks (voronoi edges), strength 0.9;
* ``ridges``: 32 views at 320x240, sharp moving ridges (waves), strength 0.7;
* ``broad``: 32 views at 320x240, broad low-frequency waves (a 12 m tile, softened), strength 1.0;
* ``large``: 32 views at 320x240, another seed and the ``waves`` pattern;
* ``mild``: 32 views at 320x240, light networks (voronoi) at strength 0.35 (photos about 27 dB
  from ground truth, the regime of the field surveys the quality goals were set on);
* ``weak``: 24 views, strength 0.15; ``none``: 24 views without caustics;
* ``dense`` (not in the default list): 48 views with 85 % / 80 % overlap, so each point is
  seen by about three times as many photos as in the sample.

The ``dive-*`` kinds are video-like: 144 frames in six overlapping rows (``dive-wander`` along a
wandering track), a median of about ten training views a point, caustics drifting smoothly with
time (``networks``, ``mild``, ``broad`` as above); ``dive-none`` is ``dive-networks``'s frames
without caustics (its ground truth as the photos), ``sample-none`` the same of ``sample``.

Every survey but the sample has a seed of its own. Methods: ``3dgs``, ``filter2d``, ``joint``,
``oracle`` (plain 3DGS on the clean images), ``recgs`` (the defaults: k from the residual
spectrum, additive, the best held-out model kept), ``recgs-last`` (the same ending with its
last model, as before keep_best), ``recgs-trim`` (robust trimming k = 1.5 with the gain
restore), ``recgs-consensus`` (C from the multi-view consensus of the photos), and the comparisons
``recgs-k9`` (the paper's fixed 9x9 block) and ``recgs-mult`` (multiplicative caustic model), run where
``--refinements`` lists the survey. Each run gets the same wall-clock limit on its survey.
Runs whose metrics.json exists are not repeated (delete the folder to redo one).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recgs_addon.core.outputs.report import write_benchmark_report  # noqa: E402

SURVEYS = {
    "sample": None,
    "networks": ["--views", "32", "--width", "320", "--height", "240", "--seed", "11", "--caustic-pattern", "voronoi",
                 "--caustic-strength", "0.9"],
    "ridges": ["--views", "32", "--width", "320", "--height", "240", "--seed", "12", "--caustic-pattern", "waves",
               "--caustic-strength", "0.7"],
    "broad": ["--views", "32", "--width", "320", "--height", "240", "--seed", "13", "--caustic-pattern", "waves",
              "--caustic-scale", "12", "--caustic-blur", "0.3", "--caustic-strength", "1.0"],
    "large": ["--views", "32", "--width", "320", "--height", "240", "--seed", "7", "--caustic-pattern", "waves"],
    "mild": ["--views", "32", "--width", "320", "--height", "240", "--seed", "21", "--caustic-pattern", "voronoi",
             "--caustic-strength", "0.35"],
    "weak": ["--views", "24", "--seed", "3", "--caustic-strength", "0.15"],
    "none": ["--views", "24", "--seed", "4", "--caustic-strength", "0"],
    # each seafloor point in ~3x as many photos (the caustics' mean over the photos that see a
    # point is what no consistency-based method can tell from texture; see benchmarks/RESULTS.md#caustics-benchmark-four-surveys)
    "dense": ["--views", "48", "--seed", "1", "--overlap", "0.85", "--sidelap", "0.8"],
}
# Dive-like surveys: 144 frames along six overlapping rows (85 % forward, 70 % side overlap), each
# seabed point in a median of about ten training views, and the caustics drifting smoothly from
# frame to frame, 0.33 s apart, as in a video (neighbouring frames share much of their light).
DIVE = ["--views", "144", "--width", "320", "--height", "240", "--lines", "6", "--overlap", "0.85",
        "--sidelap", "0.7", "--caustic-motion", "smooth", "--caustic-dt", "0.33"]
SURVEYS.update({
    "dive-networks": DIVE + ["--seed", "32", "--caustic-pattern", "voronoi", "--caustic-strength", "0.9",
                             "--save-depth"],
    "dive-mild": DIVE + ["--seed", "31", "--caustic-pattern", "voronoi", "--caustic-strength", "0.35"],
    "dive-broad": DIVE + ["--seed", "33", "--caustic-pattern", "waves", "--caustic-scale", "12",
                          "--caustic-blur", "0.3", "--caustic-strength", "1.0"],
    "dive-wander": DIVE + ["--seed", "35", "--path", "wander", "--caustic-pattern", "voronoi",
                           "--caustic-strength", "0.6"],
})
# Dive surveys behind green coastal water (tools/survey_water.py): the diver rises and sinks
# between about 1.6 and 3.8 m above the seabed, so ranges run from about 1.5 to 5 m and every
# point is seen from several; clean/ holds the true colour (no water, the caustics' mean light).
WATER = ["--water", "coastal", "--altitude", "2.7", "--altitude-swing", "1.1", "--save-depth"]
SURVEYS.update({
    "dive-water": DIVE + WATER + ["--seed", "41", "--caustic-strength", "0"],
    "dive-water-networks": DIVE + WATER + ["--seed", "42", "--caustic-pattern", "voronoi",
                                           "--caustic-strength", "0.9"],
    "dive-water-clear": DIVE + ["--water", "clear", "--altitude", "2.7", "--altitude-swing", "1.1",
                                "--save-depth", "--seed", "43", "--caustic-strength", "0"],
})
# Surveys flown level at one altitude (a diver or a robot keeping its height over lawnmower rows),
# the camera pitched 15 degrees forward: each seabed point is seen from ranges that differ by the
# field of view only (about x1.3), the range changes mostly across the image and from point to
# point. A sandy seabed in green coastal water; a reef-like one (60 rocks: relief, texture and
# occlusion) in green coastal water, in clear ocean water, in the coastal water with caustic
# networks, and in the clear water under a softer wave pattern of light.
LEVEL = DIVE + ["--altitude", "3.0", "--pitch", "15", "--save-depth"]
REEF = LEVEL + ["--rocks", "60"]
SURVEYS.update({
    "level-water": LEVEL + ["--water", "coastal", "--seed", "61", "--caustic-strength", "0"],
    "level-reef-water": REEF + ["--water", "coastal", "--seed", "64", "--caustic-strength", "0"],
    "level-reef-clear": REEF + ["--water", "clear", "--seed", "62", "--caustic-strength", "0"],
    "level-reef-networks": REEF + ["--water", "coastal", "--seed", "63", "--caustic-pattern", "voronoi",
                                   "--caustic-strength", "0.9"],
    "level-reef-clear-waves": REEF + ["--water", "clear", "--seed", "66", "--caustic-pattern", "waves",
                                      "--caustic-strength", "0.8"],
})
# The reef flown lower and looking further ahead (2.6 m up, pitched 38 degrees: ranges about
# 2.7-5.8 m) behind a green coastal water whose veil is bright and builds up slowly (attenuation
# 0.50 / 0.12 / 0.18 per m, backscatter 0.40 / 0.18 / 0.22, veil 0.03 / 0.20 / 0.22): the veil's
# growth with range and the attenuation trade against each other over the ranges one altitude
# gives. Without caustics and under light networks.
GREEN = DIVE + ["--altitude", "2.6", "--pitch", "38", "--save-depth", "--rocks", "60", "--water", "coastal",
                "--water-attenuation", "0.50,0.12,0.18", "--water-backscatter", "0.40,0.18,0.22",
                "--water-colour", "0.03,0.20,0.22"]
SURVEYS.update({
    "level-reef-green": GREEN + ["--seed", "67", "--caustic-strength", "0"],
    "level-reef-green-networks": GREEN + ["--seed", "68", "--caustic-pattern", "voronoi", "--caustic-strength", "0.9"],
})
# Lawnmower rows that cross each seabed point only two or three times, as most divers and
# robots shoot: 64 frames in six rows with 65 % side overlap (each point in about six frames of
# each of two or three rows), frames a third of a second apart, sharp light networks drifting
# as a shallow reef's do; the generator's depth saved for the estimators' bounds.
ROWS = ["--views", "64", "--width", "320", "--height", "240", "--lines", "6", "--overlap", "0.85",
        "--sidelap", "0.65", "--caustic-motion", "smooth", "--caustic-dt", "0.33", "--save-depth"]
SURVEYS.update({
    "rows-networks": ROWS + ["--seed", "71", "--caustic-pattern", "voronoi", "--caustic-strength", "0.9"],
    # ... filmed as a video under light refracted by a rippled surface, which forgets itself in
    # about a tenth of a second (the README's survey's light): three frames between two
    # keyframes (12 frames a second) rendered as look frames with their true poses (looks/,
    # looks.json), which the caustic estimator gathers light from; training keeps the 64 keyframes
    "rows-looks": ROWS + ["--seed", "72", "--caustic-pattern", "refraction", "--caustic-strength", "0.8",
                          "--look-frames", "3"],
    # ... the same rows without look frames (the sand and a few rocks: little relief), and over a
    # reef (60 rocks): the bases tools/relight_survey.py puts lamps and waters over
    "rows-72": ROWS + ["--seed", "72", "--caustic-pattern", "refraction", "--caustic-strength", "0.8"],
    # ... filmed at a diver's pace: a keyframe a second (15 % of the footprint) and five video
    # frames between two (6 frames a second), so each seabed point stays in view for several
    # seconds of light that forgets itself in a fifth of one: the keyframes alone see a point
    # under a few lights, the video under many more
    "rows-video": ROWS + ["--seed", "74", "--caustic-pattern", "refraction", "--caustic-strength", "0.8",
                          "--caustic-dt", "1.0", "--look-frames", "5"],
    "rows-reef": ROWS + ["--seed", "73", "--rocks", "60", "--caustic-pattern", "refraction",
                         "--caustic-strength", "0.8"],
})
# A dive survey in deep water lit by a lamp on the camera (tools/survey_lamp.py): no sunlight
# caustics; clean/ holds the seabed under even light.
SURVEYS.update({
    "dive-lamp": DIVE + ["--seed", "51", "--caustic-strength", "0", "--lamp"],
    # ... and a lamp in green coastal water, the diver rising and sinking: the lamp's light
    # attenuated on its way to the seabed as on its way back
    "dive-lamp-water": DIVE + WATER + ["--seed", "52", "--caustic-strength", "0", "--lamp"],
})
# The hard cases real footage brings: a tiled floor seen forward and down (pitched 45 degrees,
# the horizon in view: repetitive texture, grazing views, open water) with a time stamp burned
# in, under light networks and without; a grid of bars on a wet, glossy floor (highlights that
# follow the view) with the stamp, no caustics.
HARD = ["--views", "48", "--width", "320", "--height", "240", "--lines", "3", "--overlap", "0.8",
        "--caustic-motion", "smooth", "--caustic-dt", "0.5", "--overlay", "--rocks", "3"]
SURVEYS.update({
    "tiles-networks": HARD + ["--seed", "81", "--floor", "tiles", "--pitch", "45", "--caustic-pattern", "voronoi",
                              "--caustic-strength", "0.7"],
    "tiles-none": HARD + ["--seed", "82", "--floor", "tiles", "--pitch", "45", "--caustic-strength", "0"],
    "grid-gloss-none": HARD + ["--seed", "83", "--floor", "grid", "--gloss", "0.8", "--pitch", "25",
                               "--caustic-strength", "0"],
})
# Every method on one density control (adc, the caustic modes' default; plain 3DGS alone
# defaults to mcmc), so that a method's score is the method's, not its densification's.
METHODS = {
    "3dgs": ["--mode", "3dgs", "--density", "adc"],
    "filter2d": ["--mode", "filter2d"],
    "joint": ["--mode", "joint"],
    "oracle": ["--mode", "oracle"],
    "recgs": ["--mode", "recgs"],
    "recgs-last": ["--mode", "recgs", "--keep-last"],
    "recgs-trim": ["--mode", "recgs", "--robust-k", "1.5"],
    "recgs-consensus": ["--mode", "recgs", "--estimator", "consensus"],
    "recgs-passes": ["--mode", "recgs", "--estimator", "passes"],
    "recgs-floor": ["--mode", "recgs", "--pass-statistic", "floor"],
    "recgs-min1": ["--mode", "recgs", "--pass-min", "1"],
    "recgs-lowpass": ["--mode", "recgs", "--estimator", "lowpass", "--fit-loss", "l1"],
    "recgs-likelihood": ["--mode", "recgs", "--estimator", "likelihood"],
    "recgs-lf": ["--mode", "recgs", "--estimator", "lightfield", "--fit-loss", "l1"],
    "recgs-l2": ["--mode", "recgs", "--estimator", "lowpass", "--fit-loss", "l2"],
    "recgs-lf-l2": ["--mode", "recgs", "--estimator", "lightfield", "--fit-loss", "l2"],
    "recgs-k9": ["--mode", "recgs", "--caustic-k", "9"],
    "recgs-mult": ["--mode", "recgs", "--caustic-model", "multiplicative"],
    "recgs-nolooks": ["--mode", "recgs", "--looks", "off"],
}
#: The estimators kept for comparisons (benchmarks/caustic_estimators), run through its train command.
ADDED = ("consensus", "likelihood", "lightfield")


# Surveys without caustics made from another survey's ground truth: the same frames and cameras
# with the clean images as the photos (no rendering needed; "no harm" is measured on the very
# seabed the caustic runs see).
CLEAN_OF = {"dive-none": "dive-networks", "sample-none": "sample", "rows-none": "rows-networks"}


def survey_dir(out: Path, name: str) -> Path:
    if name in CLEAN_OF:
        src = survey_dir(out, CLEAN_OF[name]).resolve()
        d = out / "surveys" / name
        if not (d / "sparse").exists():
            d.mkdir(parents=True, exist_ok=True)
            for link, target in (("images", "clean"), ("clean", "clean"), ("sparse", "sparse"),
                                 ("frames.json", "frames.json")):
                if (src / target).exists() and not (d / link).exists():
                    (d / link).symlink_to(src / target)
        return d
    if SURVEYS[name] is None:
        return ROOT / "data" / name
    d = out / "surveys" / name
    if not (d / "sparse").is_dir():
        t = time.perf_counter()
        subprocess.run([sys.executable, str(ROOT / "tools" / "make_survey.py"), "--out", str(d), *SURVEYS[name]],
                       check=True, stdout=subprocess.DEVNULL)
        print(f"generated {name} in {time.perf_counter() - t:.0f} s", flush=True)
    return d


def run_method(scene: Path, out: Path, method: str, minutes: float, extra: list[str], threads: int = 0) -> dict:
    """Run one method on one survey through the job runner (skipped where its metrics exist), on
    ``threads`` threads (0: the machine's default)."""
    metrics = out / "metrics.json"
    if metrics.is_file():
        return json.loads(metrics.read_text())
    args = METHODS[method]
    # the estimators kept for comparisons run through the train command that adds them
    runner = "benchmarks.caustic_estimators" if any(a in ADDED for a in args) else "recgs_addon"
    cmd = [sys.executable, "-m", runner, "train", str(scene), "--out", str(out),
           "--max-minutes", str(minutes), *args, *extra]
    t = time.perf_counter()
    env = dict(os.environ)
    if threads:
        env.update({k: str(threads) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS")})
    proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"{method} on {scene} failed:\n{proc.stderr[-2000:]}")
    m = json.loads(metrics.read_text())
    print(f"{scene.name:8s} {method:12s} {m.get('psnr_test_gt', float('nan')):6.2f} dB held-out (gt), "
          f"{m['seconds']:6.1f} s, {m['gaussians']} Gaussians, wall {time.perf_counter() - t:.0f} s, "
          f"train decaustic {m.get('psnr_decaustic_gt')}, {m['reason']}", flush=True)
    return m


def _clean(survey: str) -> bool:
    """A survey without caustics (its photos are the ground truth)."""
    return survey == "none" or survey in CLEAN_OF


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--surveys", default="networks,ridges,broad,mild,weak,none")  # any of SURVEYS, CLEAN_OF
    p.add_argument("--methods", default="3dgs,oracle,recgs,recgs-last,recgs-trim,recgs-consensus")
    p.add_argument("--refinements", default="sample", help="surveys that also run recgs-k9, recgs-mult")
    p.add_argument("--minutes", type=float, default=5.0, help="wall-clock limit per run (the quality goals are stated for 5)")
    p.add_argument("--large-minutes", type=float, default=5.0, help="wall-clock limit per run on 'large'")
    p.add_argument("--quick", action="store_true", help="downscale 2 and 0.5 min per run (smoke test)")
    p.add_argument("--extra", default="", help="more runner options for every run, space separated")
    p.add_argument("--jobs", type=int, default=1,
                   help="runs at once, each on cores / jobs threads (the same for every method)")
    args = p.parse_args(argv)
    surveys = [s for s in args.surveys.split(",") if s]
    refine = set(args.refinements.split(","))
    results: dict = {}
    extra = args.extra.split()
    if args.quick:
        extra += ["--downscale", "2"]
    threads = max(1, (os.cpu_count() or 1) // args.jobs) if args.jobs > 1 else 0
    runs = []
    for s in surveys:
        scene = survey_dir(args.out, s)
        methods = [m for m in args.methods.split(",") if m]
        if s in refine:
            methods += ["recgs-k9", "recgs-mult"]
        if _clean(s):  # oracle is 3dgs here; the question is only whether recgs stays out of the way
            methods = [m for m in methods if m != "oracle"]
        minutes = 0.5 if args.quick else (args.large_minutes if s == "large" else args.minutes)
        results[s] = {}
        runs += [(s, m, scene, minutes) for m in methods]
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = {(s, m): pool.submit(run_method, scene, args.out / s / m, m, minutes, extra, threads)
                for s, m, scene, minutes in runs}
        for (s, m), f in done.items():
            results[s][m] = f.result()
    for s in surveys:
        if _clean(s) and "3dgs" in results[s]:
            results[s]["oracle"] = results[s]["3dgs"]
    all_methods = list(METHODS)
    path = write_benchmark_report(args.out, surveys, [m for m in all_methods if any(m in r for r in results.values())],
                                  results)
    (args.out / "benchmark.json").write_text(json.dumps(
        {s: {m: {k: v for k, v in r.items() if k not in ("config",)} for m, r in rs.items()}
         for s, rs in results.items()}, indent=1))
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
