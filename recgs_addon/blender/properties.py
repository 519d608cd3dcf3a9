"""The sidebar's settings and job status: ``scene.recgs`` (saved with the .blend).

Settings map one to one onto ``python -m recgs_addon train`` options (see
:func:`train_options`); the status fields are written by the timer that follows the job
(``job_follow.pump``) and only drawn by the panel.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..core.caustics.config import CAUSTIC_MODES
from ..core.options.capture import SFM_OPTIONS, VIDEO_OPTIONS
from ..core.options.scene import IMPORT_OPTIONS as SCENE_TABLE
from ..core.options.train import TRAIN_OPTIONS

#: Folder settings may be relative to the .blend ("//..."); Blender 4.5+ wants that declared.
_PATH = {"options": {"PATH_SUPPORTS_BLEND_RELATIVE"}} if bpy.app.version >= (4, 5, 0) else {}


def _setting(dest: str, table=TRAIN_OPTIONS, **extra):
    """The bpy property of option ``dest`` of ``table`` (``train``'s unless given), from its
    declaration (core/options/): label, description (the option's help), default, choices and
    range."""
    opt = table[dest]
    st = opt.setting
    kw = {"name": st.label, "description": opt.setting_help(), "default": opt.setting_default(), **extra}
    for key, value in (("min", st.minimum), ("max", st.maximum), ("soft_max", st.soft_max), ("step", st.step)):
        if value is not None:
            kw[key] = value
    if opt.choices and isinstance(opt.choices[0], tuple):   # labelled choices: a menu
        kw["items"] = [tuple(c) for c in opt.choices]
        for key in ("min", "max", "soft_max", "step"):
            kw.pop(key, None)
        return EnumProperty(**kw)
    kind = st.kind or {bool: "bool", int: "int", float: "float"}.get(opt.type, "str")
    return {"bool": BoolProperty, "int": IntProperty, "float": FloatProperty, "str": StringProperty}[kind](**kw)

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
    scene_dir: _setting("scene_dir", SCENE_TABLE, subtype="DIR_PATH", **_PATH)
    images: _setting("images")
    photo_dir: StringProperty(**_PATH, name="Photo Folder", subtype="DIR_PATH",
                              description="Photos without a COLMAP model: Reconstruct from Photos runs "
                                          "structure from motion on them and writes the scene folder")
    link_photos: _setting("link", SFM_OPTIONS)
    video_path: StringProperty(**_PATH, name="Video File", subtype="FILE_PATH",
                               description="A clip of the survey (MP4, MOV, MKV): Import Video chooses sharp, "
                                           "distinct frames, runs structure from motion on them and writes the "
                                           "scene folder")
    video_frames: _setting("frames", VIDEO_OPTIONS)
    video_every: _setting("every", VIDEO_OPTIONS, unit="TIME_ABSOLUTE")
    video_max_side: _setting("max_side", VIDEO_OPTIONS)
    # -- training ----------------------------------------------------------------------------
    mode: _setting("mode")
    max_minutes: _setting("max_minutes", unit="NONE")
    budget_auto: BoolProperty(name="Automatic Budget", default=True,
                              description="Stop adding Gaussians when held-out quality stops improving")
    budget: _setting("budget")
    downscale: _setting("downscale")
    max_side: _setting("max_side")
    caustic_k: _setting("caustic_k")
    medium: _setting("medium")
    lamp: _setting("lamp")
    blocks: _setting("blocks")
    cluster: _setting("cluster")
    water_view: EnumProperty(name="Show", default="TRUE_COLOUR", update=_water_view,
                             description="Show the seabed in its true colour, or as seen underwater (the fitted "
                                         "water as the world's volume, in EEVEE and Cycles)",
                             items=[("TRUE_COLOUR", "True Colour", "The seabed without the water"),
                                    ("UNDERWATER", "As Seen Underwater", "The fitted water in front of the seabed")])
    water: StringProperty(name="Fitted Water", default="",
                          description="The water the last training job fitted (coefficients as JSON; empty: none)")
    # -- advanced ----------------------------------------------------------------------------
    preset: _setting("preset")
    iterations: _setting("iterations")
    sh_degree: _setting("sh_degree")
    seed: _setting("seed")
    holdout_every: _setting("holdout_every")
    checkpoint_every: _setting("checkpoint_every")
    device: _setting("device")
    eager: _setting("eager")
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


def _unless_default(key: str):
    """A text setting whose default (or empty) means the option is not given."""
    default = TRAIN_OPTIONS[key].setting_default()
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
    "device": _unless_default("device"), "eager": _copy("eager"),
    "caustic_k": (lambda s: s.caustic_k if s.mode in CAUSTIC_MODES else None, _copy("caustic_k")[1]),
    "images": _unless_default("images"), "medium": _unless_default("medium"), "lamp": _unless_default("lamp"),
    "blocks": _zero_is_none("blocks"), "cluster": _unless_default("cluster"),
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
