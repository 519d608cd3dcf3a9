"""How good are the pass estimator's caustic-free targets, before any training?

    .venv/bin/python benchmarks/bench_targets.py SURVEY [--model MODEL.ply] [--depth points|true|model]
        [--statistics floor,field] [--bound] [--looks [--look-max-frames N]] [--set FIELD=VALUE ...]

For a generated survey with ground truth (``clean/``), builds every training frame's target as
the pass estimator does (core/caustics/passes.py) and prints, against ground truth: the photos,
the targets (the mean PSNR over the training frames, as ``psnr_decaustic_gt`` in a run's
metrics; where too few passes saw a pixel the photo stands in, or RecGS's low-pass target when a
model is given), and the depth error of the geometry (where the survey has the generator's true
depth, ``tools/make_survey.py --save-depth``). ``--depth``: ``points`` (the survey's sparse
points refined by the plane sweep: what a run uses), ``true`` (the generator's depth: the
estimator's ceiling) or ``model`` (the given model's own rendered depth, unrefined). Each of
``--statistics`` is measured (``floor``: the floor of the light; ``field``: each frame's light
modelled, then the colour), with the independent looks a pixel had. ``--bound`` (with the true
depth) adds the statistics' ceilings: each photo with its true light, denoised as the field
denoises its light, taken off; the floor taken over the frames whose *true* light is lowest;
and what the gathered frames hold at best, the ground truth warped from them into each frame
against its own.
``--looks``: the keyframes gather also from the survey's look frames (``looks.json``, placed
as a job places them; their depth from the sparse points), as a run does. Prints the time of
each part.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recgs_addon.core.caustics import fft_filter, geometry, passes  # noqa: E402
from recgs_addon.core.caustics.estimate import compensate_caustics  # noqa: E402
from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.io.frames import read_frame_times  # noqa: E402
from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.render.rasterizer import render  # noqa: E402
from recgs_addon.core.train.data import TrainData, view_tensors  # noqa: E402
from recgs_addon.core.train.losses import psnr  # noqa: E402


def model_renders(ply: Path, data: TrainData, ids) -> dict:
    """{i: (rgb, surface depth, alpha)} of the PLY's model in frames ``ids``."""
    g = read_gaussian_ply(ply)
    t = [torch.from_numpy(np.ascontiguousarray(a)).float()
         for a in (g.means, g.log_scales, g.quats, g.logit_opacities, g.sh)]
    out = {}
    for i in ids:
        cam = data.camera(i)
        vm, K = view_tensors(cam, "cpu")
        with torch.no_grad():
            r = render(*t, vm, K, cam.width, cam.height, sh_degree=g.sh_degree)
        out[i] = (r.rgb, r.depth / r.alpha.clamp_min(1e-6), r.alpha)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("survey", type=Path)
    ap.add_argument("--model", type=Path, default=None, help="a trained model's PLY (low-pass fallback, --depth model)")
    ap.add_argument("--depth", choices=("points", "true", "model"), default="points")
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--statistics", default="floor,field", help="the pass estimator's statistics to compare")
    ap.add_argument("--bound", action="store_true", help="the statistics' ceilings (needs --depth true)")
    ap.add_argument("--looks", action="store_true",
                    help="gather also from the survey's look frames (looks.json; their depth from the sparse points)")
    ap.add_argument("--look-max-frames", type=int, default=passes.LOOK_MAX_FRAMES,
                    help="with --looks: the frames a keyframe gathers from at most")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a PassSettings field for this measurement (repeatable), e.g. --set per_pass=8")
    args = ap.parse_args(argv)
    if args.depth == "model" and args.model is None:
        ap.error("--depth model needs --model")
    if args.bound and args.depth != "true":
        ap.error("--bound needs --depth true")

    scene = load_scene(args.survey)
    data = TrainData(scene, 1, args.holdout_every, gt_scene=load_scene(args.survey, image_dir=args.survey / "clean"),
                     max_side=1600)
    ids = data.train_ids
    times = read_frame_times(args.survey) or {}
    photos = {i: data.view(i)[1] for i in ids}
    gts = {i: data.gt_view(i) for i in ids}
    print(f"{args.survey.name}: {len(ids)} training frames; photos {np.mean([psnr(photos[i], gts[i]) for i in ids]):.2f} dB")
    renders = model_renders(args.model, data, ids) if args.model else None
    fallback = None
    if renders:
        k = fft_filter.choose_k([photos[i] - renders[i][0] for i in ids])
        low = [compensate_caustics(photos[i], renders[i][0], k) for i in ids]
        fallback = low
        print(f"  model render {np.mean([psnr(renders[i][0].clamp(0, 1), gts[i]) for i in ids]):.2f} dB, "
              f"low-pass targets (k {k}) {np.mean([psnr(x.clamp(0, 1), gts[i]) for x, i in zip(low, ids)]):.2f} dB")
    true = {}
    if (args.survey / "depth").is_dir():
        true = {i: torch.from_numpy(np.load(args.survey / "depth" / (Path(scene.cameras[i].name).stem + ".npy"))).float()
                for i in ids}
    views = []
    for i in ids:
        cam = data.camera(i)
        vm, K = view_tensors(cam, "cpu")
        if args.depth == "true":
            d = true[i]
        elif renders:   # points: the model's depth stands where there are no points, and is swept too
            d = torch.where(renders[i][2] > 0.5, renders[i][1], torch.full_like(renders[i][1], float("nan")))
        else:
            d = torch.full((cam.height, cam.width), float("nan"))
        views.append(geometry.PassView(photos[i], d, torch.isfinite(d) & (d > 0), vm, K, times.get(cam.name)))
    t = time.perf_counter()
    if args.depth == "points":
        overlap = geometry.survey_geometry(views, torch.tensor(np.asarray(scene.points), dtype=torch.float32))
    else:
        overlap = geometry.overlap_matrix(views)
    t_geo = time.perf_counter() - t
    if true:
        err = np.concatenate([((v.surface - true[i]).abs() / true[i])[torch.isfinite(v.surface) & torch.isfinite(true[i])]
                              .numpy() for v, i in zip(views, ids)])
        print(f"  depth ({args.depth}): median error {100 * np.median(err):.2f} %, 90th percentile "
              f"{100 * np.percentile(err, 90):.2f} % ({t_geo:.1f} s)")
    t = time.perf_counter()
    light = passes.light_statistics(views, overlap)
    settings = passes.settings_for(light)
    for item in args.set:
        field, _, value = item.partition("=")
        if not hasattr(settings, field):
            ap.error(f"--set {item}: PassSettings has no field {field!r}")
        kind = type(getattr(settings, field))
        settings = dataclasses.replace(settings, **{field: kind(value)})
    t_light = time.perf_counter() - t
    print(f"  light: std {light['light_std']} log units, correlation time {light['correlation_s']} s, "
          f"decorrelation time {light.get('light_seconds')} s (shared variance by lag {light['shared']}; {t_light:.1f} s)")
    if args.set:
        print(f"  settings: {', '.join(args.set)}")
    frames, wide, extra = views, overlap, {}
    if args.looks:
        frames, wide, settings = with_look_frames(args.survey, scene, data, ids, views, overlap, settings, times,
                                                  args.look_max_frames)
        extra = {"ids": list(range(len(views))), "sources": list(range(len(frames))),
                 "keyframes": set(range(len(views)))}
        print(f"  look frames: {len(frames) - len(views)} gathered from (at most {args.look_max_frames} frames a keyframe)")
    for stat in filter(None, args.statistics.split(",")):
        t = time.perf_counter()
        targets, info = passes.pass_targets(frames, dataclasses.replace(settings, statistic=stat), fallback,
                                            overlap=wide, **extra)
        t_est = time.perf_counter() - t
        p = np.mean([psnr(x.clamp(0, 1), gts[i]) for x, i in zip(targets, ids)])
        print(f"  targets, {stat}: {p:.2f} dB (median passes {np.median(info['passes']):g}, independent looks "
              f"{np.median(info['looks']):.1f}, share from the passes {np.mean(info['share']):.2f}; {t_est:.1f} s)")
    if args.bound:
        bound(views, settings, overlap, ids, gts)
        resampling(views, settings, overlap, gts, ids)
    return 0


def resampling(views, settings, overlap, gts, ids, every: int = 4) -> None:
    """What the gathered frames can hold at best on this geometry: the ground truth of every
    ``every``-th frame against the ground truth of the frames it gathers from, warped into it
    (resampling, and what the renderer makes of a view: noise, shading that follows the view),
    one frame at a time and their mean."""
    from recgs_addon.core.model.colour import linear_to_srgb

    clean = [dataclasses.replace(v, photo=gts[i]) for v, i in zip(views, ids)]
    one, mean = [], []
    for k in range(0, len(clean), every):
        samples, valid, _, _ = passes.gather(k, clean, passes.choose_passes(k, clean, overlap, settings),
                                             settings.depth_tol)
        own = linear_to_srgb(samples[0].clamp(0, 1))
        for f in range(1, len(samples)):
            if int(valid[f].sum()) >= 1000:
                one.append(psnr(linear_to_srgb(samples[f].clamp(0, 1)), own, valid[f]))
        w = valid[1:].float().unsqueeze(-1)
        avg = (samples[1:] * w).sum(0) / w.sum(0).clamp_min(1)
        mean.append(psnr(linear_to_srgb(avg.clamp(0, 1)), own, valid[1:].any(0)))
    print(f"  ground truth warped from the gathered frames into each frame: one frame {np.median(one):.2f} dB "
          f"(median of {len(one)}), their mean {np.mean(mean):.2f} dB")


def with_look_frames(survey: Path, scene, data: TrainData, ids, views, overlap, settings, times, max_frames: int):
    """The keyframes' ``views`` and the survey's look frames (placed as a job places them, at the
    keyframes' size, their depth from the sparse points) as frames to gather from: (frames,
    overlap of them all, settings with the looks)."""
    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.io.looks import place_looks, read_looks

    found = read_looks(survey)
    if found is None:
        raise SystemExit(f"{survey}: no looks.json")
    keys = [data.camera(i) for i in ids]
    placed, _ = place_looks(found.looks, keys, [times.get(c.name) for c in keys])
    looks = []
    for lk, cam, _ in placed:
        photo = torch.from_numpy(read_image(lk.path, size=(cam.width, cam.height)))
        vm, K = view_tensors(cam, "cpu")
        nan = torch.full((cam.height, cam.width), float("nan"))
        looks.append(geometry.PassView(photo, nan, torch.zeros(cam.height, cam.width, dtype=torch.bool), vm, K, lk.time))
    geometry.prior_geometry(looks, torch.tensor(np.asarray(scene.points), dtype=torch.float32))
    frames = views + looks
    wide = passes.with_looks(settings, [v.time for v in frames])
    return (frames, geometry.with_looks_overlap(overlap, views, looks, range(len(views))),
            dataclasses.replace(wide, max_frames=max(settings.max_frames, max_frames)))


def bound(views, settings, overlap, ids, gts) -> None:
    """The statistics' ceilings on this geometry: each frame's photo with its *true* light (photo
    over clean frame) taken off after the same denoising the field gives its modelled light
    (what a light of that form can represent), and the floor taken over the frames whose true
    light is lowest instead of their blurred grey level (what the floor's choice of frames
    costs)."""
    from recgs_addon.core.caustics.passes import apply_count_gain, gain_by_count
    from recgs_addon.core.caustics.tv import tv_denoise
    from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear

    truth = [srgb_to_linear(gts[i].clamp(0, 1)) for i in ids]
    owns = [srgb_to_linear(v.photo.clamp(0, 1)) for v in views]
    true_light = [torch.log((o.mean(-1) + 0.01) / (g.mean(-1) + 0.01)) for o, g in zip(owns, truth)]
    floors, chosen, counts = [], [], []
    for k, v in enumerate(views):
        groups = passes.choose_passes(k, views, overlap, settings)
        samples, valid, _, _ = passes.gather(k, views, groups, settings.depth_tol)
        sigma = settings.floor_sigma * v.photo.shape[1] / 320.0
        floors.append(passes.floor_statistic(samples, valid, settings.floor_tol, sigma, settings.own_weight))
        light = torch.stack([true_light[j] if j == k else
                             geometry.warp(v, views[j], settings.depth_tol, true_light[j].unsqueeze(-1))[0][..., 0]
                             for g in groups for j in g])
        key = torch.where(valid, light, torch.full_like(light, float("inf")))
        m = (valid & (key <= key.amin(0, keepdim=True) + np.log1p(settings.floor_tol))).float()
        chosen.append(torch.einsum("fhwc,fhw->hwc", samples, m) / m.sum(0).clamp_min(1e-6).unsqueeze(-1))
        counts.append(valid.sum(0))
    # each frame's true light (both signs) denoised as the field denoises its light: what a
    # light of that form can take out of the photo, with the colour it is measured against exact
    field = [o * torch.exp(-tv_denoise(light.unsqueeze(0), settings.field_lambda, v.covered.float().unsqueeze(0) + 1e-3,
                                       iters=passes.FIELD_ITERS)[0]).unsqueeze(-1)
             for o, light, v in zip(owns, true_light, views)]
    for name, stats in (("field, each frame's true light in the field's form", field),
                        ("floor, frames chosen by their true light", chosen)):
        gains = gain_by_count(owns, stats, counts)
        out = [linear_to_srgb(apply_count_gain(x, c, passes._for_counts(gains, c)).clamp_min(0)) for x, c in zip(stats, counts)]
        out = [torch.where(v.covered.unsqueeze(-1), o, v.photo) for o, v in zip(out, views)]
        print(f"  bound, {name}: {np.mean([psnr(o.clamp(0, 1), gts[i]) for o, i in zip(out, ids)]):.2f} dB")


if __name__ == "__main__":
    sys.exit(main())
