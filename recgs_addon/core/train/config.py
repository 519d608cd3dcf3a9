"""Training settings: :class:`TrainConfig` holds every setting of the trainer (a caustic
method's own settings live beside it, in core/caustics/config.py); :func:`preset` gives

* ``default``: coarse to fine, density control :data:`DEFAULT_STRATEGY` (INRIA's clone/split
  under a budget of one Gaussian per 5 pixels of seabed, the training pixels over the median
  views of a sparse point, or per 8 training pixels if fewer, that stops growing once held-out PSNR
  stops improving; ``strategy="mcmc"``: 3DGS-MCMC, Gaussians below opacity 0.1 relocated,
  growth by opacity, one per 36 pixels), SH degree raised only when it helps held-out views,
  stop on a held-out plateau, and end with the model that scored best on the held-out photos
  (measured in benchmarks/RESULTS.md);
* ``vanilla``: INRIA's schedule: 30k iterations, densify every 100 from 500 to 15k, opacity
  reset every 3k, SH degree +1 every 1k.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Optional

from ..errors import RecGSError
from .strategies import DEFAULT_STRATEGY, STRATEGIES, Strategy, default_strategy, make_strategy, strategy_fields, \
    strategy_from_dict


#: The water model's settings (core/train/water.py): auto fits it where the survey sees each
#: point from several ranges and keeps it where it changes the photos measurably.
MEDIUM_MODES = ("auto", "on", "off")
#: The lamp's settings (light fixed to the camera, core/train/lamp.py): auto models it where the
#: survey shows it (core/caustics/light.py).
LAMP_MODES = ("auto", "on", "off")


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
    #: with a time limit, no density control after this share of it, so the run ends on a model
    #: whose last Gaussians have settled (1 = density control to the end)
    densify_until_share: float = 1.0
    opacity_reset_every: int = 3000
    #: which Gaussians are added, moved and removed, with its own settings (strategies.py):
    #: clone/split (INRIA, the default) or 3DGS-MCMC
    density: Strategy = field(default_factory=default_strategy)
    # coarse to fine: ((until_step, extra downscale factor), ...); the last level is 1
    pyramid: tuple = ()
    # evaluation and stopping
    eval_every: int = 1000
    eval_views: int = 0                  # 0 = all held-out views
    plateau_patience: int = 0            # evals without a gain of plateau_min_gain dB -> stop; 0 = never
    plateau_min_gain: float = 0.02
    growth_patience: int = 3             # budget auto: evals without plateau_min_gain*5 dB -> stop growth
    growth_rate: float = 0.0             # max fractional growth per densification (0 = unlimited)
    sh_probation: int = 1000             # steps given to a new SH degree before it is judged
    sh_min_gain: float = 0.05            # dB a new SH degree must add on held-out views
    keep_best: bool = False              # end with the model that scored best on the held-out photos as captured
    log_every: int = 50
    background: tuple = (0.0, 0.0, 0.0)
    compiled: Optional[bool] = None      # rasterizer through torch.compile: None = when available
    medium: str = "auto"                 # water (attenuation, backscatter) fitted with the Gaussians:
                                         # "auto" (where the survey can tell it from colour), "on", "off"
    lamp: str = "auto"                   # light fixed to the camera (a lamp's cone and fall-off, vignetting)
                                         # fitted with the Gaussians: "auto" (where the survey shows it), "on", "off"
    block: Optional[dict] = None         # one block of a survey trained in blocks (core/blocks): the views
                                         # it trains on ("train") and is scored on ("test"), by name, and
                                         # the cell of the seabed whose sparse points start it ("cell")

    @property
    def strategy(self) -> str:
        """The density control's name (``adc`` or ``mcmc``)."""
        return self.density.name

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The config saved in a checkpoint (``asdict`` form). Keys that are not trainer
        settings (a method's own, which older checkpoints kept in the same dict) are ignored."""
        dens = strategy_from_dict(d["density"] if isinstance(d.get("density"), dict) else d)
        d = {k: v for k, v in d.items() if k in cls.__dataclass_fields__ and k != "density"}
        d.setdefault("max_side", 0)   # checkpoints from before the cap trained at the photos' size
        d.setdefault("lamp", "off")   # ... and from before the lamp modelled none
        return cls(**{**d, "density": dens, "pyramid": tuple(tuple(x) for x in d["pyramid"]),
                      "background": tuple(d["background"])})

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
        self.density.validate()
        if self.medium not in MEDIUM_MODES:
            raise RecGSError(f"unknown medium setting {self.medium!r} (choose {', '.join(MEDIUM_MODES)})")
        if self.lamp not in LAMP_MODES:
            raise RecGSError(f"unknown lamp setting {self.lamp!r} (choose {', '.join(LAMP_MODES)})")
        if self.holdout_every < 0:
            raise RecGSError(f"holdout every must be 0 (hold out none) or a positive number, got {self.holdout_every}")
        if not 0 <= self.seed < 2 ** 64:   # what numpy's and torch's generators take
            raise RecGSError(f"seed must be a whole number from 0 to 2^64 - 1, got {self.seed}")


def preset(name: str, **overrides) -> TrainConfig:
    """``vanilla``: INRIA's schedule. ``default``: the lean schedule described in docs/dev/training.md.
    ``overrides`` may name the density control (``strategy``) and its settings by their names."""
    kind = overrides.pop("strategy", None) or DEFAULT_STRATEGY
    overrides = {k: v for k, v in overrides.items() if v is not None}   # None: the default
    own = strategy_fields(kind)   # an unknown name is refused here
    dens = make_strategy(kind, **{k: overrides.pop(k) for k in list(overrides) if k in own})
    others = {f.name for f in fields(TrainConfig)}
    stray = [k for k in overrides if k not in others and any(k in strategy_fields(n) for n in STRATEGIES)]
    if stray:
        raise RecGSError(f"{', '.join(stray)}: not a setting of density control {kind!r}")
    if name == "vanilla":
        cfg = TrainConfig(preset="vanilla", iterations=30_000, sh_policy="schedule",
                          plateau_patience=0, budget=10**9, eval_every=1000)
    elif name == "default":
        cfg = TrainConfig(preset="default", iterations=30_000, densify_from=200, densify_until=4000,
                          densify_every=100, opacity_reset_every=0, pyramid=((300, 2),),
                          eval_every=250, plateau_patience=4, growth_patience=2, sh_policy="probation",
                          growth_rate=0.25, keep_best=True, densify_until_share=0.8)
    else:
        raise RecGSError(f"unknown preset {name!r} (choose default or vanilla)")
    return replace(cfg, density=dens, **{k: v for k, v in overrides.items() if v is not None})
