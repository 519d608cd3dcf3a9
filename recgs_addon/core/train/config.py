"""Training settings: :class:`TrainConfig` holds every setting of the trainer (a caustic
method's own settings live beside it, in core/caustics/config.py); :func:`preset` gives

* ``default``: coarse to fine, density control :data:`DEFAULT_STRATEGY` (INRIA's clone/split
  under a budget of one Gaussian per 3.5 pixels of seabed, the training pixels over the median
  views of a sparse point, or per 8 training pixels if fewer, that stops growing once held-out PSNR
  stops improving; ``strategy="mcmc"``: 3DGS-MCMC, Gaussians below opacity 0.1 relocated,
  growth by opacity, one per 36 pixels), SH degree raised only when it helps held-out views,
  stop on a held-out plateau, and end with the model that scored best on the held-out photos
  (measured in benchmarks/RESULTS.md);
* ``vanilla``: INRIA's schedule: 30k iterations, densify every 100 from 500 to 15k, opacity
  reset every 3k, SH degree +1 every 1k.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from ..errors import RecGSError


#: The default preset's settings that go with each density control (benchmarks/RESULTS.md:
#: training-quality-vs-size, training-relocation-five-minutes): 3DGS-MCMC's regularisers,
#: relocation below opacity 0.1 (the paper's 0.005 left the budget on faint Gaussians: +0.27
#: and +0.51 dB at 59,733 Gaussians after 3000 steps, two seeds, and 8 % less time a step;
#: nerfstudio culls below 0.1 too) and one Gaussian per 6x6 block of training pixels, or
#: INRIA's clone/split with one per 8 pixels and one per 3.5 pixels of seabed (the training
#: pixels over the median views of a sparse point): on dive surveys (12 views a point) the
#: second cuts the model to a quarter or a third and scores as high or higher in a time limit
#: (benchmarks/RESULTS.md#budget-by-seabed).
DENSITY_DEFAULTS = {
    "mcmc": dict(strategy="mcmc", opacity_reg=0.01, scale_reg=0.01, pixels_per_gaussian=36.0, relocate_opacity=0.1),
    "adc": dict(strategy="adc", opacity_reg=0.0, scale_reg=0.0, pixels_per_gaussian=8.0,
                surface_pixels_per_gaussian=3.5),
}
#: The density control of every mode unless asked otherwise: INRIA's clone/split. The caustic
#: methods need its sharper model (on the sample, 4 minutes, recgs: caustic-free images 23.61 dB
#: against MCMC's 21.88), and plain 3DGS scores higher with it too: 5 minutes on clean photos,
#: +2.0 dB held-out on the 24-photo sample and +3.0 and +3.5 dB on a 144-frame dive survey
#: (benchmarks/RESULTS.md#training-density-default).
DEFAULT_STRATEGY = "adc"
#: The water model's settings (core/train/water.py): auto fits it where the survey sees each
#: point from several ranges and keeps it where it changes the photos measurably.
MEDIUM_MODES = ("auto", "on", "off")


@dataclass
class TrainConfig:
    preset: str = "default"
    iterations: int = 30_000            # upper bound on optimisation steps
    max_minutes: Optional[float] = None  # wall-clock limit (None: none)
    budget: Optional[int] = None         # max Gaussians; None = "auto" (stop growth on plateau)
    downscale: int = 1                   # training resolution = image size / downscale ...
    max_side: int = 1600                 # ... its long side at most this many pixels (0: no cap; the
                                         # reference 3DGS code caps at 1600 too: a 24 MP photo trains at 1600x1200)
    sh_degree: int = 3                   # cap on the SH degree
    sh_policy: str = "probation"         # "probation" (raise only if it helps) | "schedule" (INRIA)
    sh_every: int = 1000                 # "schedule": +1 degree every this many steps
    seed: int = 0
    device: str = "cpu"
    holdout_every: int = 8               # every 8th image by sorted name is held out, from the 5th (data.holdout_split); 0 = none
    # learning rates (INRIA); means scaled by the scene extent, decayed log-linearly
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lambda_dssim: float = 0.2
    # density control
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4
    opacity_reset_every: int = 3000
    strategy: str = DEFAULT_STRATEGY     # "adc": clone/split by screen gradient (INRIA) | "mcmc": 3DGS-MCMC
    opacity_reg: float = 0.0             # loss + this * mean opacity (3DGS-MCMC: 0.01)
    scale_reg: float = 0.0               # loss + this * mean scale / scene extent (3DGS-MCMC: 0.01, unnormalised)
    mcmc_draw: str = "opacity"           # mcmc: draw sources by "opacity" (3DGS-MCMC) or "gradient" (opacity x screen gradient)
    noise_lr: float = 0.0                # mcmc: exploration noise on nearly transparent Gaussians (3DGS-MCMC: 5e5)
    relocate_opacity: float = 0.005      # mcmc: Gaussians below this opacity are relocated (3DGS-MCMC: 0.005)
    # coarse to fine: ((until_step, extra downscale factor), ...); the last level is 1
    pyramid: tuple = ()
    # evaluation and stopping
    eval_every: int = 1000
    eval_views: int = 0                  # 0 = all held-out views
    plateau_patience: int = 0            # evals without a gain of plateau_min_gain dB -> stop; 0 = never
    plateau_min_gain: float = 0.02
    growth_patience: int = 3             # budget auto: evals without plateau_min_gain*5 dB -> stop growth
    growth_rate: float = 0.0             # max fractional growth per densification (0 = unlimited)
    pixels_per_gaussian: float = 0.0     # budget auto: at most (training pixels / this) Gaussians
    surface_pixels_per_gaussian: float = 0.0  # ... and at most (training pixels / median views of a
                                              # sparse point / this): trainer.auto_budget
    sh_probation: int = 1000             # steps given to a new SH degree before it is judged
    sh_min_gain: float = 0.05            # dB a new SH degree must add on held-out views
    keep_best: bool = False              # end with the model that scored best on the held-out photos as captured
    log_every: int = 50
    background: tuple = (0.0, 0.0, 0.0)
    compiled: Optional[bool] = None      # rasterizer through torch.compile: None = when available
    medium: str = "auto"                 # water (attenuation, backscatter) fitted with the Gaussians:
                                         # "auto" (where the survey can tell it from colour), "on", "off"

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The config saved in a checkpoint (``asdict`` form). Keys that are not trainer
        settings (a method's own, which older checkpoints kept in the same dict) are ignored."""
        d = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        d.setdefault("max_side", 0)   # checkpoints from before the cap trained at the photos' size
        return cls(**{**d, "pyramid": tuple(tuple(x) for x in d["pyramid"]), "background": tuple(d["background"])})

    def validate(self) -> None:
        """Refuse settings no run can use (called before any data is read)."""
        if self.downscale < 1:
            raise RecGSError(f"downscale must be an integer >= 1, got {self.downscale}")
        if self.max_side < 0 or (0 < self.max_side < 8):
            raise RecGSError(f"the training image's long side must be 0 (the photos' own size) or at least "
                             f"8 pixels, got {self.max_side}")
        if self.budget is not None and self.budget < 1:
            raise RecGSError(f"budget must be at least 1 Gaussian, got {self.budget}")
        if self.iterations < 1:
            raise RecGSError(f"iterations must be at least 1, got {self.iterations}")
        if self.max_minutes is not None and not self.max_minutes > 0:   # NaN fails this too
            raise RecGSError(f"the time limit must be a number of minutes above 0, got {self.max_minutes}")
        if not 0 < self.relocate_opacity < 1:
            raise RecGSError(f"relocate_opacity must be between 0 and 1, got {self.relocate_opacity}")
        if self.strategy not in DENSITY_DEFAULTS:
            raise RecGSError(f"unknown density strategy {self.strategy!r} (choose {' or '.join(DENSITY_DEFAULTS)})")
        if self.medium not in MEDIUM_MODES:
            raise RecGSError(f"unknown medium setting {self.medium!r} (choose {', '.join(MEDIUM_MODES)})")
        if self.holdout_every < 0:
            raise RecGSError(f"holdout every must be 0 (hold out none) or a positive number, got {self.holdout_every}")
        if not 0 <= self.seed < 2 ** 64:   # what numpy's and torch's generators take
            raise RecGSError(f"seed must be a whole number from 0 to 2^64 - 1, got {self.seed}")


def preset(name: str, **overrides) -> TrainConfig:
    """``vanilla``: INRIA's schedule. ``default``: the lean schedule described in docs/dev/training.md."""
    if name == "vanilla":
        cfg = TrainConfig(preset="vanilla", iterations=30_000, sh_policy="schedule",
                          plateau_patience=0, budget=10**9, eval_every=1000)
    elif name == "default":
        cfg = TrainConfig(preset="default", iterations=30_000, densify_from=200, densify_until=4000,
                          densify_every=100, opacity_reset_every=0, pyramid=((300, 2),),
                          eval_every=250, plateau_patience=4, growth_patience=2, sh_policy="probation",
                          growth_rate=0.25, keep_best=True,
                          **DENSITY_DEFAULTS.get(overrides.get("strategy") or DEFAULT_STRATEGY, {}))
    else:
        raise RecGSError(f"unknown preset {name!r} (choose default or vanilla)")
    return replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
