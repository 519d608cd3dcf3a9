"""What light each survey shows (core/caustics/light.py): caustics found or not, the moving light,
its share, the light fixed to the camera, the exposure, and what a lamp the trainer would model.

    .venv/bin/python benchmarks/bench_light.py [--out out/bench] [--surveys networks,dive-lamp,...]
        [--real wreck-lamp,auv-seabed,pool-tiles,reef-transect]

Generated surveys come from benchmarks/bench_caustics.py (made once in OUT/surveys); the battery
of real footage (benchmarks/footage.py, ../shared/footage) is imported at the defaults into
OUT/real/NAME once (an item not here is skipped, and said). Prints one row per survey and whether
the finding is what the survey holds (every generated survey knows whether it has caustics; the
real footage has none): the moving light between frames taken from nearly the same place and
far apart, the survey's noise floor, and the evidence that decided.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

#: Surveys by whether they hold sunlight caustics.
CAUSTIC = ("sample", "networks", "ridges", "broad", "mild", "weak", "dive-networks", "dive-mild", "dive-broad",
           "dive-wander", "dive-water-networks", "tiles-networks")
CLEAN = ("none", "dive-none", "sample-none", "dive-water", "dive-water-clear", "dive-lamp", "tiles-none",
         "grid-gloss-none")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--surveys", default="sample,networks,ridges,broad,mild,weak,none,sample-none,dive-networks,"
                                        "dive-none,dive-lamp")
    p.add_argument("--real", default="wreck-lamp,auv-seabed,pool-tiles,reef-transect")
    args = p.parse_args(argv)
    from bench_caustics import survey_dir
    from footage import missing, real_survey
    from recgs_addon.core.caustics.light import survey_light
    from recgs_addon.core.io.colmap import load_scene
    from recgs_addon.core.io.frames import read_frame_times
    from recgs_addon.core.train.config import TrainConfig
    from recgs_addon.core.train.data import TrainData
    from recgs_addon.core.train.lamp import lamp_decision

    todo = [(s, survey_dir(args.out, s), s in CAUSTIC) for s in args.surveys.split(",") if s]
    for r in [r for r in args.real.split(",") if r]:
        if missing(r):
            print(f"skipped real:{r}: {missing(r)}", file=sys.stderr)
        else:
            todo.append((f"real:{r}", real_survey(args.out, r), False))
    cfg = TrainConfig()
    print("| survey | caustics | found | moving light, near | far | floor | its share | fixed to the camera | explained "
          "| exposure | pairs | lamp modelled | seconds | decided by |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    right = 0
    for name, d, has in todo:
        scene = load_scene(d)
        data = TrainData(scene, cfg.downscale, cfg.holdout_every, "cpu", max_side=cfg.max_side)
        t = time.perf_counter()
        f = survey_light(data, times=read_frame_times(d) or {})
        lamp, _ = lamp_decision(f.summary())
        right += f.caustics == has
        print(f"| {name} | {'yes' if has else 'no'} | {'yes' if f.caustics else 'no'} | {f.moving:.3f} | "
              f"{f.moving_far:.3f} | {f.floor:.3f} | {f.share:.2f} | {f.camera:.3f} | {f.explained:.2f} | "
              f"{f.exposure:.3f} | {f.pairs} | {'yes' if lamp else 'no'} | {time.perf_counter() - t:.1f} | "
              f"{f.decided_by} |", flush=True)
    print(f"\nfound right on {right} of {len(todo)} surveys")
    print(json.dumps({"right": right, "surveys": len(todo)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
