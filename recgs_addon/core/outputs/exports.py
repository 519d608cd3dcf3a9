"""Files a training run leaves beside its PLY (no bpy):

* ``renders/NAME.png`` (+ ``.exr``): held-out views rendered by the final model;
* caustic modes: ``caustic/NAME.exr`` (the additive caustic estimate C of each training view,
  float, signed) and ``decaustic/NAME.png`` (+ ``.exr``): the caustic-free image ``I - C``
  (clipped to [0, 1] in the PNG only).

Returns the scores these images allow: PSNR of the caustic-free training images against the
ground truth (and of the captured ones, for reference) where the survey has ground truth.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..io.images import write_image
from ..train.losses import psnr


def _stem(name: str) -> Path:
    return Path(name).with_suffix("")


def write_outputs(method, out: Path) -> dict:
    """Write the files above for a training method (core/caustics/method.py); returns the scores."""
    out = Path(out)
    trainer = method.trainer
    data = trainer.data
    cams = data.scene.cameras
    for i in data.test_ids:
        rgb = trainer.render_view(i).clamp(0, 1).cpu().numpy()
        stem = _stem(cams[i].name)
        write_image(out / "renders" / f"{stem}.png", rgb)
        write_image(out / "renders" / f"{stem}.exr", rgb)
    result: dict = {}
    caustic = bool(data.train_ids) and method.decaustic_image(data.train_ids[0]) is not None
    captured, cleaned = [], []
    for i in data.train_ids:
        image = data.view(i, 1)[1]
        gt = data.gt_view(i)
        if gt is not None:
            captured.append(psnr(image, gt))
        if not caustic:
            continue
        free = method.decaustic_image(i)
        stem = _stem(cams[i].name)
        write_image(out / "caustic" / f"{stem}.exr", (image - free).cpu().numpy())
        write_image(out / "decaustic" / f"{stem}.png", free.cpu().numpy())
        write_image(out / "decaustic" / f"{stem}.exr", free.cpu().numpy())
        if gt is not None:
            cleaned.append(psnr(torch.clamp(free, 0, 1), gt))
    if captured:
        result["psnr_captured_gt"] = float(np.mean(captured))
    if cleaned:
        result["psnr_decaustic_gt"] = float(np.mean(cleaned))
    return result
