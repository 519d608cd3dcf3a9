"""Where the caustics go: per Gaussian, how many training views carry it.

A Gaussian's blending weight in a view is ``sum over pixels of alpha_i T_i`` (in pixels): the
share of the view's colour it supplies, which the rasterizer's backward adds up
(``render(..., weights=...)``; training's density control reads the same). A Gaussian
"carries" a view where that weight is at least ``min_weight`` pixels. A Gaussian
carried by few views has its colour fitted to the light of those few photos: with moving
caustics, to their caustics (docs/method.md).
"""
from __future__ import annotations

import numpy as np
import torch

from ..render.rasterizer import render
from ..train.data import view_tensors


#: Views are rendered at most this many pixels on the long side (a weight is a share of the
#: view; counted in training-resolution pixels, it hardly depends on the render's size, and a
#: survey of 150 frames at 1600 px would take over an hour at full size).
SUPPORT_SIDE = 400


def blending_weights(trainer, index: int, max_side: int = SUPPORT_SIDE) -> torch.Tensor:
    """(N,) blending weight (pixels at the training resolution) of every Gaussian in training
    view ``index``, rendered at most ``max_side`` pixels on the long side."""
    w, h = trainer.data.sizes[index]
    level = max(1, -(-max(w, h) // max_side))
    cam = trainer.data.camera(index, level)
    viewmat, K = view_tensors(cam, trainer.device)
    p = {n: v.detach() for n, v in trainer.params.items()}
    dc = p["sh_dc"].clone().requires_grad_(True)   # something for the backward to reach
    k = p["sh_rest"].shape[1] if trainer.sh_degree else 0
    weights = torch.zeros(dc.shape[0], dtype=torch.float32, device=dc.device)
    out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], (dc, p["sh_rest"][:, :k]),
                 viewmat, K, cam.width, cam.height, sh_degree=trainer.sh_degree,
                 compiled=trainer.compiler.compiled(),   # the training's own path (numba's: 2.5x eager)
                 weights=weights)
    out.rgb.sum().backward()
    return weights * trainer.data.pixel_area(index, cam)


def view_support(trainer, min_weight: float = 1.0) -> np.ndarray:
    """(N,) int: the number of training views that carry each Gaussian."""
    count = torch.zeros(trainer.params["means"].shape[0], dtype=torch.int64, device="cpu")
    for i in trainer.data.train_ids:
        count += (blending_weights(trainer, i) >= min_weight).cpu()
    return count.numpy()


def support_summary(support: np.ndarray) -> dict:
    """Median views per Gaussian, the share carried by at most 2 views and by none, and the
    histogram (views -> Gaussians) up to 10 views (the last bin holds 10 or more)."""
    if support.size == 0:
        return {}
    hist = np.bincount(np.minimum(support, 10), minlength=11)
    return {"median_views": float(np.median(support)), "share_le2": float(np.mean(support <= 2)),
            "share_none": float(np.mean(support == 0)), "histogram": [int(h) for h in hist]}
