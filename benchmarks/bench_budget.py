"""Quality against size: a clean survey trained for a fixed time at several Gaussian budgets.

    .venv/bin/python benchmarks/bench_budget.py SCENE_DIR [--images clean] [--minutes 5]
        [--budgets auto,60000,20000,7000] [--no-compiler]

Each budget runs ``python -m recgs_addon train SCENE --mode 3dgs --max-minutes M --budget B``
(one after another, in one invocation: compare the rows with each other) and the table gives
held-out PSNR and SSIM against the captured held-out photos (the survey is clean, so they are
the ground truth), the Gaussians the run ended with, its steps and seconds, and steps per
second. ``--no-compiler`` hides every C++ compiler from the runs (an artist's machine: the
eager path throughout); otherwise the runs share one per-user compile cache in a temporary
folder (the first run warms it).
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
    ap.add_argument("--no-compiler", action="store_true")
    ap.add_argument("--extra", default="", help="more trainer arguments, space separated")
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="recgs-budget-") as tmp:
        env = dict(os.environ, RECGS_CACHE_DIR=str(Path(tmp) / "cache"), PYTHONPATH=str(ROOT))
        if a.no_compiler:
            (Path(tmp) / "bin").mkdir()
            env["PATH"] = str(Path(tmp) / "bin")
            env.pop("CXX", None)
        for budget in a.budgets.split(","):
            out = Path(tmp) / f"out-{budget}"
            cmd = [sys.executable, "-m", "recgs_addon", "train", str(a.scene), "--out", str(out), "--mode", "3dgs",
                   "--max-minutes", str(a.minutes), "--budget", budget, "--checkpoint-every", "1e9"]
            cmd += ["--images", a.images] if a.images else []
            cmd += a.extra.split()
            res = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
            done = {}
            for line in res.stdout.splitlines():
                if line.startswith('{"event": "done"'):
                    done = json.loads(line)
            row = {"budget": budget, "rc": res.returncode, "psnr": done.get("psnr_test"), "ssim": done.get("ssim_test"),
                   "gaussians": done.get("gaussians"), "steps": done.get("iterations"), "seconds": done.get("seconds"),
                   "best_step": done.get("best_step")}
            if res.returncode:
                row["error"] = res.stderr.strip().splitlines()[-1:]
            rows.append(row)
            print(json.dumps(row), flush=True)
    f = lambda v, p=2: "-" if v is None else f"{v:.{p}f}"  # noqa: E731
    print(f"\n{a.scene} ({a.images or 'images'}), {a.minutes} min a run, "
          f"{'no compiler' if a.no_compiler else 'compiler available'}")
    print("| budget | held-out PSNR (dB) | SSIM | Gaussians | steps | seconds | steps/s | best step |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        sps = r["steps"] / r["seconds"] if r["steps"] and r["seconds"] else None
        print(f"| {r['budget']} | {f(r['psnr'])} | {f(r['ssim'], 3)} | {r['gaussians']} | {r['steps']} | "
              f"{f(r['seconds'], 0)} | {f(sps)} | {r['best_step']} |")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
