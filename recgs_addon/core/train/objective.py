"""What the trainer fits: the one seam between the trainer and the methods that change it.

The trainer (``trainer.py``) knows nothing of caustics. Per view it asks its
:class:`Objective` two questions:

* ``target(index, image, render)``: for a *training* view, the image the loss compares the
  render against and the weight of each pixel (which pixels count), given the photo and the
  step's render (detached: weights are chosen, not learnt);
* ``reference(index, image, render)``: for a *held-out* view, the image a render is scored
  against for the run's own decisions (growth, SH degree, plateau).

plus ``use_ssim`` (whether the loss keeps its SSIM term), ``loss_kind`` (L1 or L2 data term) and ``param_groups()``: extra tensors fitted with the Gaussians (the ``joint`` baseline's
per-view fields), stepped by a second Adam the trainer owns.

The base class fits the photos as captured, every pixel counting: plain 3DGS. The caustic
methods (core/caustics/) fill it with caustic-free estimates and robust weights; they change
it between training segments, never from inside a step.

Shapes: ``image`` and targets are (H, W, 3) float32 tensors at the step's resolution;
weights are (H, W) float32 in [0, 1] or ``None`` (all pixels weigh 1).
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from .data import resample


class Objective:
    """Fit the photos as captured; every pixel counts."""

    #: whether the loss keeps its SSIM term (``TrainConfig.lambda_dssim``) for this objective
    use_ssim = True
    #: the data term: "l1" (the median of what the views show), "l2" (their mean), or a function
    #: (render, target) -> (H, W, 3) per-pixel term (losses.training_loss)
    loss_kind = "l1"

    def target(self, index: int, image: torch.Tensor,
               render: torch.Tensor) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """(target (H, W, 3), weight (H, W) or None) for training view ``index`` whose photo at
        the step's resolution is ``image`` and whose render (detached) is ``render``."""
        return image, None

    def reference(self, index: int, image: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
        """What held-out view ``index``'s ``render`` is scored against (default: its photo)."""
        return image

    def param_groups(self) -> list[dict]:
        """Extra tensors the trainer optimises with the Gaussians, as Adam parameter groups
        (``{"params": [...], "lr": ...}``; default: none)."""
        return []


class FixedTargets(Objective):
    """Per-view replacement targets (and optional weights) held at full training resolution and
    area-averaged to each pyramid level; views without one fit their photo, all pixels counting.

    :meth:`put` sets a view's target (H, W, 3) and weight (H, W); they are kept as float16
    (half the memory of float32, a 2^-11 step at full scale: an eighth of an 8-bit grey
    level), so a survey of hundreds of views holds them beside its photos. :meth:`get` gives
    the target back as float32. Targets may change between training segments (the caustic
    methods do; ``clear()`` returns to the photos). ``reference(index, image, render)``,
    optional: what held-out view ``index``'s render is scored against."""

    def __init__(self, reference: Optional[Callable[[int, torch.Tensor, torch.Tensor], torch.Tensor]] = None):
        self.images: dict[int, torch.Tensor] = {}
        self.weights: dict[int, torch.Tensor] = {}
        self._reference = reference

    def put(self, index: int, image: torch.Tensor, weight: Optional[torch.Tensor] = None) -> None:
        self.images[index] = image.detach().to(torch.float16)
        if weight is None:
            self.weights.pop(index, None)
        else:
            self.weights[index] = weight.detach().to(torch.float16)

    def get(self, index: int) -> Optional[torch.Tensor]:
        """View ``index``'s target (H, W, 3) float32 at full training resolution, or None."""
        t = self.images.get(index)
        return None if t is None else t.float()

    def reference(self, index, image, render):
        return image if self._reference is None else self._reference(index, image, render)

    def target(self, index, image, render):
        h, w = image.shape[:2]
        t = self.images.get(index)
        wt = self.weights.get(index)
        return (image if t is None else resample(t.float(), h, w)), (None if wt is None else resample(wt.float(), h, w))

    def clear(self) -> None:
        self.images.clear()
        self.weights.clear()

    @staticmethod
    def bytes_per_pixel() -> int:
        """Memory a view's target takes per pixel (three float16 channels)."""
        return 6
