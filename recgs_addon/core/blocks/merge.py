"""The blocks' Gaussians merged into one scene, and the merged scene scored.

Each block keeps only the Gaussians whose centre lies in its own cell (the margin it trained
with is the neighbours' to keep), so every point of the seabed is held by one block's
Gaussians. Blocks whose SH degrees differ are merged at the highest, the others' higher
coefficients zero (the same colours). The scene is scored on the survey's held-out photos,
those that cross a seam apart from the others: a seam that shows costs them, not the rest.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..model.cells import Cell
from ..model.gaussians import GaussianSet
from ..render.rasterizer import render
from ..train.data import TrainData, view_tensors
from ..train.losses import psnr


def merge_gaussians(parts: list[tuple[GaussianSet, Cell]]) -> tuple[GaussianSet, list[int]]:
    """(one GaussianSet, how many each part kept): each part's Gaussians inside its cell."""
    kept = [g.subset(cell.contains(g.means)) for g, cell in parts]
    if not kept:
        return GaussianSet.empty(), []
    degree = max(g.sh_degree for g in kept)
    kept = [g.with_sh_degree(degree) for g in kept]
    merged = GaussianSet(*(np.concatenate([getattr(g, n) for g in kept])
                           for n in ("means", "log_scales", "quats", "logit_opacities", "sh")))
    return merged, [len(g) for g in kept]


@dataclass
class ViewScore:
    name: str
    psnr: float                     # against the photo as captured
    psnr_gt: Optional[float]        # against the ground truth, where the survey has one
    seam: bool                      # the photo crosses a seam


@torch.no_grad()
def score_views(g: GaussianSet, data: TrainData, ids: list[int], seam_names: set[str],
                keep: Optional[dict] = None) -> list[ViewScore]:
    """PSNR of ``g``'s render of each view ``ids`` of ``data`` (its training size) against the
    photo and the ground truth. ``keep``: a dict that receives, for the views that cross a seam,
    their render beside their photo (H, 2W, 3) uint8 by name."""
    t = {n: torch.from_numpy(getattr(g, n)) for n in ("means", "log_scales", "quats", "logit_opacities", "sh")}
    scores = []
    for i in ids:
        cam, photo = data.view(i, 1)
        viewmat, K = view_tensors(cam, "cpu")
        rgb = render(t["means"], t["log_scales"], t["quats"], t["logit_opacities"], t["sh"], viewmat, K,
                     cam.width, cam.height, sh_degree=g.sh_degree).rgb.clamp(0, 1)
        gt = data.gt_view(i)
        name = data.scene.cameras[i].name
        if keep is not None and name in seam_names:
            keep[name] = (torch.cat([rgb, photo.clamp(0, 1)], dim=1) * 255 + 0.5).to(torch.uint8).numpy()
        scores.append(ViewScore(name, psnr(rgb, photo), None if gt is None else psnr(rgb, gt), name in seam_names))
    return scores


def summarise(scores: list[ViewScore]) -> dict:
    """Mean PSNRs of all held-out views, of those that cross a seam and of the others."""
    def mean(vals):
        vals = [v for v in vals if v is not None]
        return float(np.mean(vals)) if vals else None

    out = {"views": len(scores), "seam_views": sum(s.seam for s in scores)}
    for key in ("psnr", "psnr_gt"):
        out[key] = mean([getattr(s, key) for s in scores])
        out[key + "_seam"] = mean([getattr(s, key) for s in scores if s.seam])
        out[key + "_inner"] = mean([getattr(s, key) for s in scores if not s.seam])
    return out
