"""Training steps with glibc's default allocator against the job's tuned one (no mmap, no trim).

    .venv/bin/python benchmarks/bench_allocator.py MODEL.ply SCENE_DIR [--images clean]
        [--steps 10] [--rounds 2] [--threads 2] [--count 0]

Each path runs in a fresh process (allocator settings hold for a whole process), alternating
paths round by round; each process loads the model into a ``vanilla`` trainer, runs two
warm-up steps and times ``--steps`` training steps. Prints, per path: seconds per step
(median; best round), page faults per step and peak resident memory, and checks that both
paths end with the same parameters (the allocator must not change a number).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def child(args) -> None:
    from recgs_addon.commands.train import tune_allocator
    allocator = tune_allocator()
    import numpy as np
    import torch

    from recgs_addon.core.io.ply import read_gaussian_ply
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer

    torch.set_num_threads(args.threads)
    g = read_gaussian_ply(args.model)
    if args.count and len(g) > args.count:
        g = g.subset(np.sort(np.random.default_rng(0).choice(len(g), args.count, replace=False)))
    tr = make_trainer(args.scene, preset("vanilla", sh_degree=g.sh_degree), images=args.images, gaussians=g)
    tr.sh_degree, tr.step = g.sh_degree, 16000     # past densification: a fixed model size
    for _ in range(2):
        tr.train_step()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    times = []
    for _ in range(args.steps):
        t0 = time.perf_counter()
        tr.train_step()
        times.append(time.perf_counter() - t0)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    h = hashlib.sha256()
    for k in sorted(tr.params):
        h.update(tr.params[k].detach().numpy().tobytes())
    print(json.dumps({"allocator": allocator, "s_per_step": statistics.median(times),
                      "faults_per_step": faults / args.steps, "gaussians": len(g),
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "params_sha256": h.hexdigest()}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("model", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--images", default=None)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--count", type=int, default=0, help="use this many of the model's Gaussians (0 = all)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    argv = [sys.executable, __file__, str(args.model), str(args.scene), "--child", "--steps", str(args.steps),
            "--threads", str(args.threads), "--count", str(args.count)]
    if args.images:
        argv += ["--images", args.images]
    paths = ["system", "retained"]
    results: dict[str, list[dict]] = {p: [] for p in paths}
    for r in range(args.rounds):
        for p in (paths if r % 2 == 0 else paths[::-1]):
            env = dict(os.environ, RECGS_MALLOC="system" if p == "system" else "")
            out = subprocess.run(argv, env=env, capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            assert res["allocator"] == p, res
            results[p].append(res)
    g = results["system"][0]["gaussians"]
    print(f"{g:,} Gaussians, {args.threads} threads, {args.steps} steps per process, best of {args.rounds} rounds")
    best = {p: min(results[p], key=lambda x: x["s_per_step"]) for p in paths}
    print(f"{'allocator':>10} {'s/step':>8} {'x retained':>10} {'faults/step':>12} {'peak RSS MB':>12}")
    for p in paths:
        b = best[p]
        print(f"{p:>10} {b['s_per_step']:8.3f} {b['s_per_step'] / best['retained']['s_per_step']:10.2f} "
              f"{b['faults_per_step']:12.0f} {b['peak_rss_mb']:12.0f}")
    same = len({x["params_sha256"] for p in paths for x in results[p]}) == 1
    print("parameters after the steps:", "identical on every path" if same else "DIFFER")


if __name__ == "__main__":
    main()
