"""Train, Resume and Cancel for a Gaussian object, and the registration of the artist's workflow.

The workflow's other parts: :mod:`.job_follow` follows the running job (:mod:`.job_progress`
shows its progress), :mod:`.reconstruct` makes a survey from photos or a video, :mod:`.outputs`
hands out a job's results and :mod:`.workflow` holds what they share.

Resume uses the object as the artist left it: when its Gaussians (world space) differ from
both the last checkpoint's PLY and what the last live update wrote, they are baked into the
mesh, written to ``OUT/edited_init.ply`` and the job starts from them (``--init-ply``, a
fresh optimiser); otherwise it continues the checkpoint (``--resume``).
"""
from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from . import gaussian_object as gobj
from . import job_follow, jobs, outputs, reconstruct
from ..core.caustics.config import CAUSTIC_MODES
from .job_follow import _begin, _check_free, cancel
from .properties import train_options
from .workflow import WorkflowError, _run, out_dir_for, scene_dir_for


def _gaussian_object(obj):
    if obj is None or not gobj.is_gaussian_object(obj):
        raise WorkflowError("Select a Gaussian object (Import COLMAP first)")
    return obj


def start_training(scene, obj, resume: bool = False, echo_stderr: bool = False, extra_args=()) -> str:
    """Start ``train`` for the Gaussian object ``obj`` with ``scene.recgs``'s settings.

    ``resume``: continue the object's last job (see the module docstring). ``extra_args``:
    more ``train`` options, verbatim (batch mode: those the settings do not hold). Returns a
    message; raises WorkflowError (or RecGSError / OSError) before anything starts."""
    _check_free()
    obj = _gaussian_object(obj)
    if jobs.missing_modules(["torch"]):
        raise WorkflowError("Training needs the training engine: click Install Training Engine (RecGS "
                            "preferences or sidebar), or choose a Python with torch in the preferences")
    s = scene.recgs
    if s.mode in CAUSTIC_MODES and s.caustic_k % 2 == 0 and s.caustic_k != 0:
        raise WorkflowError(f"Caustic Filter Size must be odd, got {s.caustic_k}")
    scene_dir = scene_dir_for(s, obj)
    out = out_dir_for(s, obj if resume else None, scene_dir)
    init_ply, how = None, "fresh, from the survey's sparse points"
    if resume:
        if not ((out / "checkpoint.pt").is_file() or (out / "blocks" / "plan.json").is_file()):
            raise WorkflowError(f"{out}: no checkpoint to resume from; use Train")
        edited, g = object_edited(obj, out)
        if edited:
            if len(g) == 0:
                raise WorkflowError(f"{obj.name}: no Gaussians left to train")
            init_ply = out / "edited_init.ply"
            bake_world(obj, g)
            from ..core.io.ply import write_gaussian_ply

            write_gaussian_ply(init_ply, g)
            how = f"from the edited object's {len(g)} Gaussians (fresh optimiser)"
        else:
            how = "continuing the checkpoint"
    argv = jobs.train_command(scene_dir, out, train_options(s), init_ply=init_ply,
                              resume=resume and init_ply is None) + [str(a) for a in extra_args]
    job = jobs.Job("train", argv, echo_stderr=echo_stderr)
    obj["recgs_out_dir"] = str(out)
    obj["recgs_scene_dir"] = obj.get("recgs_scene_dir", str(scene_dir))
    _begin(job, scene, object_name=obj.name, scene_dir=str(scene_dir), out_dir=str(out))
    return f"Training {obj.name} ({s.mode}) {how}; output in {out}"


def object_edited(obj, out: Path):
    """``(edited, world-space Gaussians)``: edited unless the object's Gaussians equal the last
    checkpoint's PLY or what the last live update wrote into it (count and array hash)."""
    from ..core.io.ply import read_gaussian_ply

    with gobj.edits_flushed(obj):
        g = gobj.gaussians_from_object(obj, world=True)
    sig = jobs.gaussian_signature(g)
    if sig == obj.get("recgs_synced"):
        return False, g
    ply = out / "point_cloud.ply"
    if ply.is_file() and sig == jobs.gaussian_signature(read_gaussian_ply(ply)):
        return False, g
    return True, g


def bake_world(obj, g) -> None:
    """Give ``obj`` the world-space Gaussians ``g`` with an identity transform (the job trains
    in world space, and live updates keep the object's transform)."""
    if np.array_equal(np.array(obj.matrix_world), np.eye(4)):
        return
    was_edit = obj.mode == "EDIT"
    if was_edit:
        bpy.ops.object.mode_set(mode="OBJECT")
    gobj.write_mesh(obj.data, g)
    obj.matrix_world = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
    obj["recgs_synced"] = jobs.gaussian_signature(g)
    if was_edit:
        bpy.ops.object.mode_set(mode="EDIT")


class RECGS_OT_train(bpy.types.Operator):
    """Train the selected Gaussian object on the scene folder's photos (a background job; the viewport updates at each checkpoint)"""

    bl_idname = "recgs.train"
    bl_label = "Train"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return _run(self, start_training, context.scene, context.active_object)


class RECGS_OT_resume(bpy.types.Operator):
    """Continue the selected object's last job; if its Gaussians were edited, train from the edited Gaussians"""

    bl_idname = "recgs.resume"
    bl_label = "Resume"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return _run(self, start_training, context.scene, context.active_object, True)


class RECGS_OT_cancel(bpy.types.Operator):
    """Stop the running job; training writes its checkpoint first, so Resume can continue it"""

    bl_idname = "recgs.cancel"
    bl_label = "Cancel"
    bl_options = {"REGISTER"}

    def execute(self, context):
        if not cancel():
            self.report({"ERROR"}, "No RecGS job is running")
            return {"CANCELLED"}
        self.report({"INFO"}, "Stopping the job (it writes its checkpoint first)")
        return {"FINISHED"}


classes = (RECGS_OT_train, RECGS_OT_resume, RECGS_OT_cancel) + reconstruct.classes + outputs.classes


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    job_follow.register()


def unregister() -> None:
    job_follow.unregister()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
