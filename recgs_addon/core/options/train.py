"""The ``train`` job's options (``python -m recgs_addon train``, the sidebar's Training panels,
batch mode): :data:`TRAIN_OPTIONS`."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..caustics.config import ESTIMATORS, FIND_CAUSTICS, LOOKS, MODE_INFO, PASS_STATISTICS, CausticConfig
from ..train.config import LAMP_MODES, MEDIUM_MODES, TrainConfig
from ..train.strategies import DEFAULT_STRATEGY, STRATEGIES, CloneSplit
from .scene import EAGER, IMAGE_FOLDER, SCENE_DIR
from .table import Option, OptionTable, Setting

_CAUSTICS = "caustic removal"
_BLOCKS = "training in blocks"
#: ``--blocks auto``, as the parsed value.
AUTO_BLOCKS = -1


def blocks_count(text) -> int:
    """``--blocks``: a count (0 or 1: one job) or ``auto`` (:data:`AUTO_BLOCKS`)."""
    if str(text).strip().lower() == "auto":
        return AUTO_BLOCKS
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a number or 'auto', got {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"takes a number of 0 or more or 'auto', got {n}")
    return n

#: What each water setting does (labels and descriptions: the sidebar's Water).
_MEDIUM = {
    "auto": ("Auto", "Model the water where the survey sees the seabed from several ranges and the water "
                     "changes the photos measurably"),
    "on": ("On", "Always model the water"),
    "off": ("Off", "Train on the photos' colours as they are"),
}
#: What each lamp setting does (the sidebar's Lamp).
_LAMP = {
    "auto": ("Auto", "Model light fixed to the camera (a lamp's cone and fall-off, vignetting) where the survey "
                     "shows it"),
    "on": ("On", "Always model light fixed to the camera"),
    "off": ("Off", "Train on the photos' light as it is"),
}
_PRESETS = (("default", "Default", "Lean schedule: grows only what the scene needs"),
            ("vanilla", "Vanilla", "INRIA's 30k-iteration schedule, only to compare with it"))

TRAIN_OPTIONS = OptionTable([
    SCENE_DIR,
    Option("--out", "Output folder (checkpoint.pt, point_cloud.ply, metrics.json, the run's report)",
           type=Path, required=True),
    Option("--mode", "What the job trains", default="3dgs",
           choices=tuple((m, label, text) for m, (label, text) in MODE_INFO.items()),
           note="Use recgs for photos with caustics: it trains on as 3dgs by itself where it finds none",
           setting=Setting("Mode", default="recgs",
                           why="The sidebar starts with RecGS: survey photos may hold caustics, and RecGS trains "
                               "as plain 3DGS where it finds none")),
    Option("--preset", "Training schedule", default="default", choices=_PRESETS, setting=Setting("Preset")),
    Option("--max-minutes", "Wall-clock limit in minutes; the run uses all of it and ends with the model that "
                            "scored best on the held-out photos", type=float,
           note="Default: none; give one",
           setting=Setting("Time Limit", default=10.0, minimum=0.0, soft_max=600.0,
                           why="0 = no limit; the sidebar starts at 10 minutes so that a job started with a "
                               "click ends by itself")),
    Option("--iterations", "Upper bound on optimisation steps (none given: the preset's)", type=int,
           note="Raise it with --resume to continue a run that reached it",
           setting=Setting("Iterations", default=0, minimum=0, why="0 = the preset's")),
    Option("--budget", "Maximum number of Gaussians, or 'auto': stop adding Gaussians when held-out quality "
                       f"stops improving, at most one per {CloneSplit.surface_pixels_per_gaussian:g} pixels of seabed "
                       "(the training pixels over the views that see a point). A fixed number gives a smaller file "
                       "and a faster viewer", default="auto",
           setting=Setting("Budget", default=500_000, minimum=1, soft_max=5_000_000, kind="int",
                           why="The number used while Automatic Budget is off")),
    Option("--density", f"Density control (default {DEFAULT_STRATEGY}): adc (INRIA's clone/split by screen "
                        "gradient) or mcmc (relocate faded Gaussians under a fixed budget, 3DGS-MCMC; 2-3.5 dB "
                        "lower held-out than adc in 5-minute runs on clean surveys)",
           choices=tuple(sorted(STRATEGIES))),
    Option("--prune-weight", "Significance, in pixels: while the model grows, a Gaussian that supplies under this "
                             "many pixels to every training view that draws it (its blending weight) is removed and "
                             "its room given to growth where the error is, and only Gaussians that supply twice this "
                             f"are copied (default {CloneSplit.prune_weight:g} with adc, 0 with mcmc; 0: off)", type=float),
    Option("--medium", "The water between seabed and camera (attenuation and backscatter), fitted with the "
                       f"Gaussians so that they hold the seabed's true colour (default {TrainConfig.medium})",
           choices=tuple((m, *_MEDIUM[m]) for m in MEDIUM_MODES),
           setting=Setting("Water", default=TrainConfig.medium)),
    Option("--lamp", "Light fixed to the camera (a lamp's or strobe's cone and its fall-off with range, the lens's "
                     "vignetting), fitted with the Gaussians so that they hold the seabed evenly lit (default "
                     f"{TrainConfig.lamp})", choices=tuple((m, *_LAMP[m]) for m in LAMP_MODES),
           setting=Setting("Lamp", default=TrainConfig.lamp)),
    Option("--downscale", "Train at the photo size divided by this (after the long side's cap): 2 or 4 for "
                          "quick trials", type=int, default=TrainConfig.downscale,
           setting=Setting("Downscale", minimum=1, maximum=32)),
    Option("--max-side", f"Long side of the training images at most this many pixels (default "
                         f"{TrainConfig.max_side}, as the reference 3DGS code; 0 = the photos' own size): memory and "
                         "step time grow with it", type=int,
           setting=Setting("Max Image Side", default=TrainConfig.max_side, minimum=0, soft_max=8192)),
    Option("--max-memory", "Gigabytes the run may use (default: what the machine has free); a run that would need "
                           "more is refused before it starts, and an automatic budget is capped to fit", type=float),
    Option("--sh-degree", "Cap on the spherical-harmonic degree (view-dependent colour); the default preset "
                          "raises the degree only where it helps. 0 gives the smallest file", type=int,
           default=TrainConfig.sh_degree, choices=tuple(range(4)),
           setting=Setting("SH Degree", minimum=0, maximum=3)),
    Option("--seed", "Seed of the random generators", type=int, default=TrainConfig.seed,
           setting=Setting("Seed", minimum=0)),
    Option("--device", "cpu, cuda or mps (where torch has them). A GPU trains the same model. On an NVIDIA "
                       "GPU with Triton (it comes with torch's CUDA builds) the whole render runs in fused "
                       "GPU kernels; elsewhere, and on mps, the plain-PyTorch path, which is about as fast as two CPU "
                       "cores: there, on a machine with more cores keep cpu", default=TrainConfig.device,
           setting=Setting("Device")),
    Option("--images", "Train on this image folder instead of images/: a name inside the scene (e.g. clean) or "
                       "a path; the same file names",
           setting=Setting("Image Folder", default=IMAGE_FOLDER)),
    Option("--holdout-every", "Hold out every Nth photo (by name, from the 5th) to score the model; 0 = none, "
                              "which also leaves no score to keep the best model by", type=int,
           default=TrainConfig.holdout_every, setting=Setting("Hold Out Every", minimum=0)),
    Option("--init-ply", "Start from these Gaussians", type=Path),
    Option("--blocks", "Split the survey into this many blocks over the seabed, train them in parallel on Ray "
                       "(each on the photos that see it, with a margin) and merge them into one scene; 0 = one job; "
                       "'auto': one job where it fits in memory, else the fewest blocks that do. For surveys larger "
                       "than one machine's memory or time; on one machine a split that trains each photo in more "
                       "than two blocks on average is refused (the blocks share its cores)", type=blocks_count,
           default=0, group=_BLOCKS, setting=Setting("Train in Blocks", minimum=0, soft_max=64, kind="int")),
    Option("--cluster", "Ray cluster to run the blocks on (an address such as ray://host:10001 or auto; default "
                        "RAY_ADDRESS, else a local Ray on this machine). Its workers must reach the output folder",
           group=_BLOCKS, setting=Setting("Cluster Address", default="",
                                           why="Empty: RAY_ADDRESS, else a local Ray on this machine")),
    Option("--block-threads", "Threads each block trains with (default: this machine's cores shared among the "
                              "blocks that run at once)", type=int, default=0, group=_BLOCKS),
    Option("--block", "Train one block of a split survey (its block.json; --blocks writes them)", type=Path,
           group=_BLOCKS),
    Option("--resume", "Continue from OUT/checkpoint.pt", type=bool),
    Option("--checkpoint-every", "Seconds between checkpoints (also the sidebar's live updates); a crash loses at "
                                 "most this", type=float, default=30.0,
           setting=Setting("Checkpoint Every", default=10.0, minimum=0.0, soft_max=600.0,
                           why="The sidebar checkpoints every 10 seconds: the viewport's live preview updates "
                               "with each checkpoint")),
    EAGER,
    Option("--compile-first", "Compile before the first step even on a cold cache (default: train eagerly while a "
                              "background process warms the cache, then switch)", type=bool),
    Option("--keep-last", "End with the last model, not the one that scored best on the held-out photos",
           type=bool),
    Option("--gt-images", "Ground-truth images with the same names, for scoring (default: SCENE/clean if present)",
           group=_CAUSTICS),
    Option("--caustic-k", "Side of the kept low-frequency block of the caustic filter, odd (the paper: 9, which "
                          "keeps -4..+4 cycles per image); 0 = chosen from the residual spectrum (default)",
           type=int, group=_CAUSTICS,
           setting=Setting("Caustic Filter Size", default=CausticConfig.caustic_k, minimum=0, maximum=63,
                           step=2)),
    Option("--caustic-model", f"additive: fit I - C (the paper); multiplicative: fit I / gain (default "
                              f"{CausticConfig.caustic_model})", choices=("additive", "multiplicative"),
           group=_CAUSTICS),
    Option("--caustic-dc", "recgs: C's mean per view: zero (default; caustics move light, they add none) or keep "
                           "(the paper)", choices=("zero", "keep"), group=_CAUSTICS),
    Option("--warmup", f"recgs: most plain steps before the first recurrence (default {CausticConfig.warmup})",
           type=int, group=_CAUSTICS),
    Option("--recurrence-steps", f"recgs: steps per recurrence (default {CausticConfig.recurrence_steps})",
           type=int, group=_CAUSTICS),
    Option("--max-recurrences", f"recgs: at most this many recurrences (default {CausticConfig.max_recurrences})",
           type=int, group=_CAUSTICS),
    Option("--recurrence-tol", "recgs: stop when the relative change of C falls below this (default "
                               f"{CausticConfig.recurrence_tol})", type=float, group=_CAUSTICS),
    Option("--caustics", "recgs: auto (default) removes caustics only where the survey shows light that moves "
                         "over the seabed between frames (a lamp on the camera, vignetting or exposure changes are "
                         "not caustics: such a survey trains as plain 3DGS, and the run says so); on: run the loop "
                         "whatever the survey shows", choices=FIND_CAUSTICS, group=_CAUSTICS),
    Option("--estimator", "recgs: auto (default) picks passes where the survey sees each seabed point in a median "
                          "of 2 or more independent passes and lowpass below; passes: each frame's target from the "
                          "other frames that saw each point (the floor of their light, over the whole band; the "
                          "survey's sparse points give the geometry); lowpass: C from the low-passed residual (the "
                          "paper)", choices=ESTIMATORS, group=_CAUSTICS),
    Option("--pass-statistic", "passes: field (default): each frame's light modelled as one continuous field "
                               "against the colour the other passes show, then the colour; floor: the mean of the "
                               "frames that saw each pixel under the floor of its light", choices=PASS_STATISTICS,
           group=_CAUSTICS),
    Option("--pass-min", f"passes: independent passes a pixel needs for its target to come from them (fewer: "
                         f"the low-pass target; default {CausticConfig.pass_min})", type=int, group=_CAUSTICS),
    Option("--looks", "passes: auto (default) gathers the light also from the survey's look frames (looks.json "
                      "and looks/: a video's frames between the keyframes, each a further look at the light; they "
                      "do not train); off: the keyframes alone", choices=LOOKS, group=_CAUSTICS),
    Option("--fit-loss", "recgs: data term of the recurrences: l1 (the paper; fits the views' median) or l2 (their "
                         f"mean; no SSIM term); default {CausticConfig.fit_loss}", choices=("l1", "l2"),
           group=_CAUSTICS),
    Option("--robust-k", "recgs: leave out of the loss pixels brighter than the render by more than k robust "
                         "sigmas (an experiment: 0, the default, is the paper's plain loss; docs/dev/caustics.md)",
           type=float, group=_CAUSTICS),
    Option("--gain-restore", "recgs with trimming: rescale the colours to the photos' mean light at the end "
                             "(default on)", choices=("on", "off"), group=_CAUSTICS),
])
