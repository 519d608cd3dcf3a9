"""Quality against size: a clean survey trained for a fixed time at several Gaussian budgets.

    .venv/bin/python benchmarks/bench_budget.py SCENE_DIR [--images clean] [--minutes 5]
        [--budgets auto,60000,20000,7000] [--densities mcmc,adc] [--no-compiler]

Each budget and density control runs ``python -m recgs_addon train SCENE --mode 3dgs
--max-minutes M --budget B --density D`` (one after another, in one invocation: compare the
rows with each other; ``mcmc`` is the default, ``adc`` the earlier one) and the table gives
held-out PSNR and SSIM against the captured held-out photos (the survey is clean, so they are
the ground truth), the Gaussians the run ended with, its steps and seconds, and steps per
second. ``--no-compiler`` hides every C++ compiler from the runs (an artist's machine:
numba's kernels where numba is installed, else eager torch). The runs share one compile cache
in a temporary folder, which the first run warms; ``--cold`` gives each run an empty one (each
starts on eager torch while numba's kernels load in the background).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--images", default=None, help="image folder of the survey to train on (e.g. clean)")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--budgets", default="auto,60000,20000,7000")
    ap.add_argument("--densities", default="mcmc", help="density controls to compare: mcmc, adc or both")
    ap.add_argument("--no-compiler", action="store_true")
    ap.add_argument("--cold", action="store_true", help="an empty compile cache for every run")
    ap.add_argument("--extra", default="", help="more trainer arguments, space separated")
    ap.add_argument("--keep", type=Path, default=None, help="keep each run's output folder here (metrics.json "
                    "holds its held-out PSNR history)")
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="recgs-budget-") as tmp:
        env = dict(os.environ, RECGS_CACHE_DIR=str(Path(tmp) / "cache"), PYTHONPATH=str(ROOT))
        if a.no_compiler:
            (Path(tmp) / "bin").mkdir()
            env["PATH"] = str(Path(tmp) / "bin")
            env.pop("CXX", None)
        for budget, dens in [(b, d) for b in a.budgets.split(",") for d in a.densities.split(",")]:
            out = (a.keep or Path(tmp)) / f"out-{budget}-{dens}"
            if a.cold:
                env["RECGS_CACHE_DIR"] = str(Path(tmp) / f"cache-{budget}-{dens}")
            cmd = [sys.executable, "-m", "recgs_addon", "train", str(a.scene), "--out", str(out), "--mode", "3dgs",
                   "--max-minutes", str(a.minutes), "--budget", budget, "--density", dens, "--checkpoint-every", "1e9"]
            cmd += ["--images", a.images] if a.images else []
            cmd += a.extra.split()
            res = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
            done = {}
            for line in res.stdout.splitlines():
                if line.startswith('{"event": "done"'):
                    done = json.loads(line)
            row = {"budget": budget, "density": dens, "rc": res.returncode, "psnr": done.get("psnr_test"), "ssim": done.get("ssim_test"),
                   "gaussians": done.get("gaussians"), "steps": done.get("iterations"), "seconds": done.get("seconds"),
                   "best_step": done.get("best_step")}
            if res.returncode:
                row["error"] = res.stderr.strip().splitlines()[-1:]
            rows.append(row)
            print(json.dumps(row), flush=True)
    f = lambda v, p=2: "-" if v is None else f"{v:.{p}f}"  # noqa: E731
    print(f"\n{a.scene} ({a.images or 'images'}), {a.minutes} min a run, "
          f"{'no compiler' if a.no_compiler else 'compiler available'}")
    print("| budget | density | held-out PSNR (dB) | SSIM | Gaussians | steps | seconds | steps/s | best step |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        sps = r["steps"] / r["seconds"] if r["steps"] and r["seconds"] else None
        print(f"| {r['budget']} | {r['density']} | {f(r['psnr'])} | {f(r['ssim'], 3)} | {r['gaussians']} | {r['steps']} | "
              f"{f(r['seconds'], 0)} | {f(sps)} | {r['best_step']} |")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
