"""The survey as the trainer sees it: :class:`TrainData` loads it, holds out every Nth image
by sorted name and keeps an image pyramid for coarse-to-fine training.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import RecGSError
from ..io.colmap import Scene
from ..io.images import training_size
from ..model.cameras import Camera

#: Smallest image side (pixels) accepted after downscaling.
MIN_IMAGE_SIDE = 8
#: Training views (spread over the survey) whose pixels colour the sparse points
#: (:meth:`TrainData.point_colours`).
COLOUR_VIEWS = 64


def holdout_split(names: list[str], every: int, held: Optional[set] = None) -> tuple[list[int], list[int]]:
    """(train indices, test indices) into ``sorted(names)`` order: every ``every``-th image is
    held out, starting half a period in (every // 2, then every // 2 + every, ...); ``every`` =
    0 keeps all. ``held``: the names held out instead (a block of a survey: the survey's own
    held-out photos that fall in it). LLFF / Mip-NeRF 360 start at the first image, but a survey's first and last
    shots see seabed that no other shot does (the start of the first line, the end of the last):
    a held-out view there scores a hole, not the model."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    if held is not None:
        return [i for i in order if names[i] not in held], [i for i in order if names[i] in held]
    if every <= 0:
        return order, []
    first = every // 2
    test = [i for k, i in enumerate(order) if k % every == first]
    train = [i for k, i in enumerate(order) if k % every != first]
    return train, test


def as_float(image: torch.Tensor) -> torch.Tensor:
    """A compact image (uint8 0-255, or float16) as float32 in [0, 1] intensity."""
    if image.dtype == torch.uint8:
        return image.float().div_(255.0)
    return image.float()


class TrainData:
    """Cameras and images of a survey for training and evaluation.

    Every photo is decoded once, at its training size (the file's size divided by
    ``downscale``, its long side capped at ``max_side``; :func:`~..io.images.training_size`),
    and kept compact: uint8 for 8-bit files, float16 otherwise. :meth:`view` hands out float32
    copies; the coarse levels of the pyramid are area averages of the training size, kept
    (as float16) while in use. Cameras are scaled to match each level.
    """

    def __init__(self, scene: Scene, downscale: int, holdout_every: int, device: str = "cpu",
                 gt_scene: Optional[Scene] = None, max_side: int = 0, test_names: Optional[list[str]] = None):
        self.scene = scene
        self.gt_scene = gt_scene
        self.downscale = downscale
        self.max_side = max_side
        self.device = device
        names = [c.name for c in scene.cameras]
        self.train_ids, self.test_ids = holdout_split(names, holdout_every,
                                                      None if test_names is None else set(test_names))
        if not self.train_ids:
            raise RecGSError(f"{scene.image_dir}: no training images left after holding out every "
                             f"{holdout_every}th image")
        self.sizes = [training_size(c.width, c.height, downscale, max_side) for c in scene.cameras]
        for cam, (w, h) in zip(scene.cameras, self.sizes):
            if min(w, h) < MIN_IMAGE_SIDE:
                raise RecGSError(f"{scene.image_path(cam)}: downscale {downscale} would make this "
                                 f"{cam.width}x{cam.height} image {w}x{h}, below {MIN_IMAGE_SIDE} px")
        self._photos: dict[int, torch.Tensor] = {}     # compact, at the training size
        self._gt: dict[int, torch.Tensor] = {}
        self._levels: dict[tuple[int, int], torch.Tensor] = {}   # float16, coarser levels
        self._overlay = None          # overlay.Overlay, found on first use (:meth:`overlay`)
        self._overlay_size = None     # the training size it was found on
        self._valid: dict[tuple[int, int, int], Optional[torch.Tensor]] = {}

    def camera(self, index: int, level: int = 1) -> Camera:
        """Camera ``index`` scaled to its training size at extra downscale ``level``."""
        w, h = self.sizes[index]
        if level != 1:
            w, h = max(1, round(w / level)), max(1, round(h / level))
        return self.scene.cameras[index].resized(w, h)

    def _decode(self, scene: Scene, index: int) -> torch.Tensor:
        img = scene.load_image(scene.cameras[index], size=self.sizes[index], compact=True)
        return torch.from_numpy(img).to(self.device)

    def photo(self, index: int) -> torch.Tensor:
        """The compact photo (H, W, 3) of camera ``index`` at its training size."""
        if index not in self._photos:
            self._photos[index] = self._decode(self.scene, index)
        return self._photos[index]

    def point_colours(self, colours: np.ndarray, gain: Optional[Callable] = None) -> np.ndarray:
        """(M, 3) uint8 the sparse points' colours read from the training photos: each point seen
        in the training views (at most :data:`COLOUR_VIEWS` of them, spread over the survey; no
        occlusion test: a seabed seen from above) takes the least squares ``sum g_k I_k / sum
        g_k^2`` of its pixels ``I_k`` (linear light, nearest pixel, the photos at the training
        size) under a known light ``g_k`` there: ``gain(cam, u, v, rng)`` gives it for a view's
        pixel positions ``u``, ``v`` and ranges ``rng`` (K,) (None: 1, the plain mean). A point
        in none of them keeps its colour in ``colours`` (M, 3) uint8, divided by the light's
        median over the points that were seen."""
        from ..model.colour import linear_to_srgb, srgb_to_linear
        pts = np.asarray(self.scene.points, np.float64)
        colours = np.asarray(colours)
        if not len(pts):
            return colours
        ids = list(self.train_ids)
        ids = [ids[k] for k in np.unique(np.linspace(0, len(ids) - 1, min(len(ids), COLOUR_VIEWS)).round().astype(int))]
        num, den, lights = np.zeros((len(pts), 3)), np.zeros(len(pts)), []
        for i in ids:
            cam, img = self.view(i, 1)
            seen, u, v, rng = cam.in_view(pts)
            if not seen.size:
                continue
            g = np.ones(seen.size) if gain is None else np.asarray(gain(cam, u, v, rng), np.float64)
            px = img[torch.from_numpy(v.astype(np.int64)), torch.from_numpy(u.astype(np.int64))]
            num[seen] += g[:, None] * srgb_to_linear(px.cpu().double()).numpy()
            den[seen] += g * g
            lights.append(g)
        lin = srgb_to_linear(torch.from_numpy(colours.astype(np.float64) / 255.0)).numpy()
        out = lin / max(float(np.median(np.concatenate(lights))) if lights else 1.0, 1e-3)
        seen = den > 0
        out[seen] = num[seen] / den[seen, None]
        return np.round(linear_to_srgb(torch.from_numpy(np.clip(out, 0.0, 1.0))).numpy() * 255).astype(np.uint8)

    def view(self, index: int, level: int = 1) -> tuple[Camera, torch.Tensor]:
        """(camera, image (H, W, 3) float32) of camera ``index`` at extra downscale ``level``."""
        cam = self.camera(index, level)
        if level == 1:
            return cam, as_float(self.photo(index))
        key = (index, level)
        if key not in self._levels:
            photo = self.photo(index)
            small = resample(as_float(photo), cam.height, cam.width)
            # kept compact like the photos: float16 is exact to 2.4e-4 in [0, 1], a sixteenth of
            # an 8-bit photo's own step (float images beyond float16's range stay float32)
            self._levels[key] = small if photo.dtype == torch.float32 else small.half()
        return cam, as_float(self._levels[key])

    def gt_view(self, index: int) -> Optional[torch.Tensor]:
        """Ground-truth image (H, W, 3) float32 of camera ``index`` at the training size, if any."""
        if self.gt_scene is None:
            return None
        if index not in self._gt:
            self._gt[index] = self._decode(self.gt_scene, index)
        return as_float(self._gt[index])

    def load_all(self, level: int = 1, on_image: Optional[Callable[[int, int], None]] = None,
                 threads: Optional[int] = None) -> None:
        """Read every image a run uses now: the photos, the ground truth, and the training
        views at ``level``. A job calls this before it writes anything, so an image whose
        header reads but whose pixels do not (a cut-off PNG) stops it with an
        :class:`~..errors.ImageError` naming the file instead of at some later step. Files are
        decoded on ``threads`` threads (default: the machine's cores, at most 8); the first
        file in the survey's order that fails is the one reported. ``on_image(done, total)``
        follows the progress."""
        jobs = [(self.scene, i, self._photos) for i in sorted(self.train_ids + self.test_ids)
                if i not in self._photos]
        if self.gt_scene is not None:
            jobs += [(self.gt_scene, i, self._gt) for i in range(len(self.gt_scene.cameras)) if i not in self._gt]
        threads = threads or min(8, os.cpu_count() or 1)
        with ThreadPoolExecutor(max(1, threads)) as pool:
            futures = [pool.submit(self._decode, scene, i) for scene, i, _ in jobs]
            try:
                for done, ((_, i, store), fut) in enumerate(zip(jobs, futures), 1):
                    store[i] = fut.result()
                    if on_image is not None:
                        on_image(done, len(jobs))
            finally:
                for fut in futures:
                    fut.cancel()
        if level != 1:
            for i in self.train_ids:
                self.view(i, level)

    def overlay(self):
        """The survey's burned-in overlay (``overlay.find_overlay``), found once on the frames of
        its most common training size (at most ``overlay.MAX_PAIRS`` consecutive pairs by name,
        spread over the survey, at ``overlay.OVERLAY_SIDE``)."""
        if self._overlay is None:
            from collections import Counter

            from . import overlay as ov
            ids = sorted(self.train_ids + self.test_ids, key=lambda i: self.scene.cameras[i].name)
            size = Counter(self.sizes[i] for i in ids).most_common(1)[0][0]
            ids = [i for i in ids if self.sizes[i] == size]
            starts = list(range(len(ids) - 1))
            if len(starts) > ov.MAX_PAIRS:
                starts = [starts[int(k * len(starts) / ov.MAX_PAIRS)] for k in range(ov.MAX_PAIRS)]
            w, h = size
            f = min(1.0, ov.OVERLAY_SIDE / max(w, h))
            hs, ws = max(1, round(h * f)), max(1, round(w * f))
            frames = [resample(as_float(self.photo(ids[k + d])).mean(-1), hs, ws).cpu() for k in starts for d in (0, 1)]
            self._overlay, self._overlay_size = ov.find_overlay(frames), size
        return self._overlay

    def valid(self, index: int, height: int, width: int) -> Optional[torch.Tensor]:
        """(height, width) bool on the view's device: the pixels of view ``index`` at that size
        that count (off the survey's burned-in overlay), or None where every pixel does."""
        key = (index, height, width)
        if key not in self._valid:
            from .overlay import mask_at
            ov = self.overlay()
            m = mask_at(ov, height, width) if self.sizes[index] == self._overlay_size else None
            self._valid[key] = None if m is None else m.to(self.device)
        return self._valid[key]

    def drop_level(self, level: int) -> None:
        for key in [k for k in self._levels if k[1] == level]:
            del self._levels[key]

    def image_bytes(self) -> int:
        """Bytes the decoded images hold now (photos, ground truth, pyramid levels)."""
        return sum(t.numel() * t.element_size()
                   for d in (self._photos, self._gt, self._levels) for t in d.values())

    def training_pixels(self, ids: Optional[list[int]] = None) -> int:
        """Pixels of the training views (``ids``, default all) at their training size."""
        return sum(self.sizes[i][0] * self.sizes[i][1] for i in (self.train_ids if ids is None else ids))

    def pixel_area(self, index: int, cam) -> float:
        """Training-resolution pixels of view ``index`` per pixel of ``cam`` (a render of it at
        a pyramid level or another size)."""
        w, h = self.sizes[index]
        return (w * h) / (cam.width * cam.height)


def block_scene(scene: Scene, block: dict) -> Scene:
    """The part of ``scene`` that one block of a survey trains on: the cameras the block names
    (``train`` and ``test``), the sparse points in its ``cell`` (margin included)."""
    from dataclasses import replace

    from ..model.cells import Cell

    wanted = set(block["train"]) | set(block["test"])
    cameras = [c for c in scene.cameras if c.name in wanted]
    missing = sorted(wanted - {c.name for c in cameras})
    if missing:
        raise RecGSError(f"{scene.model_dir}: block {block.get('name', '?')} names {len(missing)} image(s) the "
                         f"survey does not hold (first: {missing[0]}); split the survey again")
    keep = Cell.from_dict(block["cell"]).contains(scene.points)
    return replace(scene, cameras=cameras, points=scene.points[keep], colors=scene.colors[keep])


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
