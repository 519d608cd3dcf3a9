"""Real footage and the generator's hard surveys at the defaults: ``--mode recgs`` beside
``--mode 3dgs`` at equal time, and whether each job kept its promises.

    .venv/bin/python benchmarks/bench_footage.py [--out out/bench] [--minutes 3] [--threads 1]
        [--real wreck-lamp,auv-seabed,pool-tiles,reef-transect] [--surveys dive-none,dive-networks]

The battery of real footage (benchmarks/footage.py, ../shared/footage; an item not here is
skipped and said) is imported once at the defaults; generated surveys come from
benchmarks/bench_caustics.py. Each survey's two runs go side by side, ``--threads`` threads each
(``python -m recgs_addon train SURVEY --mode M --max-minutes N``), into
``OUT/footage/SURVEY/MODE-Nmin`` (a run whose metrics exist is not repeated). One row a survey:
what the light finding decided and on what evidence, the held-out PSNR of each run against the
held-out photos as captured, RecGS's steps over plain's, each job's seconds over its limit and its
peak resident memory over its plan's, the overlay masked and the share the passes abstained on.
Prints a Markdown table and one JSON line.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def run_pair(scene: Path, out: Path, minutes: float, threads: int) -> dict:
    """``recgs`` and ``3dgs`` on ``scene`` side by side; their metrics."""
    procs, results = {}, {}
    for mode in ("recgs", "3dgs"):
        d = out / f"{mode}-{minutes:g}min"
        if (d / "metrics.json").is_file():
            continue
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
               "NUMBA_NUM_THREADS": str(threads)}
        d.mkdir(parents=True, exist_ok=True)
        log = open(d / "log.txt", "w")
        procs[mode] = (subprocess.Popen([sys.executable, "-m", "recgs_addon", "train", str(scene), "--out", str(d),
                                         "--mode", mode, "--max-minutes", str(minutes)], cwd=ROOT, env=env,
                                        stdout=subprocess.DEVNULL, stderr=log), log, time.perf_counter())
    for mode, (p, log, t) in procs.items():
        p.wait()
        log.close()
    for mode in ("recgs", "3dgs"):
        f = out / f"{mode}-{minutes:g}min" / "metrics.json"
        results[mode] = json.loads(f.read_text()) if f.is_file() else None
    return results


def row(name: str, r: dict, minutes: float) -> dict:
    rec, plain = r["recgs"], r["3dgs"]
    if rec is None or plain is None:
        return {"survey": name, "failed": True}
    limit = 60 * minutes
    light = rec.get("light") or {}
    mem = lambda m: (m.get("peak_resident_bytes") or 0) / max(1, (m.get("plan") or {}).get("peak_bytes") or 1)  # noqa: E731
    return {"survey": name, "caustics": light.get("caustics"), "decided_by": light.get("decided_by"),
            "moving": light.get("moving"), "moving_far": light.get("moving_far"), "floor": light.get("floor"),
            "recgs": rec.get("psnr_test_captured"), "plain": plain.get("psnr_test_captured"),
            "recgs_gt": rec.get("psnr_test_gt"), "plain_gt": plain.get("psnr_test_gt"),
            "steps": rec["iterations"], "plain_steps": plain["iterations"],
            "time_recgs": rec["job_seconds"] / limit, "time_plain": plain["job_seconds"] / limit,
            "memory_recgs": mem(rec), "memory_plain": mem(plain),
            "overlay": (rec.get("overlay") or {}).get("share"), "abstained": (rec.get("passes") or {}).get("abstained"),
            "dropped": rec.get("caustics_dropped"), "kept": (rec.get("candidates") or {}).get("kept")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--minutes", type=float, default=3.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--real", default="wreck-lamp,auv-seabed,pool-tiles,reef-transect")
    p.add_argument("--surveys", default="")
    a = p.parse_args(argv)
    from bench_caustics import survey_dir
    from footage import missing, real_survey

    todo = []
    for name in [n for n in a.real.split(",") if n]:
        if missing(name):
            print(f"skipped {name}: {missing(name)}", file=sys.stderr)
        else:
            todo.append((name, real_survey(a.out, name)))
    todo += [(s, survey_dir(a.out, s)) for s in a.surveys.split(",") if s]
    rows = []
    print("| survey | caustics found | moving near / far / floor | decided by | RecGS (dB) | 3DGS (dB) | steps, RecGS / "
          "3DGS | job / limit | peak / plan | overlay | abstained |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, scene in todo:
        r = row(name, run_pair(scene, a.out / "footage" / name, a.minutes, a.threads), a.minutes)
        rows.append(r)
        if r.get("failed"):
            print(f"| {name} | a run failed (see its log.txt) |", flush=True)
            continue
        f = lambda v, d=2: "-" if v is None else f"{v:.{d}f}"   # noqa: E731
        print(f"| {name} | {'yes' if r['caustics'] else 'no'} | {f(r['moving'], 3)} / {f(r['moving_far'], 3)} / "
              f"{f(r['floor'], 3)} | {r['decided_by']} | {f(r['recgs'])} | {f(r['plain'])} | "
              f"{r['steps']:,} / {r['plain_steps']:,} ({r['steps'] / max(1, r['plain_steps']):.2f}) | "
              f"{f(r['time_recgs'])} / {f(r['time_plain'])} | {f(r['memory_recgs'])} / {f(r['memory_plain'])} | "
              f"{f(r['overlay'], 3)} | {f(r['abstained'], 3)} |", flush=True)
    print(json.dumps({"minutes": a.minutes, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
