"""The pass estimator's time and memory on a survey, beside what the plan expects of it
(``core/caustics/cost.py``: the constants there come from this benchmark).

    .venv/bin/python benchmarks/bench_pass_cost.py SURVEY [--max-side 640] [--warmup 200] [--looks auto|off]
        [--look-max-frames 36]

Trains ``--warmup`` plain steps (the model whose depth the estimator tries beside the points'),
then runs the estimator whole, whatever the light (its light test is lifted), sampling the
process's resident memory every 50 ms. Prints one JSON line: the frames and their megapixels,
the probe time, the seconds (and each part's), the peak memory over what the job held before,
the probe units a megapixel and the bytes a pixel they come to, and the plan's estimate. Where the
survey has ground truth (``clean/``), also the training frames' targets (the passes' estimates
where they cover a pixel, the photo elsewhere) and the held-out frames' references against it,
and the independent looks a point had: ``--looks off`` leaves the survey's look frames out,
``--look-max-frames`` sets how many frames a keyframe gathers from with them
(``passes.LOOK_MAX_FRAMES``).
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recgs_addon.core.caustics import cost, estimators, passes  # noqa: E402
from recgs_addon.core.caustics.build import make_method  # noqa: E402
from recgs_addon.core.caustics.config import CausticConfig  # noqa: E402
from recgs_addon.core.train.config import preset  # noqa: E402
from recgs_addon.core.train.losses import psnr  # noqa: E402
from recgs_addon.core.train.plan import resident_bytes  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("survey")
    p.add_argument("--max-side", type=int, default=1600)
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--looks", choices=("auto", "off"), default="auto")
    p.add_argument("--look-max-frames", type=int, default=passes.LOOK_MAX_FRAMES)
    a = p.parse_args(argv)
    passes.LOOK_MAX_FRAMES = a.look_max_frames
    cfg = preset("default", max_side=a.max_side, medium="off", iterations=a.warmup)
    clean = Path(a.survey) / "clean"
    m = make_method(a.survey, cfg, CausticConfig(mode="recgs", estimator="passes", caustics="on", looks=a.looks),
                    gt_images=clean if clean.is_dir() else None)
    tr = m.trainer
    tr.data.load_all(tr.level())
    tr.train_until(lambda: tr.step >= a.warmup)
    estimators.LIGHT_FLOOR = -1.0   # the whole estimate, whatever the light
    data = tr.data
    planned = cost.pass_cost([data.sizes[i] for i in data.train_ids + data.test_ids])
    peak, stop = [0], [False]

    def watch():
        while not stop[0]:
            peak[0] = max(peak[0], resident_bytes() or 0)
            time.sleep(0.05)
    before = resident_bytes() or 0
    th = threading.Thread(target=watch)
    th.start()
    t = time.perf_counter()
    g = m._make_pass_estimates()
    seconds = time.perf_counter() - t
    stop[0] = True
    th.join()
    probe = cost.probe_seconds()
    scores = {}
    if clean.is_dir() and g.get("estimates") is not None:
        scores["targets_db"] = round(float(np.mean([
            psnr(passes.blend(g["estimates"][i].float(), g["weights"][i].float(), data.view(i)[1]).clamp(0, 1),
                 data.gt_view(i)) for i in data.train_ids])), 2)
        if m.references:
            scores["references_db"] = round(float(np.mean([psnr(r.float().clamp(0, 1), data.gt_view(i))
                                                           for i, r in m.references.items()])), 2)
        scores["photos_db"] = round(float(np.mean([psnr(data.view(i)[1], data.gt_view(i)) for i in data.train_ids])), 2)
    info = m.pass_info or {}
    print(json.dumps({**scores, "median_looks": info.get("median_looks"),
                      "look_frames": (info.get("look_frames") or {}).get("used"), "look_max_frames": a.look_max_frames,
        "survey": a.survey, "frames": len(data.train_ids) + len(data.test_ids), "size": data.sizes[data.train_ids[0]],
        "megapixels": round(planned.megapixels, 2), "probe_ms": round(1000 * probe, 3), "seconds": round(seconds, 1),
        "parts": m.pass_info.get("part_seconds"), "peak_extra_gb": round((peak[0] - before) / 2 ** 30, 3),
        "units_per_megapixel": round(seconds / probe / planned.megapixels), "bytes_per_pixel":
            round((peak[0] - before) / (planned.megapixels * 1e6)),
        "planned_seconds": round(planned.seconds, 1), "planned_gb": round(planned.bytes / 2 ** 30, 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
