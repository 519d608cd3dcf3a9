"""What pruning a trained model by its Gaussians' blending weights costs, without retraining.

    .venv/bin/python benchmarks/bench_prune.py SURVEY MODEL.ply [--keep 0.5,0.33,0.25]

Loads ``MODEL.ply`` into a trainer of ``SURVEY`` (held out every 8th view; scored against
``SURVEY/clean`` where it exists), measures every Gaussian's blending weight in every training
view (``core.outputs.diagnostics.blending_weights``: pixels of the view it supplies), and
prints held-out PSNR of the whole model and of the share ``--keep`` of it ranked by the largest
weight in any view (``max``) and by the weight summed over the views (``sum``: LightGaussian's
global significance, without its volume factor). Prints the time the weights took.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.outputs.diagnostics import blending_weights  # noqa: E402
from recgs_addon.core.train.config import preset  # noqa: E402
from recgs_addon.core.train.trainer import make_trainer  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("survey", type=Path)
    ap.add_argument("model", type=Path)
    ap.add_argument("--keep", default="0.5,0.33,0.25", help="shares of the Gaussians to keep")
    args = ap.parse_args(argv)
    gt = args.survey / "clean"
    g = read_gaussian_ply(args.model)
    tr = make_trainer(args.survey, preset("default", holdout_every=8, sh_degree=3), gaussians=g,
                      gt_images=gt if gt.is_dir() else None)
    n = tr.params["means"].shape[0]
    t = time.perf_counter()
    weights = torch.stack([blending_weights(tr, i).cpu() for i in tr.data.train_ids])   # (views, N)
    print(f"{args.model}: {n:,} Gaussians, SH degree {tr.sh_degree}; weights over {weights.shape[0]} views "
          f"{time.perf_counter() - t:.1f} s")
    key = "psnr_gt" if gt.is_dir() else "psnr"
    print(f"  all: held-out {tr.evaluate()[key]:.2f} dB; carried by no view (< 1 px in each): "
          f"{float((weights.max(0).values < 1).float().mean()):.0%}")
    snap = tr.snapshot()
    for name, score in (("max", weights.max(0).values), ("sum", weights.sum(0))):
        for share in (float(x) for x in args.keep.split(",")):
            keep = score >= torch.sort(score, descending=True).values[max(1, int(share * n)) - 1]
            sub = {"params": {k: v[keep.to(v.device)] for k, v in snap["params"].items()}, "sh_degree": snap["sh_degree"]}
            with tr.using(sub):
                print(f"  keep {share:.2f} by {name}: {int(keep.sum()):,} Gaussians, held-out {tr.evaluate()[key]:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
