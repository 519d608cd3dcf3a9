"""The sidebar's settings and job status: ``scene.recgs`` (saved with the .blend).

Settings map one to one onto ``python -m recgs_addon train`` options (see
:func:`train_options`); the status fields are written by the timer that follows the job
(``job_follow.pump``) and only drawn by the panel.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..core.caustics.config import CAUSTIC_MODES, MODE_INFO
from ..core.capture.frame_choice import DEFAULT_FRAMES, MIN_FRAMES
from ..core.capture.video import DEFAULT_MAX_SIDE

#: Folder settings may be relative to the .blend ("//..."); Blender 4.5+ wants that declared.
_PATH = {"options": {"PATH_SUPPORTS_BLEND_RELATIVE"}} if bpy.app.version >= (4, 5, 0) else {}

MODE_ITEMS = [(mode, label, description) for mode, (label, description) in MODE_INFO.items()]

STATUS_ITEMS = [
    ("IDLE", "Idle", "No job has run"),
    ("RUNNING", "Running", "A job is running"),
    ("CANCELLING", "Cancelling", "The job was asked to stop and is writing its checkpoint"),
    ("DONE", "Done", "The last job finished"),
    ("CANCELLED", "Cancelled", "The last job was cancelled; Resume continues it"),
    ("FAILED", "Failed", "The last job failed; see the message"),
]


def _water_view(settings, context) -> None:
    from .water import on_water_view
    on_water_view(settings, context)


class RecGSSettings(bpy.types.PropertyGroup):
    # -- scene -------------------------------------------------------------------------------
    scene_dir: StringProperty(**_PATH, name="Scene Folder", subtype="DIR_PATH",
                              description="Survey folder holding images/ and a COLMAP model in sparse/0")
    images: StringProperty(name="Image Folder", default="images",
                           description="Photo folder inside the scene folder used for import and training")
    photo_dir: StringProperty(**_PATH, name="Photo Folder", subtype="DIR_PATH",
                              description="Photos without a COLMAP model: Reconstruct from Photos runs "
                                          "structure from motion on them and writes the scene folder")
    link_photos: BoolProperty(name="Link Photos", default=False,
                              description="Reconstruct: symlink the photos into the scene folder instead "
                                          "of copying them")
    video_path: StringProperty(**_PATH, name="Video File", subtype="FILE_PATH",
                               description="A clip of the survey (MP4, MOV, MKV): Import Video chooses sharp, "
                                           "distinct frames, runs structure from motion on them and writes the "
                                           "scene folder")
    video_frames: IntProperty(name="Frames", default=DEFAULT_FRAMES, min=MIN_FRAMES, soft_max=1000,
                              description="About this many frames of the clip (at most 4 a second of it)")
    video_every: FloatProperty(name="Every", default=0.0, min=0.0, soft_max=10.0, unit="TIME_ABSOLUTE",
                               description="One frame every this many seconds instead of a count (0: use Frames)")
    video_max_side: IntProperty(name="Max Frame Side", default=DEFAULT_MAX_SIDE, min=0, soft_max=8192,
                                description="Long side of the written frames at most this many pixels "
                                            "(0: the clip's own size)")
    # -- training ----------------------------------------------------------------------------
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default="recgs",
                       description="What the job trains")
    max_minutes: FloatProperty(name="Time Limit", default=10.0, min=0.0, soft_max=600.0, unit="NONE",
                               description="Wall-clock limit in minutes (0 = none)")
    budget_auto: BoolProperty(name="Automatic Budget", default=True,
                              description="Stop adding Gaussians when held-out quality stops improving")
    budget: IntProperty(name="Budget", default=500_000, min=1, soft_max=5_000_000,
                        description="Maximum number of Gaussians")
    downscale: IntProperty(name="Downscale", default=1, min=1, max=32,
                           description="Train at the photo size divided by this")
    max_side: IntProperty(name="Max Image Side", default=1600, min=0, soft_max=8192,
                          description="Long side of the training images at most this many pixels "
                                      "(0 = the photos' own size); memory and step time grow with it")
    caustic_k: IntProperty(name="Caustic Filter Size", default=0, min=0, max=63, step=2,
                           description="Side of the kept low-frequency block of the caustic filter: "
                                       "0 = chosen from the residual spectrum (default); odd sizes "
                                       "fix it (9 keeps -4..+4 cycles per image, as the paper)")
    medium: EnumProperty(name="Water", default="auto",
                         description="The water between seabed and camera (attenuation, backscatter), fitted with "
                                     "the Gaussians so that they hold the seabed's true colour",
                         items=[("auto", "Auto", "Model the water where the survey sees the seabed from several "
                                                 "ranges and the water changes the photos measurably"),
                                ("on", "On", "Always model the water"),
                                ("off", "Off", "Train on the photos' colours as they are")])
    water_view: EnumProperty(name="Show", default="TRUE_COLOUR", update=_water_view,
                             description="Show the seabed in its true colour, or as seen underwater (the fitted "
                                         "water as the world's volume, in EEVEE and Cycles)",
                             items=[("TRUE_COLOUR", "True Colour", "The seabed without the water"),
                                    ("UNDERWATER", "As Seen Underwater", "The fitted water in front of the seabed")])
    water: StringProperty(name="Fitted Water", default="",
                          description="The water the last training job fitted (coefficients as JSON; empty: none)")
    # -- advanced ----------------------------------------------------------------------------
    preset: EnumProperty(name="Preset", default="default", description="Training schedule",
                         items=[("default", "Default", "Lean schedule: grows only what the scene needs"),
                                ("vanilla", "Vanilla", "INRIA's 30k-iteration schedule")])
    iterations: IntProperty(name="Iterations", default=0, min=0,
                            description="Upper bound on optimisation steps (0 = the preset's)")
    sh_degree: IntProperty(name="SH Degree", default=3, min=0, max=3,
                           description="Cap on the spherical-harmonic degree")
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the random generators")
    holdout_every: IntProperty(name="Hold Out Every", default=8, min=0,
                               description="Hold out every Nth photo for the quality figure (0 = none)")
    checkpoint_every: FloatProperty(name="Checkpoint Every", default=10.0, min=0.0, soft_max=600.0,
                                    description="Seconds between checkpoints (and live viewport updates)")
    device: StringProperty(name="Device", default="cpu", description="cpu, cuda or mps (where torch has them)")
    eager: BoolProperty(name="Plain PyTorch", default=False,
                        description="Render with plain PyTorch only: neither numba's kernels nor torch.compile "
                                    "(about 2.5x slower steps; the reference the fast paths are tested against)")
    out_dir: StringProperty(**_PATH, name="Output Folder", subtype="DIR_PATH",
                            description="Where the job writes checkpoint, PLY, metrics and images "
                                        "(empty: recgs_out inside the scene folder)")
    # -- job status (written by the timer) ----------------------------------------------------
    status: EnumProperty(name="Status", items=STATUS_ITEMS, default="IDLE", description="State of the last job")
    job_kind: StringProperty(name="Job", description="What the job does: train, sfm or video")
    phase: StringProperty(name="Phase", description="The step the job is at, as it reports it")
    iteration: IntProperty(name="Iteration", default=0, description="Optimisation steps done")
    gaussians: IntProperty(name="Gaussians", default=0, description="Gaussians in the model now")
    psnr_test: FloatProperty(name="Held-out PSNR", default=-1.0,
                             description="Quality on the held-out photos in dB; negative: not measured yet")
    elapsed: FloatProperty(name="Elapsed", default=0.0, description="Seconds since the job started")
    eta: FloatProperty(name="Remaining", default=-1.0, description="Seconds left, estimated; negative: unknown")
    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR",
                            description="Share of the job done")
    message: StringProperty(name="Message", description="The job's last message: a result, a note, or why it failed")
    plan: StringProperty(name="Plan", description="What the job said it will need before it started "
                                                  "(resolution, memory, time per 1,000 steps), one line each")


def _parse_budget(s: RecGSSettings, value) -> None:
    s.budget_auto = str(value) == "auto"
    if not s.budget_auto:
        if not str(value).isdigit() or int(value) < 1:
            raise ValueError(f"--budget must be a number of Gaussians or 'auto', got {value!r}")
        s.budget = int(value)


def _copy(key: str):
    """A setting that is the option as it is (an option not given leaves the setting alone)."""
    def read(s):
        return getattr(s, key)

    def write(s, value):
        if value is not None:
            setattr(s, key, value)
    return read, write


def _zero_is_none(key: str):
    """A setting where 0 means the option is not given (no limit)."""
    return (lambda s: getattr(s, key) if getattr(s, key) > 0 else None,
            lambda s, value: setattr(s, key, value or 0))


def _unless(key: str, default: str):
    """A text setting whose ``default`` (or empty) means the option is not given."""
    return (lambda s: getattr(s, key) if getattr(s, key) and getattr(s, key) != default else None,
            lambda s, value: setattr(s, key, str(value)) if value else None)


#: The ``train`` options (argparse dests) the settings hold, each with how the settings give
#: the option (``read``) and take it from a parsed command line (``write``): the one list the
#: panel's jobs (:func:`train_options`), batch runs (:func:`apply_train_args`) and the
#: generated reference follow.
SETTINGS = {
    "mode": _copy("mode"), "preset": _copy("preset"),
    "max_minutes": _zero_is_none("max_minutes"), "iterations": _zero_is_none("iterations"),
    "budget": (lambda s: "auto" if s.budget_auto else s.budget, _parse_budget),
    "downscale": _copy("downscale"), "max_side": _copy("max_side"), "sh_degree": _copy("sh_degree"),
    "seed": _copy("seed"), "holdout_every": _copy("holdout_every"), "checkpoint_every": _copy("checkpoint_every"),
    "device": _unless("device", "cpu"), "eager": _copy("eager"),
    "caustic_k": (lambda s: s.caustic_k if s.mode in CAUSTIC_MODES else None, _copy("caustic_k")[1]),
    "images": _unless("images", "images"), "medium": _unless("medium", "auto"),
}
#: ``train`` options (argparse dests) that the settings hold.
SETTINGS_OPTIONS = tuple(SETTINGS)


def train_options(s: RecGSSettings) -> dict:
    """Trainer options (``train_command`` keys) from the settings."""
    return {key: read(s) for key, (read, _) in SETTINGS.items()}


def apply_train_args(s: RecGSSettings, args) -> None:
    """Copy parsed ``train`` arguments (an argparse namespace) into the settings."""
    for key, (_, write) in SETTINGS.items():
        write(s, getattr(args, key, None))


classes = (RecGSSettings,)


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.recgs = PointerProperty(type=RecGSSettings)


def unregister() -> None:
    del bpy.types.Scene.recgs
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
