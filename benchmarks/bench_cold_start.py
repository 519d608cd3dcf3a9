"""Time to the first training step, and what a short run reaches, from a cold start.

    .venv/bin/python benchmarks/bench_cold_start.py [SCENE_DIR] [--iterations 600] [--cases ...]

Each case runs ``python -m recgs_addon train`` as a new user would, in its own empty
``RECGS_CACHE_DIR`` (so torch.compile's cache is cold) and prints, from the job's JSON lines:
seconds from launch to the first step, to the last step, steps per second over the run, the
step at which the compiled path took over, held-out PSNR against the captured photos (and
against ground truth where the survey has it) and the Gaussian count.

Cases:
  no-compiler   PATH holds no C++ compiler (and CXX is unset), empty caches: numba's path (eager at once
                while a background process fills numba's cold cache, then numba)
  no-compiler-warm  the same on the cache no-compiler left behind (numba from the first step)
  auto-cold     a compiler, numba refused (RECGS_NUMBA=0): eager at once, a background warm-up, then compiled
  compile-first the behaviour before the switch: compile (cold) before the first step (RECGS_NUMBA=0)
  auto-warm     the same, on the cache auto-cold left behind (warm-up run first)
  eager         --eager

All cases run one after another in one invocation (the machine is shared: compare them with
each other, not with figures from another run). Same seed, same iteration count: the PSNRs
differ only by float32 rounding between the paths and by the order of work.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = ("no-compiler", "no-compiler-warm", "auto-cold", "compile-first", "auto-warm", "eager")


def run_case(case: str, scene: Path, iterations: int, work: Path) -> dict:
    shared = {"auto-cold": "cache-auto", "auto-warm": "cache-auto", "no-compiler-warm": "cache-no-compiler"}
    cache = work / shared.get(case, f"cache-{case}")
    if case in ("auto-cold", "no-compiler") and cache.exists():
        shutil.rmtree(cache)
    env = dict(os.environ, RECGS_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    for var in ("TORCHINDUCTOR_CACHE_DIR", "NUMBA_CACHE_DIR", "RECGS_NUMBA"):
        env.pop(var, None)
    if case.startswith("auto") or case == "compile-first":   # torch.compile's path (numba is the default)
        env["RECGS_NUMBA"] = "0"
    if case.startswith("no-compiler"):
        empty = work / "empty-bin"
        empty.mkdir(exist_ok=True)
        env["PATH"] = str(empty)
        env.pop("CXX", None)
    if case == "no-compiler-warm":   # finish the warm-up no-compiler started (killed at its end), or run alone
        subprocess.run([sys.executable, "-m", "recgs_addon.core.train.compiling", "--numba"], env=env,
                       check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if case == "auto-warm":   # finish the warm-up the cold run started (it is killed at the run's end)
        subprocess.run([sys.executable, "-m", "recgs_addon.core.train.compiling"], env=env, check=True,
                       cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out = work / f"out-{case}"
    cmd = [sys.executable, "-m", "recgs_addon", "train", str(scene), "--out", str(out),
           "--iterations", str(iterations), "--checkpoint-every", "1e9"]
    cmd += {"eager": ["--eager"], "compile-first": ["--compile-first"]}.get(case, [])
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    first = last = None
    switched = switched_s = None
    path = None
    done = {}
    for line in proc.stdout:
        if not line.startswith("{"):
            continue
        ev = json.loads(line)
        now = time.perf_counter() - t0
        if ev.get("event") == "progress" and ev.get("iteration", 0) >= 1:
            first = first if first is not None else now
            last = now
        if ev.get("event") == "compile" and "from step" in ev.get("message", ""):
            switched, switched_s = ev.get("iteration"), now
            path = "numba" if "numba" in ev["message"] else "compiled"
        if ev.get("event") == "done":
            done = ev
    proc.wait()
    total = time.perf_counter() - t0
    state = (done.get("compile") or {})
    if switched is None and state.get("state") == "compiled":
        path = "compiled"
    elif switched is None and state.get("numba") == "ready":
        path = "numba"
    return {"case": case, "first_step_s": first, "run_s": done.get("seconds"), "total_s": total,
            "steps": done.get("iterations"), "switched_at": switched, "switched_s": switched_s, "fast_path": path,
            "psnr": done.get("psnr_test"), "psnr_gt": done.get("psnr_test_gt"), "gaussians": done.get("gaussians"),
            "rc": proc.returncode}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", type=Path, default=ROOT / "data" / "sample")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--cases", default=",".join(CASES))
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="recgs-cold-") as tmp:
        for case in a.cases.split(","):
            r = run_case(case, a.scene, a.iterations, Path(tmp))
            rows.append(r)
            print(json.dumps(r), flush=True)
    f = lambda v, p=1: "-" if v is None else f"{v:.{p}f}"  # noqa: E731
    print(f"\n{a.scene}, {a.iterations} steps, torch threads as default")
    print("| case | first step (s) | training (s) | whole job (s) | steps/s | fast path | from step | at (s) | "
          "held-out PSNR (dB) | vs ground truth (dB) | Gaussians |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        sps = r["steps"] / r["run_s"] if r["steps"] and r["run_s"] else None
        from_step = r['switched_at'] if r['switched_at'] is not None else (1 if r['fast_path'] else '-')
        print(f"| {r['case']} | {f(r['first_step_s'])} | {f(r['run_s'])} | {f(r['total_s'])} | {f(sps, 2)} | "
              f"{r['fast_path'] or 'eager'} | {from_step} | {f(r.get('switched_s'))} | {f(r['psnr'], 2)} | "
              f"{f(r['psnr_gt'], 2)} | {r['gaussians']} |")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
