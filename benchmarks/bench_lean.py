"""A lean model side by side: the same training with and without significance pruning.

    .venv/bin/python benchmarks/bench_lean.py SURVEY:MODE [SURVEY:MODE ...] [--minutes 5]
        [--out out/bench_lean] [--before "--prune-weight 0"] [--after ""]

For each survey (a COLMAP survey folder, scored against its ``clean/`` photos where it has
them) and mode, runs ``python -m recgs_addon train`` twice at the same time, one thread each
(``--before``'s extra arguments and ``--after``'s: by default significance pruning off and at
its default), and prints for each run: held-out PSNR against the ground truth (or the photos),
Gaussians, steps, steps a second over the last 60 s of training (from the progress lines), the
exported PLY's size, the view-support median (training views that carry a Gaussian) and the
Gaussians removed as needless. The two runs of a pair share the machine, so their ratio is
what to read; one pair at a time.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def steps_per_second(events: list, last_s: float = 60.0) -> float:
    """Steps a second over the last ``last_s`` seconds of training, from progress events."""
    prog = [e for e in events if e.get("event") == "progress" and "elapsed" in e]
    if len(prog) < 2:
        return float("nan")
    end = prog[-1]
    start = next((e for e in prog if e["elapsed"] >= end["elapsed"] - last_s), prog[0])
    dt = end["elapsed"] - start["elapsed"]
    return (end["iteration"] - start["iteration"]) / dt if dt > 0 else float("nan")


def summary(out: Path, events: list) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    ply = out / "point_cloud.ply"
    psnr = m.get("psnr_test_gt") if m.get("psnr_test_gt") is not None else m.get("psnr_test")
    return {"psnr": psnr, "gaussians": m["gaussians"], "steps": m["iterations"],
            "steps_per_s": steps_per_second(events), "ply_mb": ply.stat().st_size / 1e6 if ply.exists() else float("nan"),
            "support": (m.get("view_support") or {}).get("median_views"),
            "needless": (m.get("density") or {}).get("needless", 0)}


def run_pair(survey: Path, mode: str, minutes: float, out: Path, variants: dict) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    procs = {}
    for name, extra in variants.items():
        dest = out / f"{survey.name}-{mode}-{name}"
        cmd = [sys.executable, "-m", "recgs_addon", "train", str(survey), "--out", str(dest), "--mode", mode,
               "--max-minutes", str(minutes), *shlex.split(extra)]
        procs[name] = (dest, subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                              stderr=subprocess.DEVNULL, text=True))
    results = {}
    for name, (dest, p) in procs.items():
        stdout, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"{survey} {mode} {name}: train exited {p.returncode}")
        events = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
        results[name] = summary(dest, events)
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="SURVEY:MODE")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_lean")
    ap.add_argument("--before", default="--prune-weight 0")
    ap.add_argument("--after", default="")
    args = ap.parse_args(argv)
    variants = {"before": args.before, "after": args.after}
    print(f"| survey, mode | run | held-out dB | Gaussians | steps | steps/s, last 60 s | PLY MB | view support | needless |")
    print("|---|---|---|---|---|---|---|---|---|")
    for spec in args.runs:
        survey, _, mode = spec.rpartition(":")
        res = run_pair(Path(survey), mode or "3dgs", args.minutes, args.out, variants)
        for name, r in res.items():
            print(f"| `{Path(survey).name}`, {mode} | {name} ({variants[name] or 'defaults'}) | {r['psnr']:.2f} | "
                  f"{r['gaussians']:,} | {r['steps']:,} | {r['steps_per_s']:.2f} | {r['ply_mb']:.1f} | "
                  f"{r['support']} | {r['needless']:,} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
