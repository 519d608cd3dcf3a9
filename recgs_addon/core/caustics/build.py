"""Build the training method a run asks for (``CausticConfig.mode``)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..errors import RecGSError
from ..model.gaussians import GaussianSet
from ..train.config import TrainConfig
from ..io.frames import read_frame_times
from ..train.trainer import Trainer, load_data
from .baselines import Filter2D, Joint
from .config import ADDED_ESTIMATORS, CausticConfig
from .light import survey_light
from .method import Method
from .recgs import RecGS


def make_method(scene_dir: str | Path, cfg: TrainConfig, ccfg: CausticConfig, images: Optional[str | Path] = None,
                gaussians: Optional[GaussianSet] = None, gt_images: Optional[str | Path] = None) -> Method:
    """Load a survey and build the method of ``ccfg.mode``; all input checks happen here,
    before any work (the method's settings here, the trainer's in :func:`load_data`). Where a
    lamp may be modelled or RecGS looks for caustics, the survey's light is looked at first
    (light.py) and given to the trainer.
    ``gt_images``: ground-truth images with the same names, for scoring (required by
    ``oracle``, which trains on them)."""
    ccfg.validate()
    if ccfg.mode == "oracle":
        if gt_images is None:
            raise RecGSError(f"{scene_dir}: mode oracle trains on ground-truth images, but there is no "
                             "clean/ folder (pass --gt-images DIR)")
        images = gt_images
    data = load_data(scene_dir, cfg, images=images, gt_images=gt_images)
    if ccfg.mode == "oracle" and gaussians is None:
        # 3DGS on the clean photos, as if the survey had been solved from them: its sparse
        # points coloured by them, not by the photos as filmed (a lamp's dark corners, the water)
        data.scene.colors = data.point_colours(data.scene.colors)
    light = None
    if cfg.lamp != "off" or (ccfg.mode == "recgs" and ccfg.caustics == "auto"):
        light = survey_light(data, times=read_frame_times(data.scene.scene_dir) or {}).summary()
    trainer = Trainer(data, cfg, gaussians, light=light)
    recgs = ADDED_ESTIMATORS.get(ccfg.estimator, RecGS)   # an estimator a benchmark compares
    kind = {"recgs": recgs, "filter2d": Filter2D, "joint": Joint}.get(ccfg.mode, Method)
    return kind(trainer, ccfg)
