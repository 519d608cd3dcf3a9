"""Water benchmark: true colour under attenuation and backscatter, side by side.

    .venv/bin/python benchmarks/bench_water.py --out out/bench [--minutes 5] [--only runs|decisions|step]

* **runs**: on ``dive-water`` (green coastal water, ranges about 1.5-5 m, no caustics) plain 3DGS,
  3DGS with the water model, and the oracle (plain 3DGS on the true-colour images); on
  ``dive-water-networks`` (the same water with sharp caustic networks) also RecGS without and
  with the water; on ``dive-water-clear`` (clear ocean water, another seabed) the first three. Each run gets the same wall-clock limit, two at a time on one thread each.
  Scores: held-out PSNR of the true-colour render against the true colour (``clean/``), of the
  true-colour photos (``truecolour/``) where the run made them, Gaussians, steps, and the fitted
  coefficients against the generator's.
* **decisions**: what ``auto`` decides before training on every survey at hand, and why.
* **step**: seconds a training step takes with and without the water (the same model, blocks
  of steps alternated in one process).

Surveys come from benchmarks/bench_caustics.py (generated once into OUT/surveys).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_caustics import run_method, survey_dir  # noqa: E402

#: (survey, run name, method, extra options)
RUNS = [
    ("dive-water", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water", "oracle", "oracle", ["--medium", "off"]),
    ("dive-water-networks", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water-networks", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water-networks", "recgs", "recgs", ["--medium", "off"]),
    ("dive-water-networks", "recgs+water", "recgs", ["--medium", "auto"]),
    ("dive-water-networks", "oracle", "oracle", ["--medium", "off"]),
    ("dive-water-clear", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water-clear", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water-clear", "oracle", "oracle", ["--medium", "off"]),
]
DECISION_SURVEYS = ["dive-water", "dive-water-networks", "dive-water-clear", "dive-none", "dive-networks", "sample-none", "networks"]


def _rel_errors(fitted: dict, truth: dict) -> dict:
    pairs = {"attenuation": "attenuation_per_m", "backscatter": "backscatter_per_m", "veil": "veiling_light"}
    return {k: [round(abs(f - t) / t, 3) for f, t in zip(fitted[k], truth[v])] for k, v in pairs.items()}


def runs(out: Path, minutes: float) -> None:
    jobs = []
    for survey, name, method, extra in RUNS:
        scene = survey_dir(out, survey)
        jobs.append((survey, name, scene, out / "water" / survey / name, method, extra))
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda j: run_method(j[2], j[3], j[4], minutes, j[5], threads=1), jobs))
    rows = []
    for (survey, name, scene, _, _, _), m in zip(jobs, results):
        meta = json.loads((scene / "survey.json").read_text())
        med = m.get("medium") or {}
        row = {"survey": survey, "run": name, "psnr_true": m.get("psnr_test_gt"),
               "psnr_truecolour_photos": m.get("psnr_truecolour_gt"), "psnr_captured": m.get("psnr_test_captured"),
               "gaussians": m.get("gaussians"), "steps": m.get("iterations"), "seconds": m.get("seconds"),
               "water": med.get("reason")}
        if med.get("coefficients") and meta.get("water"):
            row["coefficient_errors"] = _rel_errors(med["coefficients"], meta["water"])
            row["coefficients"] = {k: [round(v, 4) for v in med["coefficients"][k]]
                                   for k in ("attenuation", "backscatter", "veil")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    (out / "water" / "runs.json").write_text(json.dumps(rows, indent=1))
    print("\n| survey | run | true colour, held-out (dB) | true-colour photos (dB) | Gaussians | steps |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"| {r['survey']} | {r['run']} | {f(r['psnr_true'])} | {f(r['psnr_truecolour_photos'])} | "
              f"{r['gaussians']:,} | {r['steps']:,} |")


def decisions(out: Path) -> None:
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer

    for name in DECISION_SURVEYS:
        scene = survey_dir(out, name)
        t = time.perf_counter()
        tr = make_trainer(scene, preset("default", medium="auto"))
        info = tr.medium_info
        print(json.dumps({"survey": name, "modelled": tr.medium is not None, "seconds": round(time.perf_counter() - t, 1),
                          "range_spread": round(info.get("range_spread", 0), 3), "prefit": info.get("prefit"),
                          "reason": info["reason"]}), flush=True)


def step_cost(out: Path, steps: int = 60, blocks: int = 4, grown=(600, 2500)) -> None:
    """Seconds a step with the water against without, on one model (dive-water, after each of
    ``grown`` plain steps, so the model has grown), blocks alternated."""
    import torch

    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer

    scene = survey_dir(out, "dive-water")
    tr = make_trainer(scene, preset("default", medium="on", eval_every=10**9))
    water = (tr.medium, tr.medium_optimizer)
    for until in grown:
        tr.medium, tr.medium_optimizer = None, None
        while tr.step < until:
            tr.train_step()
        times = {"water": [], "plain": []}
        for b in range(blocks):
            for name in ("plain", "water") if b % 2 == 0 else ("water", "plain"):
                tr.medium, tr.medium_optimizer = water if name == "water" else (None, None)
                t = time.perf_counter()
                for _ in range(steps):
                    tr.train_step()
                times[name].append((time.perf_counter() - t) / steps)
        w, p = sum(times["water"]) / blocks, sum(times["plain"]) / blocks
        print(json.dumps({"after_steps": until, "gaussians": int(tr.params["means"].shape[0]),
                          "threads": torch.get_num_threads(), "path": tr.compiler.compiled(),
                          "seconds_per_step_plain": round(p, 4), "seconds_per_step_water": round(w, 4),
                          "ratio": round(w / p, 3)}), flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--only", choices=("runs", "decisions", "step"), default=None)
    a = p.parse_args()
    if a.only in (None, "decisions"):
        decisions(a.out)
    if a.only in (None, "step"):
        step_cost(a.out)
    if a.only in (None, "runs"):
        runs(a.out, a.minutes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
