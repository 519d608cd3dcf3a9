"""Build the training method a run asks for (``CausticConfig.mode``)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..errors import RecGSError
from ..model.gaussians import GaussianSet
from ..train.config import TrainConfig
from ..train.trainer import make_trainer
from .baselines import Filter2D, Joint
from .config import CausticConfig
from .method import Method
from .recgs import RecGS


def make_method(scene_dir: str | Path, cfg: TrainConfig, ccfg: CausticConfig, images: Optional[str | Path] = None,
                gaussians: Optional[GaussianSet] = None, gt_images: Optional[str | Path] = None) -> Method:
    """Load a survey and build the method of ``ccfg.mode``; all input checks happen here,
    before any work (the method's settings here, the trainer's in :func:`make_trainer`).
    ``gt_images``: ground-truth images with the same names, for scoring (required by
    ``oracle``, which trains on them)."""
    ccfg.validate()
    if ccfg.mode == "oracle":
        if gt_images is None:
            raise RecGSError(f"{scene_dir}: mode oracle trains on ground-truth images, but there is no "
                             "clean/ folder (pass --gt-images DIR)")
        images = gt_images
    trainer = make_trainer(scene_dir, cfg, images=images, gaussians=gaussians, gt_images=gt_images)
    kind = {"recgs": RecGS, "filter2d": Filter2D, "joint": Joint}.get(ccfg.mode, Method)
    return kind(trainer, ccfg)
