"""The survey as the trainer sees it: :class:`TrainData` loads it, holds out every Nth image
by sorted name (LLFF) and keeps an image pyramid for coarse-to-fine training.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from ..errors import RecGSError
from ..io.colmap import Scene
from ..model.cameras import Camera

#: Smallest image side (pixels) accepted after downscaling.
MIN_IMAGE_SIDE = 8


def holdout_split(names: list[str], every: int) -> tuple[list[int], list[int]]:
    """(train indices, test indices) into ``sorted(names)`` order: every ``every``-th image
    (0, every, 2*every, ...) is held out, as in LLFF/Mip-NeRF 360; ``every`` = 0 keeps all."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    if every <= 0:
        return order, []
    test = [i for k, i in enumerate(order) if k % every == 0]
    train = [i for k, i in enumerate(order) if k % every != 0]
    return train, test


class TrainData:
    """Cameras and images of a survey for training and evaluation.

    Images are read once per pyramid level (OIIO box filter) and kept as (H, W, 3) float32
    tensors. Cameras are scaled to match each level.
    """

    def __init__(self, scene: Scene, downscale: int, holdout_every: int, device: str = "cpu",
                 gt_scene: Optional[Scene] = None):
        self.scene = scene
        self.gt_scene = gt_scene
        self.downscale = downscale
        self.device = device
        names = [c.name for c in scene.cameras]
        self.train_ids, self.test_ids = holdout_split(names, holdout_every)
        if not self.train_ids:
            raise RecGSError(f"{scene.image_dir}: no training images left after holding out every "
                             f"{holdout_every}th image")
        for cam in scene.cameras:
            w, h = round(cam.width / downscale), round(cam.height / downscale)
            if min(w, h) < MIN_IMAGE_SIDE:
                raise RecGSError(f"{scene.image_path(cam)}: downscale {downscale} would make this "
                                 f"{cam.width}x{cam.height} image {w}x{h}, below {MIN_IMAGE_SIDE} px")
        self._cache: dict[tuple[int, int], tuple[Camera, torch.Tensor]] = {}

    def view(self, index: int, level: int = 1) -> tuple[Camera, torch.Tensor]:
        """(camera, image (H, W, 3)) of camera ``index`` at extra downscale ``level``."""
        key = (index, level)
        if key not in self._cache:
            cam = self.scene.cameras[index]
            f = self.downscale * level
            img = self.scene.load_image(cam, downscale=f)
            self._cache[key] = (cam.resized(img.shape[1], img.shape[0]), torch.from_numpy(img).to(self.device))
        return self._cache[key]

    def gt_view(self, index: int) -> Optional[torch.Tensor]:
        """Ground-truth image (H, W, 3) of camera ``index`` at the training resolution, if any."""
        if self.gt_scene is None:
            return None
        key = (index, "gt")
        if key not in self._cache:
            cam = self.gt_scene.cameras[index]
            self._cache[key] = (cam, torch.from_numpy(self.gt_scene.load_image(cam, self.downscale)).to(self.device))
        return self._cache[key][1]

    def load_all(self, level: int = 1) -> None:
        """Read every image a run uses now: the training views at ``level``, the held-out views
        at the training size and the ground truth. A job calls this before it writes anything,
        so an image whose header reads but whose pixels do not (a cut-off PNG) stops it with
        an :class:`~..errors.ImageError` naming the file instead of at some later step. The
        images stay cached, as training would have cached them on first use."""
        for i in self.train_ids:
            self.view(i, level)
        for i in self.test_ids:
            self.view(i, 1)
        if self.gt_scene is not None:
            for i in range(len(self.gt_scene.cameras)):
                self.gt_view(i)

    def drop_level(self, level: int) -> None:
        for key in [k for k in self._cache if k[1] == level]:
            del self._cache[key]


def view_tensors(cam: Camera, device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor(cam.viewmat, dtype=torch.float32, device=device),
            torch.tensor(cam.K, dtype=torch.float32, device=device))

def resample(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W, C) or (H, W) image area-averaged to ``height x width`` (returned as is when
    it already has that size): full-resolution targets and weights at a pyramid level."""
    if image.shape[:2] == (height, width):
        return image
    x = image.unsqueeze(-1) if image.dim() == 2 else image
    x = torch.nn.functional.adaptive_avg_pool2d(x.permute(2, 0, 1), (height, width)).permute(1, 2, 0)
    return x.squeeze(-1) if image.dim() == 2 else x


def resolve_image_dir(scene_dir: Path, images) -> Path:
    """An image folder given absolute, relative to the working directory, or by its name
    inside the scene folder (``clean``)."""
    p = Path(images)
    if p.is_absolute() or (p.is_dir() and not (scene_dir / p).is_dir()):
        return p
    return scene_dir / p


def default_gt_dir(scene_dir: str | Path) -> Optional[Path]:
    """The survey's ground-truth folder (``clean/``, as tools/make_survey.py writes) if any."""
    d = Path(scene_dir) / "clean"
    return d if d.is_dir() else None
