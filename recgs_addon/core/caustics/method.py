"""A training method: the trainer plus what a caustic method adds, behind one interface the
``train`` command, the benchmarks and the outputs use.

:class:`Method` is plain 3DGS (``3dgs``, or ``oracle`` trained on the ground-truth photos).
The caustic methods (``recgs.py``, ``baselines.py``) subclass it: they fill the trainer's
:class:`~..train.objective.Objective` and, for RecGS, drive the trainer in segments.
``build.make_method`` builds the method ``CausticConfig.mode`` names.
"""
from __future__ import annotations

from dataclasses import asdict
from typing import Callable, Optional

import torch

from ..train.trainer import Progress, Trainer
from .config import CausticConfig


class Method:
    """Plain 3DGS: the trainer as it is."""

    def __init__(self, trainer: Trainer, ccfg: CausticConfig):
        self.trainer, self.ccfg = trainer, ccfg

    @property
    def data(self):
        return self.trainer.data

    def run(self, on_progress: Optional[Callable[[Progress], None]] = None,
            should_stop: Optional[Callable[[], bool]] = None,
            on_checkpoint: Optional[Callable[[Trainer], None]] = None, checkpoint_every_s: float = 60.0) -> str:
        """Train until done or ``should_stop()``; returns why it stopped (``"stopped"``: told to)."""
        return self.trainer.run(on_progress, should_stop, on_checkpoint, checkpoint_every_s)

    def decaustic_image(self, index: int) -> Optional[torch.Tensor]:
        """Caustic-free estimate (H, W, 3, not clipped) of a training view's photo; None for
        methods that make none."""
        return None

    def finishing_renders(self) -> int:
        """Renders of the model the method makes after training (its end-of-run choice, its
        caustic-free photos), for the time limit's reserve (``Trainer.finishing_reserve``)."""
        return 0

    def takes_light_off(self) -> bool:
        """Whether the method's caustic-free photos differ from the photos: False for methods
        that make none, and for a caustic method that found no light to take off (its photos are
        caustic-free as they are, so no copies of them are written)."""
        return type(self).decaustic_image is not Method.decaustic_image

    def finishing_images(self) -> int:
        """Images the method writes after training, for the reserve: a caustic map and the
        caustic-free photo (PNG and EXR) of every training view where it takes light off."""
        return 3 * len(self.data.train_ids) if self.takes_light_off() else 0

    def state_bytes(self) -> int:
        """Memory the method's per-view state (caustic maps, targets) takes at its largest."""
        return 0

    def planned_work(self):
        """What the method's work besides training will cost (a ``cost.PassCost``: seconds and
        peak bytes), or None where it has none worth planning."""
        return None

    def fit_work(self, time_limit_s, room_bytes) -> Optional[str]:
        """Given the run's time limit (seconds, or None) and the memory left once training has
        what it needs (bytes, or None), give up the work :meth:`planned_work` names where it does
        not fit, and say why (None: it fits, or there is none)."""
        return None

    def summary(self) -> dict:
        """What the method adds to a run's metrics."""
        return {"best_step": self.trainer.best_step}

    def state_dict(self) -> dict:
        s = self.trainer.state_dict()
        s["caustic_config"] = asdict(self.ccfg)
        return s

    def load_state_dict(self, s: dict) -> None:
        self.trainer.load_state_dict(s)
