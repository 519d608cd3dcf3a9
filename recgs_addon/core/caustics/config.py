"""Settings of the caustic methods (the trainer's own are in core/train/config.py).

``mode`` chooses the method: ``3dgs`` (plain, on the photos as captured), ``oracle`` (plain, on
the ground-truth photos: the upper bound), ``recgs`` (the recurrent loop, ``recgs.py``),
``filter2d`` and ``joint`` (the paper's baselines, ``baselines.py``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from ..errors import RecGSError

#: Every mode: its name in the panel and what it does (the command line's --mode, the panel's
#: Mode and the report take them from here).
MODE_INFO = {
    "3dgs": ("3DGS", "Plain Gaussian Splatting of the photos as they are (caustics included)"),
    "recgs": ("RecGS", "Gaussian Splatting with recurrent caustic removal (Zhang et al. 2024)"),
    "filter2d": ("2D Filter", "Remove caustics with the low-pass filter on each photo only, then train"),
    "joint": ("Joint", "Learn the caustic images together with the Gaussians"),
    "oracle": ("Oracle", "Train on the survey's caustic-free ground truth (clean/), for comparison"),
}
MODES = tuple(MODE_INFO)
#: Modes that train on caustic-free estimates (and write caustic maps).
CAUSTIC_MODES = ("recgs", "filter2d", "joint")
#: How RecGS estimates each view's caustics (estimators.py): ``auto`` chooses between the passes
#: and the paper's low-pass by the survey's views per point.
ESTIMATORS = ("auto", "lowpass", "passes")
#: Estimators kept for the record's comparisons (benchmarks/caustic_estimators), by name: the
#: :class:`.recgs.RecGS` subclass that makes their estimates. Empty unless a benchmark registers them.
ADDED_ESTIMATORS: dict = {}
#: The pass estimator's statistics (passes.py): each frame's light modelled, or the floor's mean.
PASS_STATISTICS = ("field", "floor")
#: Look frames (a video's frames between the keyframes, looks.json): gathered from where the survey has them, or not.
LOOKS = ("auto", "off")
#: Whether RecGS looks for caustics before removing any (light.py): ``auto`` removes them only
#: where the survey shows light that moves over the seabed; ``on`` runs the loop regardless.
FIND_CAUSTICS = ("auto", "on")


@dataclass
class CausticConfig:
    mode: str = "3dgs"
    caustics: str = "auto"               # recgs: auto = only where the survey shows caustics (light.py) | on
    caustic_k: int = 0                   # low-pass block size (odd; the paper: 9); 0 = from the residual spectrum
    caustic_dc: bool = False             # recgs: keep C's DC term (the paper); False: C has zero mean per view
    caustic_model: str = "additive"      # additive: I - C (paper) | multiplicative: I / exp(C_log)
    warmup: int = 3000                   # recgs: at most this many plain steps before the first recurrence
    warmup_share: Optional[float] = None  # recgs: ... and at most this share of the time limit
                                          # (None: the estimator's, recgs.WARMUP_SHARE)
    recurrence_patience: int = 2         # recgs: rounds in a row that hurt held-out views before C is dropped
    harm_tol: float = 0.5                # recgs: dB below the plain model's held-out PSNR that counts as hurting
    stall_ratio: float = 0.6             # recgs: C is not settling when its change shrinks by less than
    stall_growth: float = 0.15           # ... this per round while mean |C| grows by more than this
    recurrence_steps: int = 200          # recgs: optimisation steps per recurrence
    max_recurrences: int = 40
    recurrence_tol: float = 0.1          # stop when mean |dC| / mean |C| falls below this
    caustic_floor: float = 0.01          # recgs: C is dropped when mean |C| is below this (1 % of full scale)
    estimator: str = "auto"              # recgs: auto = from the survey's views per point (estimators.choose_estimator)
                                         # | lowpass: C = lowpass(I - render) (paper)
                                         # | passes: the floor of the light over the passes that saw each point (passes.py)
    pass_statistic: str = "field"        # passes: field = each frame's light modelled, then the colour | floor
    pass_min: int = 1                    # passes: independent passes a pixel needs (fewer: the low-pass target)
    looks: str = "auto"                  # passes: auto = gather the light also from the survey's look frames
                                         # (looks.json: a video's frames between the keyframes) | off
    fit_loss: str = "l1"                 # recgs: data term of the recurrences: l1 (paper; the views' median) | l2 (their mean)
    robust_k: float = 0.0                # recgs: trim pixels brighter than the render by > k robust sigmas; 0 = off (the paper)
    gain_restore: bool = True            # recgs with trimming: rescale colours so renders keep the photos' mean light

    #: Settings added since a release, with the value that reproduces runs saved before them.
    _BEFORE = {"caustic_dc": True, "robust_k": 0.0, "gain_restore": False, "estimator": "lowpass", "fit_loss": "l1",
               "caustics": "on", "pass_statistic": "floor", "pass_min": 3, "looks": "off"}

    @classmethod
    def from_dict(cls, d: dict) -> "CausticConfig":
        """The settings saved in a checkpoint (``asdict`` form; checkpoints before the split kept
        them in the trainer's dict, whose other keys are ignored). A setting newer than the
        checkpoint takes the value the run was made with, so a resume continues it unchanged."""
        d = {**cls._BEFORE, **{k: v for k, v in d.items() if k in cls.__dataclass_fields__}}
        return cls(**d)

    def validate(self) -> None:
        """Refuse settings no run can use (called before any data is read)."""
        if self.mode not in MODES:
            raise RecGSError(f"unknown mode {self.mode!r} (choose from {', '.join(MODES)})")
        if self.caustic_k < 0 or (self.caustic_k and self.caustic_k % 2 == 0):
            raise RecGSError(f"caustic filter size must be a positive odd number (or 0 = auto), got {self.caustic_k}")
        if self.caustic_model not in ("additive", "multiplicative"):
            raise RecGSError(f"unknown caustic model {self.caustic_model!r} (additive or multiplicative)")
        if self.caustics not in FIND_CAUSTICS:
            raise RecGSError(f"unknown caustics setting {self.caustics!r} (choose from {', '.join(FIND_CAUSTICS)})")
        if self.estimator not in ESTIMATORS and self.estimator not in ADDED_ESTIMATORS:
            raise RecGSError(f"unknown caustic estimator {self.estimator!r} "
                             f"(choose from {', '.join(ESTIMATORS + tuple(ADDED_ESTIMATORS))})")
        if self.pass_statistic not in PASS_STATISTICS:
            raise RecGSError(f"unknown pass statistic {self.pass_statistic!r} (choose from {', '.join(PASS_STATISTICS)})")
        if self.looks not in LOOKS:
            raise RecGSError(f"unknown look-frames setting {self.looks!r} (choose from {', '.join(LOOKS)})")
        if self.pass_min < 1:
            raise RecGSError(f"the passes a pixel needs must be at least 1, got {self.pass_min}")
        if self.fit_loss not in ("l1", "l2"):
            raise RecGSError(f"unknown fit loss {self.fit_loss!r} (l1 or l2)")
        if self.robust_k < 0:
            raise RecGSError(f"robust trimming k must be >= 0 (0 = off), got {self.robust_k}")
        if self.recurrence_steps < 1:
            raise RecGSError(f"recurrence steps must be at least 1, got {self.recurrence_steps}")
        if self.warmup_share is not None and not 0 < self.warmup_share <= 1:   # NaN fails this too
            raise RecGSError(f"warm-up share must be in (0, 1], got {self.warmup_share}")
        if self.warmup < 0:
            raise RecGSError(f"warmup must be 0 or more steps, got {self.warmup}")
        if self.max_recurrences < 0:
            raise RecGSError(f"max recurrences must be 0 or more, got {self.max_recurrences}")
        if not self.recurrence_tol >= 0 or math.isinf(self.recurrence_tol):   # NaN fails the first test
            raise RecGSError(f"recurrence tolerance must be a number >= 0, got {self.recurrence_tol}")
        if not math.isfinite(self.robust_k):
            raise RecGSError(f"robust trimming k must be a number >= 0 (0 = off), got {self.robust_k}")


def register_estimator(name: str, method) -> None:
    """Add an estimator kept for comparisons: ``--estimator name`` builds ``method`` (a
    :class:`.recgs.RecGS` subclass) in place of RecGS (benchmarks/caustic_estimators)."""
    if name in ESTIMATORS:
        raise ValueError(f"{name!r} is one of the product's estimators")
    ADDED_ESTIMATORS[name] = method
