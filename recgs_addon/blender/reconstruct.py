"""Reconstruct from Photos and Import Video: the ``sfm`` and ``video`` jobs that make a COLMAP
survey in the Scene Folder, imported as a Gaussian object when they end (:mod:`.job_follow`)."""
from __future__ import annotations

import bpy

from ..core.io.looks import placing_finished
from . import jobs
from .job_follow import _begin, _check_free
from .workflow import WorkflowError, _abspath, _check_modules, _run


def start_reconstruction(scene, echo_stderr: bool = False) -> str:
    """Run ``sfm`` on the Photo Folder into the Scene Folder (default: PHOTOS_scene beside
    the photos); the result is imported when the job ends."""
    _check_free()
    s = scene.recgs
    photos = _abspath(s.photo_dir)
    if photos is None:
        raise WorkflowError("Set the Photo Folder (the photos to reconstruct)")
    if not photos.is_dir():
        raise WorkflowError(f"{photos}: photo folder is missing")
    _check_modules("pycolmap", what="Reconstruct from Photos")
    target = _abspath(s.scene_dir) or photos.parent / f"{photos.name}_scene"
    if (target / "sparse" / "0").exists():
        raise WorkflowError(f"{target}: already has a COLMAP model (sparse/0); use Import COLMAP")
    job = jobs.Job("sfm", jobs.sfm_command(photos, target, link=s.link_photos), echo_stderr=echo_stderr)
    s.scene_dir = str(target)
    _begin(job, scene, scene_dir=str(target))
    return f"Reconstructing {photos} into {target}"


def start_video_import(scene, echo_stderr: bool = False) -> str:
    """Run ``video`` on the Video File into the Scene Folder (default: CLIP_survey beside the
    clip); the result is imported when the job ends. After a cancel, the same request
    continues where the job stopped (the command resumes its steps)."""
    _check_free()
    s = scene.recgs
    clip = _abspath(s.video_path)
    if clip is None:
        raise WorkflowError("Set the Video File (a clip of the survey)")
    if not clip.is_file():
        raise WorkflowError(f"{clip}: video file is missing")
    if "av" in jobs.missing_modules(["av"]):
        raise WorkflowError("Import Video needs PyAV, which comes with the training engine: click Install "
                            "Training Engine (or Update Training Engine) in the RecGS preferences or sidebar, "
                            "or choose a Python with PyAV in the preferences")
    _check_modules("pycolmap", what="Import Video")
    target = _abspath(s.scene_dir) or clip.parent / f"{clip.stem}_survey"
    # a job stopped while it placed the look frames has its model already: it goes on
    if (target / "sparse" / "0").exists() and placing_finished(target, target / "sparse" / "0"):
        raise WorkflowError(f"{target}: already has a COLMAP model (sparse/0); use Import COLMAP, or clear "
                            "the Scene Folder to import the video beside it")
    argv = jobs.video_command(clip, target, s.video_frames, s.video_every, s.video_max_side)
    job = jobs.Job("video", argv, echo_stderr=echo_stderr)
    s.scene_dir = str(target)
    _begin(job, scene, scene_dir=str(target))
    return f"Importing {clip} into {target}"


class RECGS_OT_reconstruct(bpy.types.Operator):
    """Run structure from motion (pycolmap) on the Photo Folder in the background, then import the result"""

    bl_idname = "recgs.reconstruct"
    bl_label = "Reconstruct from Photos"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return _run(self, start_reconstruction, context.scene)


class RECGS_OT_import_video(bpy.types.Operator):
    """Choose sharp, distinct frames of the Video File and run structure from motion on them in the background (one camera, frames matched in time order), then import the survey"""

    bl_idname = "recgs.import_video"
    bl_label = "Import Video"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return _run(self, start_video_import, context.scene)


classes = (RECGS_OT_reconstruct, RECGS_OT_import_video)
