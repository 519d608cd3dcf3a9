"""Surveys of an artist's size: hundreds of photos of 1600x1200 or 24 MP, memory and time.

    .venv/bin/python benchmarks/bench_survey_size.py [--views 100,300,500] [--width 1600] [--minutes 10]
        [--device cpu] [--mode 3dgs] [--out out/bench/size] [--survey SURVEY]

For each view count a survey is generated once (tools/make_survey.py at 320x240 without
ground truth, a lawnmower over a wider seabed; OUT/surveys/svN) and its photos scaled to
``--width`` as JPEG (benchmarks/scale_survey.py; OUT/surveys/svN_W). Then ``python -m
recgs_addon train`` runs on it with the defaults and ``--max-minutes``, its resident memory
(the process and its children) sampled every half second, and the benchmark prints:

* the plan the job printed before training (resolution, memory estimate, seconds per 1,000 steps),
* seconds from the command to the first step (decoding every photo included),
* peak resident memory, against the plan's estimates (to start, and with the model at its budget),
* steps per minute once training, the final Gaussian count and held-out PSNR (against the
  held-out photos: these surveys have no ground truth).

Results go to OUT/size.json and OUT/size.md. Upscaled 320x240 renders have less detail than
real photos; the figures are for memory and time, not quality.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from scale_survey import scale_survey  # noqa: E402


def tree_rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` and its descendants (Linux /proc), MB."""
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * 4096
            with open(f"/proc/{p}/task/{p}/children") as f:
                todo += [int(c) for c in f.read().split()]
        except (OSError, ValueError):
            continue
    return total / 2 ** 20


def generate(out: Path, views: int, seed: int, width: int = 320) -> Path:
    d = out / "surveys" / f"sv{views}" if width == 320 else out / "surveys" / f"sv{views}_from{width}"
    if not (d / "sparse").is_dir():
        lines = max(3, round((views / 12) ** 0.5))
        cmd = [sys.executable, str(ROOT / "tools" / "make_survey.py"), "--out", str(d), "--views", str(views),
               "--width", str(width), "--height", str(width * 3 // 4), "--seed", str(seed), "--lines", str(lines), "--overlap", "0.8",
               "--sidelap", "0.6", "--no-clean", "--points", "20000"]
        t = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        print(f"generated {views} views in {time.perf_counter() - t:.0f} s", flush=True)
    return d


def run(scene: Path, out: Path, minutes: float, device: str, mode: str) -> dict:
    cmd = [sys.executable, "-m", "recgs_addon", "train", str(scene), "--out", str(out), "--mode", mode,
           "--max-minutes", str(minutes), "--device", device]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    peak = [0.0]
    stop = threading.Event()

    def watch():
        while not stop.is_set():
            peak[0] = max(peak[0], tree_rss_mb(proc.pid))
            time.sleep(0.5)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    events, first_step, done = [], None, None
    for line in proc.stdout:
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        events.append(ev)
        if ev.get("event") == "progress" and first_step is None and ev.get("iteration", 0) >= 1:
            first_step = time.perf_counter() - t0
        if ev.get("event") == "done":
            done = ev
    proc.wait()
    stop.set()
    th.join()
    plan = next((e for e in events if e.get("event") == "plan"), {})
    progress = [e for e in events if e.get("event") == "progress"]
    spm = None
    if len(progress) >= 2:
        a, b = progress[0], progress[-1]
        if b["elapsed"] > a["elapsed"]:
            spm = 60 * (b["iteration"] - a["iteration"]) / (b["elapsed"] - a["elapsed"])
    error = next((e.get("message") for e in events if e.get("event") == "error"), None)
    return {"returncode": proc.returncode, "error": error, "plan_lines": plan.get("lines"),
            "plan_peak_mb": round(plan.get("peak_bytes", 0) / 2 ** 20),
            "plan_start_mb": round((plan.get("start_bytes") or 0) / 2 ** 20), "peak_mb": round(peak[0]),
            "first_step_s": None if first_step is None else round(first_step, 1),
            "steps_per_minute": None if spm is None else round(spm, 1),
            "steps": None if done is None else done.get("iterations"),
            "gaussians": None if done is None else done.get("gaussians"),
            "psnr_test": None if done is None else done.get("psnr_test"),
            "wall_s": round(time.perf_counter() - t0, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", default="100,300,500")
    ap.add_argument("--width", type=int, default=1600, help="photo width after scaling (5600: 23.5 MP)")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--mode", default="3dgs")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "size")
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--gen-width", type=int, default=320,
                    help="width the survey is rendered at before scaling (160: four times faster to make)")
    ap.add_argument("--survey", type=Path, default=None,
                    help="scale this survey instead of generating one per --views (e.g. a bench_caustics survey)")
    args = ap.parse_args(argv)
    results = {}
    sources = ([(len(list((args.survey / "images").iterdir())), args.survey)] if args.survey else
               [(n, None) for n in (int(v) for v in args.views.split(","))])
    for n, given in sources:
        small = given or generate(args.out, n, args.seed, args.gen_width)
        big = args.out / "surveys" / f"{small.name}_{args.width}"
        if not (big / "sparse").is_dir():
            print(scale_survey(small, big, args.width), flush=True)
        key = f"{n} views of {small.name} {args.width} px {args.device} {args.mode}"
        results[key] = r = run(big, args.out / "runs" / key.replace(" ", "_"), args.minutes, args.device, args.mode)
        print(key, json.dumps(r), flush=True)
    (args.out / "size.json").write_text(json.dumps(results, indent=1))
    rows = ["| survey | first step (s) | peak memory (MB) | plan: to start / at the budget (MB) | steps/min | steps "
            "| Gaussians | held-out PSNR vs photos (dB) |", "|---|---|---|---|---|---|---|---|"]
    for k, r in results.items():
        rows.append(f"| {k} | {r['first_step_s']} | {r['peak_mb']} | {r['plan_start_mb']} / {r['plan_peak_mb']} "
                    f"| {r['steps_per_minute']} "
                    f"| {r['steps']} | {r['gaussians']} | {r['psnr_test']} |")
    (args.out / "size.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
