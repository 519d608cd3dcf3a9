"""The RecGS paper's baselines, as methods:

* ``filter2d``: fit ``I - lowpass(I - mean I)`` per image from the start (no 3D reasoning);
* ``joint``: learn a per-image ``k x k`` Fourier field with the Gaussians, fitting
  ``I - field_i`` (the alternative the paper reports as failing: the fields and the Gaussians
  trade the low frequencies of the scene between them).

Held-out views are scored with their caustics compensated as RecGS does (``recgs.py``).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..train.objective import FixedTargets, Objective
from ..train.trainer import Trainer
from . import fft_filter
from .config import CausticConfig
from .estimate import compensate_caustics
from .method import Method


class Filter2D(Method):
    def __init__(self, trainer: Trainer, ccfg: CausticConfig):
        super().__init__(trainer, ccfg)
        self.k: Optional[int] = ccfg.caustic_k or None
        self.targets = FixedTargets(reference=lambda index, image, render: fft_filter.filter2d(
            image, self.k or fft_filter.DEFAULT_K))
        data = self.data
        if self.k is None:
            imgs = [data.view(i, 1)[1] for i in data.train_ids]
            self.k = fft_filter.choose_k([m - m.mean(dim=(0, 1), keepdim=True) for m in imgs])
        for i in data.train_ids:
            self.targets.put(i, fft_filter.filter2d(data.view(i, 1)[1], self.k))
        trainer.set_objective(self.targets)

    def decaustic_image(self, index: int) -> torch.Tensor:
        return self.targets.get(index)

    def state_bytes(self) -> int:
        return self.targets.bytes_per_pixel() * self.data.training_pixels()

    def summary(self) -> dict:
        return {**super().summary(), "caustic_k": self.k}


class _FieldObjective(Objective):
    """Fit ``I - field_i``; the fields are learnt with the Gaussians."""

    def __init__(self, fields: "CausticFields", lr: float, compensate):
        self.fields, self.lr, self._compensate = fields, lr, compensate

    def target(self, index, image, render):
        return image - self.fields.field(index, image.shape[0], image.shape[1]), None

    def reference(self, index, image, render):
        return self._compensate(image, render)

    def param_groups(self):
        return [{"params": list(self.fields.parameters()), "lr": self.lr}]


class Joint(Method):
    def __init__(self, trainer: Trainer, ccfg: CausticConfig):
        super().__init__(trainer, ccfg)
        self.k = ccfg.caustic_k or fft_filter.DEFAULT_K
        self.fields = CausticFields(len(self.data.scene.cameras), self.k).to(trainer.device)
        trainer.set_objective(_FieldObjective(self.fields, trainer.cfg.lr_sh_dc * 2, self._compensate))

    def _compensate(self, image, render):
        return compensate_caustics(image, render, self.k, self.ccfg.caustic_model, self.ccfg.caustic_dc)

    @torch.no_grad()
    def decaustic_image(self, index: int) -> torch.Tensor:
        image = self.data.view(index, 1)[1]
        return image - self.fields.field(index, image.shape[0], image.shape[1])

    def summary(self) -> dict:
        return {**super().summary(), "caustic_k": self.k}

    def state_dict(self) -> dict:
        s = super().state_dict()
        s["caustic"] = {"fields": self.fields.state_dict()}
        return s

    def load_state_dict(self, s: dict) -> None:
        super().load_state_dict(s)
        self.fields.load_state_dict(s["caustic"]["fields"])


class CausticFields(torch.nn.Module):
    """Per-image low-frequency fields for the ``joint`` baseline: ``k x k`` complex Fourier
    coefficients per image and channel, learnt with the Gaussians. ``field(i, H, W)`` is the
    real part of the inverse FFT with amplitudes independent of the resolution
    (``norm="forward"``), so the same coefficients serve every pyramid level."""

    def __init__(self, n_images: int, k: int = fft_filter.DEFAULT_K, channels: int = 3):
        super().__init__()
        self.r = fft_filter.check_k(k)
        self.k = k
        self.coef = torch.nn.Parameter(torch.zeros(n_images, channels, k, k, 2, device="cpu"))

    def field(self, index: int, height: int, width: int) -> torch.Tensor:
        """(H, W, C) field of image ``index``."""
        r = self.r
        dev = self.coef.device
        f = torch.arange(-r, r + 1, device=dev)
        rows = torch.remainder(f, height)
        cols = torch.remainder(f, width)
        coef = torch.view_as_complex(self.coef[index])  # (C, k, k)
        c = coef.shape[0]
        spec = torch.zeros(c, height * width, dtype=coef.dtype, device=dev)
        flat = (rows.unsqueeze(1) * width + cols.unsqueeze(0)).reshape(-1)
        spec = spec.index_add(1, flat, coef.reshape(c, -1))
        out = torch.fft.ifft2(spec.view(c, height, width), norm="forward").real
        return out.permute(1, 2, 0)
