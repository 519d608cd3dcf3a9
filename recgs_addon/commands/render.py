"""The ``render`` command: a model rendered from a survey's cameras (a PNG and a float EXR per
view, in OUT), each view's PSNR against its photo as JSON lines (no Blender needed)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..core.errors import RecGSError
from ..core.options.scene import RENDER_OPTIONS
from .events import emit, fail, finite


def add_render_arguments(p) -> None:
    """The ``render`` options, from their one declaration (core/options/)."""
    RENDER_OPTIONS.add_to(p)


def run_render(args) -> int:
    import torch

    from ..core.io.atomic import make_folder
    from ..core.io.colmap import load_scene
    from ..core.io.images import write_image
    from ..core.train.losses import psnr
    from ..core.io.ply import read_gaussian_ply
    from ..core.render.rasterizer import render
    from ..core.train.data import resolve_image_dir

    try:
        if args.downscale < 1:
            raise RecGSError(f"--downscale must be an integer >= 1, got {args.downscale}")
        if args.out.exists() and not args.out.is_dir():
            raise RecGSError(f"{args.out}: is a file, not a folder (choose another output folder)")
        g = read_gaussian_ply(args.model)
        image_dir = None
        if args.images:
            image_dir = resolve_image_dir(args.scene_dir, args.images)
        scene = load_scene(args.scene_dir, image_dir=image_dir)
        cams = scene.cameras
        if args.names:
            wanted = [n.strip() for n in args.names.split(",") if n.strip()]
            unknown = [n for n in wanted if n not in {c.name for c in cams}]
            if unknown:
                raise RecGSError(f"{scene.model_dir}: no camera for image(s) {', '.join(unknown)}")
            cams = [c for c in cams if c.name in wanted]
        make_folder(args.out)
    except RecGSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    t = {k: torch.tensor(v) for k, v in (("means", g.means), ("log_scales", g.log_scales), ("quats", g.quats),
                                         ("logit_opacities", g.logit_opacities), ("sh", g.sh))}
    results = []
    try:
        for cam in cams:
            results.append(_render_one(args, scene, cam, t, render, psnr, write_image))
    except RecGSError as exc:   # an image that does not decode, a full disk
        return fail(str(exc))
    mean = float(np.mean([r["psnr"] for r in results if r["psnr"] is not None])) if results else None
    emit("done", views=len(results), mean_psnr=mean)
    return 0


def _render_one(args, scene, cam, t, render, psnr, write_image) -> dict:
    """Render one camera, write its PNG and EXR, return its PSNR and time."""
    import torch

    img = scene.load_image(cam, downscale=args.downscale)
    c = cam.resized(img.shape[1], img.shape[0])
    t0 = time.perf_counter()
    with torch.no_grad():
        out = render(t["means"], t["log_scales"], t["quats"], t["logit_opacities"], t["sh"],
                     torch.tensor(cam.viewmat, dtype=torch.float32), torch.tensor(c.K, dtype=torch.float32),
                     img.shape[1], img.shape[0], compiled=False if args.eager else None)
    dt = time.perf_counter() - t0
    rgb = out.rgb.numpy()
    stem = Path(cam.name).with_suffix("")
    write_image(args.out / f"{stem}.png", rgb)
    write_image(args.out / f"{stem}.exr", rgb)
    value = psnr(torch.from_numpy(np.clip(rgb, 0, 1)), torch.from_numpy(img))
    result = {"name": cam.name, "psnr": finite(value), "seconds": round(dt, 3)}
    emit("rendered", **result)
    return result
