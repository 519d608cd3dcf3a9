"""Files a training run leaves beside its PLY (no bpy):

* ``renders/NAME.png`` (+ ``.exr``): held-out views rendered by the final model (in the
  seabed's true colour where the run modelled the water);
* where the run modelled the water: ``medium.json`` (the fitted coefficients); where it modelled a
  lamp on the camera: ``lamp.json`` (its terms); with either, ``truecolour/NAME.png`` (+ ``.exr``):
  each training photo (caustic-free in the caustic modes) taken out of the water and the lamp's
  light along the model's range: the seabed's true colour, evenly lit;
* caustic modes, where the run took light off: ``caustic/NAME.exr`` (the additive caustic
  estimate C of each training view, float, signed) and ``decaustic/NAME.png`` (+ ``.exr``): the
  caustic-free image ``I - C`` (clipped to [0, 1] in the PNG only). A run that found no caustics
  writes neither: its photos are caustic-free as they are.

Returns the scores these images allow: PSNR of the caustic-free training images against the
ground truth (and of the captured ones, for reference) where the survey has ground truth.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..io.atomic import atomic_path
from ..io.images import write_image
from ..model.colour import linear_to_srgb, srgb_to_linear
from ..model.medium import Medium, out_of_water
from ..train.losses import psnr

#: The most an evenly lit photo brightens a pixel the lamp left dark (its noise grows with it).
MAX_GAIN = 20.0


def _stem(name: str) -> Path:
    return Path(name).with_suffix("")


def write_outputs(method, out: Path) -> dict:
    """Write the files above for a training method (core/caustics/method.py); returns the scores."""
    out = Path(out)
    trainer = method.trainer
    data = trainer.data
    cams = data.scene.cameras
    for i in data.test_ids:
        rgb = trainer.render_view(i, seen=False).clamp(0, 1).cpu().numpy()
        stem = _stem(cams[i].name)
        write_image(out / "renders" / f"{stem}.png", rgb)
        write_image(out / "renders" / f"{stem}.exr", rgb)
    result: dict = {}
    if trainer.forms_image:
        _write_models(trainer, out)
    captured, cleaned, true_scores = [], [], []
    takes_off = method.takes_light_off()
    for i in data.train_ids:
        image = data.view(i, 1)[1]
        gt = data.gt_view(i)
        stem = _stem(cams[i].name)
        if gt is not None:
            captured.append(psnr(image, gt))
        # made once a view (None where the method makes none): it may render the view and
        # estimate its light
        free = method.decaustic_image(i) if takes_off else None
        if free is not None:
            write_image(out / "caustic" / f"{stem}.exr", (image - free).cpu().numpy())
            write_image(out / "decaustic" / f"{stem}.png", free.cpu().numpy())
            write_image(out / "decaustic" / f"{stem}.exr", free.cpu().numpy())
            if gt is not None:
                cleaned.append(psnr(torch.clamp(free, 0, 1), gt))
        if trainer.forms_image:
            true = true_colour_photo(trainer, i, image if free is None else free).clamp(0, 1)
            write_image(out / "truecolour" / f"{stem}.png", true.cpu().numpy())
            write_image(out / "truecolour" / f"{stem}.exr", true.cpu().numpy())
            if gt is not None:
                true_scores.append(psnr(true, gt))
    if true_scores:
        result["psnr_truecolour_gt"] = float(np.mean(true_scores))
    if captured:
        result["psnr_captured_gt"] = float(np.mean(captured))
    if cleaned:
        result["psnr_decaustic_gt"] = float(np.mean(cleaned))
    return result


@torch.no_grad()
def true_colour_photo(trainer, index: int, image: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) a training view's photo (sRGB) taken out of the water along the model's range
    at each pixel (:func:`~..model.medium.out_of_water`, the direct signal's gain capped)."""
    out = trainer.render_output(index, seen=False)
    cam = trainer.data.view(index, 1)[0]
    rng_t = Medium.range_of(out.alpha, out.depth, trainer.ray_len(cam))
    rng = rng_t.cpu().numpy()
    true = srgb_to_linear(image.clamp(0, 1)).cpu().numpy()
    if trainer.medium is not None:
        true = out_of_water(true, rng, trainer.medium.values())
    if trainer.lamp is not None:   # evenly lit: the lamp's light taken out, its gain capped as the water's
        gain = torch.exp(trainer.lamp_log_gain_of(cam, rng_t)).cpu().numpy()[..., None]
        true = true / np.maximum(gain, 1.0 / MAX_GAIN)
    return linear_to_srgb(torch.from_numpy(true.astype(np.float32)))


def _write_models(trainer, out: Path) -> None:
    """``medium.json`` and ``lamp.json`` (see the module), for the models the run kept."""
    if trainer.medium is not None:
        with atomic_path(out / "medium.json", "medium") as tmp:
            tmp.write_text(json.dumps({
                "model": "seen = J exp(-attenuation r) + veil (1 - exp(-backscatter r)), per linear sRGB channel, "
                         "r the range along the ray in scene units (metres where the survey's poses are in metres)",
                **trainer.medium_summary()}, indent=2))
    if trainer.lamp is not None:
        with atomic_path(out / "lamp.json", "lamp") as tmp:
            tmp.write_text(json.dumps({
                "model": "seen = J L, log L = sum_k pattern[k] x^i y^j + fall log(r / r0) + attenuation (r - r0), in "
                         "linear light; x, y the pixel's position from the principal point in half-widths of the "
                         "image, terms (i, j) with 1 <= i + j <= 4 in the order (1,0), (0,1), (2,0), (1,1), (0,2), ...; "
                         "r the range along the ray in scene units", **trainer.lamp_summary()}, indent=2))
