"""A survey trained as one job and in blocks on Ray, at the same total compute.

    .venv/bin/python benchmarks/bench_blocks.py [--survey S] [--views 400] [--blocks 4] [--minutes 10]
        [--out out/bench/blocks] [--mode 3dgs]

The survey (generated once unless ``--survey`` is given: tools/make_survey.py, ``--views``
photos of 160x120 in 8 lawnmower rows over a seabed many footprints long, no caustics) is
trained twice, one run after the other on this machine:

* one job: ``train S --max-minutes M`` on all the cores (torch's threads);
* blocks: ``train S --blocks B --max-minutes M`` on a local Ray: as many blocks at a time as
  there are cores, a thread each, each block M x (blocks at a time) / B minutes, so that
  both runs spend the same core-minutes.

With ``--speed STEPS`` it instead trains the same blocks twice for STEPS steps each: as many
workers as cores with a thread each, against one worker with all the cores (the blocks one
after another), and prints wall time and held-out PSNR of each.

Both models are scored by the same code (core/blocks/merge.py's ``score_views``) on the same
held-out photos, those that cross a seam of the split apart from the rest. Printed and written
to OUT/blocks.json and OUT/blocks.md: held-out PSNR (all, crossing a seam, inside one block),
Gaussians, steps, wall time, peak memory (the one job's process tree; each block's worker).
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
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_survey_size import tree_rss_mb  # noqa: E402


def generate(out: Path, views: int, seed: int) -> Path:
    d = out / f"survey{views}"
    if not (d / "sparse").is_dir():
        subprocess.run([sys.executable, str(ROOT / "tools" / "make_survey.py"), "--out", str(d), "--views", str(views),
                        "--width", "160", "--height", "120", "--lines", "8", "--overlap", "0.8", "--sidelap", "0.6",
                        "--caustic-strength", "0", "--no-clean", "--points", "20000", "--seed", str(seed)],
                       check=True, stdout=subprocess.DEVNULL)
    return d


def run(cmd: list[str], log: Path) -> dict:
    """Run ``cmd``, sampling its process tree's memory; (wall seconds, peak MB, the done event)."""
    t0 = time.perf_counter()
    with open(log, "w") as err:
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
        peak = [0.0]

        def sample():
            while p.poll() is None:
                peak[0] = max(peak[0], tree_rss_mb(p.pid))
                time.sleep(0.5)
        th = threading.Thread(target=sample, daemon=True)
        th.start()
        lines = p.stdout.read().splitlines()
        p.wait()
        th.join()
    done = next((json.loads(x) for x in reversed(lines) if x.startswith('{"event": "done"')), None)
    if p.returncode != 0 or done is None:
        raise SystemExit(f"{' '.join(cmd)} failed; see {log}")
    return {"wall_s": round(time.perf_counter() - t0, 1), "peak_tree_mb": round(peak[0]), "done": done}


def seam_views(out: Path) -> set[str]:
    """The held-out photos that cross a seam of the split a job in blocks wrote to ``out``."""
    return set(json.loads((out / "blocks" / "plan.json").read_text())["seam_views"])


def score(ply: Path, survey: Path, seams: set[str]) -> dict:
    from recgs_addon.core.blocks.merge import score_views, summarise
    from recgs_addon.core.io.ply import read_gaussian_ply
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import load_data

    data = load_data(survey, preset("default"))
    return summarise(score_views(read_gaussian_ply(ply), data, data.test_ids, seams))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--survey", type=Path)
    ap.add_argument("--views", type=int, default=400)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--mode", default="3dgs")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "blocks")
    ap.add_argument("--speed", type=int, default=0, metavar="STEPS")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    survey = a.survey or generate(a.out, a.views, a.seed)
    if a.speed:
        return speed(a, survey)
    common = [str(survey), "--mode", a.mode, "--max-minutes", str(a.minutes)]
    one_out, blk_out = a.out / "one", a.out / f"blocks{a.blocks}"
    py = [sys.executable, "-m", "recgs_addon", "train"]
    one = run(py + common + ["--out", str(one_out)], a.out / "one.log")
    blk = run(py + common + ["--out", str(blk_out), "--blocks", str(a.blocks)], a.out / "blocks.log")
    seams = seam_views(blk_out)
    rows = {"one job": (one, score(one_out / "point_cloud.ply", survey, seams)),
            f"{a.blocks} blocks": (blk, score(blk_out / "point_cloud.ply", survey, seams))}
    record = {"survey": str(survey), "minutes": a.minutes, "blocks": a.blocks, "runs": {}}
    md = ["| run | held-out PSNR (dB) | crossing a seam | inside a block | Gaussians | steps | wall (s) | "
          "peak memory (MB) |", "|---|---|---|---|---|---|---|---|"]
    for name, (r, s) in rows.items():
        d = r["done"]
        if "blocks" in d:
            mem = "workers " + " / ".join(str(b["peak_rss_mb"]) for b in d["blocks"]) + f", all {r['peak_tree_mb']}"
        else:
            mem = str(r["peak_tree_mb"])
        md.append(f"| {name} | {s['psnr']:.2f} | {s['psnr_seam']:.2f} ({s['seam_views']}) | {s['psnr_inner']:.2f} | "
                  f"{d['gaussians']:,} | {d['iterations']:,} | {r['wall_s']:.0f} | {mem} |")
        record["runs"][name] = {"scores": s, "wall_s": r["wall_s"], "peak_tree_mb": r["peak_tree_mb"],
                                "gaussians": d["gaussians"], "iterations": d["iterations"],
                                "blocks": d.get("blocks")}
    (a.out / "blocks.json").write_text(json.dumps(record, indent=1))
    (a.out / "blocks.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def speed(a, survey: Path) -> None:
    import os

    cores = os.cpu_count() or 1
    py = [sys.executable, "-m", "recgs_addon", "train", str(survey), "--mode", a.mode, "--blocks", str(a.blocks),
          "--iterations", str(a.speed)]
    md = ["| blocks run as | held-out PSNR (dB) | Gaussians | steps | wall (s) |", "|---|---|---|---|---|"]
    record = {}
    for name, threads in ((f"{cores} workers of 1 thread", 1), (f"1 worker of {cores} threads", cores)):
        out = a.out / f"speed_t{threads}"
        r = run(py + ["--out", str(out), "--block-threads", str(threads)], a.out / f"speed_t{threads}.log")
        s = score(out / "point_cloud.ply", survey, seam_views(out))
        d = r["done"]
        md.append(f"| {name} | {s['psnr']:.2f} | {d['gaussians']:,} | {d['iterations']:,} | {r['wall_s']:.0f} |")
        record[name] = {"scores": s, "wall_s": r["wall_s"], "gaussians": d["gaussians"], "iterations": d["iterations"]}
    (a.out / "speed.json").write_text(json.dumps(record, indent=1))
    print("\n".join(md))


if __name__ == "__main__":
    main()
