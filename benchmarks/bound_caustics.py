"""How close can any model whose low frequencies come from the photos get to the clean scene?

    .venv/bin/python benchmarks/bound_caustics.py SCENE_DIR MODEL.ply [--targets captured]
        [--loss l2] [--steps 1500] [--rounds 5] [--k 25] [--threads 1]

RecGS's targets are ``I - lowpass(I - render) = highpass(I) + lowpass(render)``: the low
frequencies of the scene are the model's own, and a smooth 3D field is low-frequency in every
view, so no per-view low-pass estimate can tell it from caustics. What sets the model's low
band is then the photos' consensus: each point averages the caustics of the few photos that
see it. This script measures that limit with the best geometry there is: it freezes the
geometry of ``MODEL.ply`` (typically the ``oracle`` model, trained on the ground-truth
photos), refits only the Gaussians' colours (SH degree 0) to the training photos
(``--targets captured``, or ``clean`` to measure what the geometry itself can express; the
recurrences then run on the clean photos too), then
runs ``--rounds`` RecGS recurrences on the colours (``C = lowpass_k(I - render)`` less its
mean, 200 steps against ``I - C`` each). It prints held-out PSNR against the ground truth
(``SCENE_DIR/clean``) after each stage, and the PSNR of the caustic-free training images.
Every 8th view by sorted name is held out, as in training.

``--estimator consensus --stat S`` replaces the rounds by one refit to the multi-view
consensus targets (benchmarks/caustic_estimators/consensus.py, statistic S of the photos
warped with the frozen geometry's depth, gain restored per sample count): how far colours from more than
each point's own photos' average can go with the same geometry. ``--estimator gradients``
does the same with log-gradient consensus (Weiss 2001): the high band integrated from the
median of the warped photos' log-gradients, the lowest ``--k`` frequencies from their mean.
``--estimator lightfield`` runs the rounds with the per-view light fields of
benchmarks/caustic_estimators/lightfield.py instead of the low-pass (one-sided coherent light
over a floor, ``--lf-lambda``, ``--lf-tau``; the survey gain in linear light each round): how far the lower
envelope of the light takes the same geometry.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recgs_addon.core.caustics import fft_filter as caustics  # noqa: E402
from benchmarks.caustic_estimators import lightfield  # noqa: E402
from benchmarks.caustic_estimators.consensus import consensus_targets, log_gradient_targets  # noqa: E402
from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.train.losses import psnr  # noqa: E402
from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.render.rasterizer import render  # noqa: E402
from recgs_addon.core.train.data import holdout_split  # noqa: E402

ROUND_STEPS = 200


def bound(scene_dir: Path, model: Path, *, targets: str = "captured", loss: str = "l2", steps: int = 1500,
          rounds: int = 5, k: int = 25, lr: float = 0.01, holdout_every: int = 8,
          compiled: bool | None = None, log=print, estimator: str = "lowpass", stat: str = "mean",
          lf_lambda: float = 0.05, lf_tau: float = 0.02) -> list[dict]:
    """Refit the colours of ``model``'s frozen Gaussians, then run ``rounds`` RecGS recurrences
    on them. Returns one record per stage: ``stage``, ``heldout`` (mean held-out PSNR against
    ``scene_dir/clean``, dB) and, for the rounds, ``train`` (PSNR of the caustic-free training
    images ``I - C`` against ground truth)."""
    scene = load_scene(scene_dir)
    clean = load_scene(scene_dir, Path(scene_dir) / "clean")
    g = read_gaussian_ply(model)
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    means, log_scales, quats, logit_op = t(g.means), t(g.log_scales), t(g.quats), t(g.logit_opacities)
    dc = t(g.sh)[:, :1, :].clone().requires_grad_(True)
    cams = scene.cameras
    train_ids, test_ids = holdout_split([c.name for c in cams], holdout_every)
    truth = {i: torch.from_numpy(clean.load_image(clean.cameras[i])) for i in range(len(cams))}
    photo = truth if targets == "clean" else {
        i: torch.from_numpy(scene.load_image(cams[i])) for i in range(len(cams))}

    view = {i: (t(c.viewmat), t(c.K)) for i, c in enumerate(cams)}

    def draw(i: int) -> torch.Tensor:
        return render(means, log_scales, quats, logit_op, dc, *view[i], cams[i].width, cams[i].height,
                      sh_degree=0, compiled=compiled).rgb

    t0 = time.perf_counter()
    records: list[dict] = []

    @torch.no_grad()
    def report(stage: str, cmaps=None) -> None:
        rec = {"stage": stage, "heldout": float(np.mean([psnr(draw(i).clamp(0, 1), truth[i]) for i in test_ids]))}
        line = f"{stage:>10}: held-out {rec['heldout']:6.2f} dB vs ground truth"
        if cmaps is not None:
            rec["train"] = float(np.mean([psnr(photo[i] - cmaps[i], truth[i]) for i in train_ids]))
            line += f", caustic-free training images {rec['train']:6.2f} dB"
        records.append(rec)
        log(f"{line}  ({time.perf_counter() - t0:.0f} s)")

    opt = torch.optim.Adam([dc], lr=lr)
    rng = np.random.default_rng(0)

    def fit(n: int, target: dict) -> None:
        order: list[int] = []
        for _ in range(n):
            if not order:
                order = list(rng.permutation(train_ids))
            i = order.pop()
            d = draw(i) - target[i]
            value = (d * d).mean() if loss == "l2" else d.abs().mean()
            opt.zero_grad()
            value.backward()
            opt.step()

    log(f"{model}: {len(means)} Gaussians, geometry frozen; {len(train_ids)} training views, "
        f"{len(test_ids)} held out; colours fit to the {targets} photos ({loss})")
    report("as given")
    fit(steps, photo)
    report("refit")
    if estimator in ("consensus", "gradients"):
        with torch.no_grad():
            outs = {i: render(means, log_scales, quats, logit_op, dc, *view[i], cams[i].width, cams[i].height,
                              sh_degree=0, compiled=compiled) for i in train_ids}
            views = [dict(photo=photo[i], depth=outs[i].depth, alpha=outs[i].alpha, viewmat=view[i][0], K=view[i][1])
                     for i in train_ids]
            if estimator == "gradients":
                tg = log_gradient_targets(views, k)
            else:
                tg, _, _ = consensus_targets(views, stat)
            cmaps = {i: photo[i] - x for i, x in zip(train_ids, tg)}
        fit(steps, {i: photo[i] - cmaps[i] for i in train_ids})
        report("log-gradients" if estimator == "gradients" else f"consensus {stat}", cmaps)
        return records
    gain = torch.ones(3)
    for r in range(rounds):
        with torch.no_grad():
            cmaps = {}
            if estimator == "lightfield":
                # one-sided coherent light over a floor (core/caustics/lightfield.py), fitted
                # under the floor light; the survey gain brings the model back at the end
                q = torch.stack([lightfield.grey_log_ratio(photo[i], lightfield.scale_linear(draw(i), 1 / gain))
                                 for i in train_ids])
                fields = lightfield.light_fields(q, k, lf_lambda, lf_tau)
                floor = {i: lightfield.remove_light(photo[i], f) for i, f in zip(train_ids, fields)}
                gain = lightfield.linear_gain((photo[i], floor[i]) for i in train_ids)
                for i in train_ids:
                    cmaps[i] = photo[i] - lightfield.scale_linear(floor[i], gain)
                target = {i: lightfield.scale_linear(floor[i], gain) for i in train_ids}
            else:
                for i in train_ids:
                    c = caustics.lowpass(photo[i] - draw(i), k)
                    cmaps[i] = c - c.mean(dim=(0, 1), keepdim=True)
                target = {i: photo[i] - cmaps[i] for i in train_ids}
        fit(ROUND_STEPS, target)
        report(f"round {r + 1}", cmaps)
    return records


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("model", type=Path)
    ap.add_argument("--targets", choices=["captured", "clean"], default="captured")
    ap.add_argument("--loss", choices=["l2", "l1"], default="l2", help="l2: the mean of the views; l1: their median")
    ap.add_argument("--steps", type=int, default=1500, help="colour-fitting steps (one view each)")
    ap.add_argument("--rounds", type=int, default=5, help="RecGS recurrences on the colours")
    ap.add_argument("--k", type=int, default=25, help="low-pass block size")
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--estimator", choices=["lowpass", "consensus", "gradients", "lightfield"], default="lowpass")
    ap.add_argument("--lf-lambda", type=float, default=0.05, help="lightfield: TV weight")
    ap.add_argument("--lf-tau", type=float, default=0.02, help="lightfield: dead band (log light)")
    ap.add_argument("--stat", choices=["mean", "median", "min", "quantile"], default="mean",
                    help="consensus: the per-pixel statistic")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bound(args.scene, args.model, targets=args.targets, loss=args.loss, steps=args.steps, rounds=args.rounds,
          k=args.k, lr=args.lr, log=lambda m: print(m, flush=True), estimator=args.estimator, stat=args.stat,
          lf_lambda=args.lf_lambda, lf_tau=args.lf_tau)


if __name__ == "__main__":
    main()
