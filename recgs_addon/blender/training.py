"""The artist's workflow: train, follow, cancel, resume, reconstruct from photos or a video, outputs.

Jobs run as separate processes (:mod:`.jobs`); Blender data is only touched on the main
thread, by :func:`pump` (a ``bpy.app.timers`` function in the UI, a plain loop in the batch
script). Each ``checkpoint`` event replaces the Gaussian object's mesh with the job's
``point_cloud.ply`` (live preview); the object's transform is kept. Only names are kept
between calls (undo invalidates Python references to Blender data).

Resume uses the object as the artist left it: when its Gaussians (world space) differ from
both the last checkpoint's PLY and what the last live update wrote, they are baked into the
mesh, written to ``OUT/edited_init.ply`` and the job starts from them (``--init-ply``, a
fresh optimiser); otherwise it continues the checkpoint (``--resume``).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import StringProperty

from ..core.errors import RecGSError
from ..core.io.atomic import copy_file, make_folder
from . import gaussian_object as gobj
from . import jobs
from .operators import add_preview, import_survey
from .properties import CAUSTIC_MODES, train_options

#: Seconds between two runs of the timer that follows a job.
TIMER_INTERVAL_S = 0.25
#: Output folder inside the scene folder when the settings leave it empty.
DEFAULT_OUT = "recgs_out"
#: Name of the text datablock that Open Report fills.
REPORT_TEXT = "RecGS report"


class WorkflowError(RecGSError):
    """A request the workflow refuses (shown to the artist with ``self.report``)."""


@dataclass
class ActiveJob:
    job: jobs.Job
    scene_name: str
    object_name: str = ""
    scene_dir: str = ""
    out_dir: str = ""


_active: Optional[ActiveJob] = None
#: The full message (with the job's last stderr lines) of the last failed job.
last_failure = ""


def active_job() -> Optional[ActiveJob]:
    """The job being followed (running, or finished but not yet drained by :func:`pump`)."""
    return _active


def is_running() -> bool:
    return _active is not None


# -- paths ------------------------------------------------------------------------------------

def _abspath(p: str) -> Optional[Path]:
    return Path(bpy.path.abspath(p)) if p else None


def scene_dir_for(settings, obj=None) -> Path:
    """The survey folder: the sidebar's Scene Folder, else the one the object came from."""
    d = _abspath(settings.scene_dir) or (_abspath(obj.get("recgs_scene_dir", "")) if obj is not None else None)
    if d is None:
        raise WorkflowError("Set the Scene Folder (a folder with images/ and sparse/0), or import a "
                            "COLMAP survey first")
    if not d.is_dir():
        raise WorkflowError(f"{d}: scene folder is missing")
    if not (d / "sparse").is_dir():
        raise WorkflowError(f"{d}: no COLMAP model (sparse/0); use Reconstruct from Photos first")
    return d


def out_dir_for(settings, obj=None, scene_dir: Optional[Path] = None) -> Optional[Path]:
    """The job folder: the object's last one, else the Output Folder, else SCENE/recgs_out."""
    if obj is not None and obj.get("recgs_out_dir"):
        return Path(obj["recgs_out_dir"])
    if settings.out_dir:
        return _abspath(settings.out_dir)
    return scene_dir / DEFAULT_OUT if scene_dir is not None else None


def _gaussian_object(obj):
    if obj is None or not gobj.is_gaussian_object(obj):
        raise WorkflowError("Select a Gaussian object (Import COLMAP first)")
    return obj


def _check_free() -> None:
    if _active is not None:
        raise WorkflowError(f"A RecGS {_active.job.kind} job is already running: cancel it or wait")


def _check_modules(*names: str, what: str) -> None:
    missing = jobs.missing_modules(names)
    if missing:
        python = jobs.worker_python()
        which = "Blender's Python" if python == sys.executable else "the Python chosen in the RecGS preferences"
        raise WorkflowError(f"{what} needs the Python package(s) {', '.join(missing)} in {which} ({python}), "
                            "which runs RecGS jobs")


# -- starting jobs ----------------------------------------------------------------------------

def _begin(job: jobs.Job, scene, **names) -> ActiveJob:
    global _active
    _active = ActiveJob(job, scene.name, **names)
    s = scene.recgs
    s.status, s.job_kind, s.phase, s.message, s.plan = "RUNNING", job.kind, "starting", "", ""
    s.iteration, s.progress, s.elapsed, s.eta, s.psnr_test = 0, 0.0, 0.0, -1.0, -1.0
    _ui_begin()
    if not bpy.app.timers.is_registered(pump):
        bpy.app.timers.register(pump, first_interval=TIMER_INTERVAL_S, persistent=True)
    _ui_update(s)
    return _active


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
        if not (out / "checkpoint.pt").is_file():
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
    if (target / "sparse" / "0").exists():
        raise WorkflowError(f"{target}: already has a COLMAP model (sparse/0); use Import COLMAP, or clear "
                            "the Scene Folder to import the video beside it")
    argv = jobs.video_command(clip, target, s.video_frames, s.video_every, s.video_max_side)
    job = jobs.Job("video", argv, echo_stderr=echo_stderr)
    s.scene_dir = str(target)
    _begin(job, scene, scene_dir=str(target))
    return f"Importing {clip} into {target}"


#: Share of a job's progress bar each phase takes (start, span).
PHASE_SPANS = {
    "sfm": {"features": (0.0, 0.4), "matching": (0.4, 0.3), "mapping": (0.7, 0.3)},
    "video": {"frames": (0.0, 0.2), "features": (0.2, 0.3), "matching": (0.5, 0.25), "mapping": (0.75, 0.25)},
}


def cancel() -> bool:
    """Ask the running job to stop (it checkpoints first). False if none runs."""
    a = _active
    if a is None or not a.job.running:
        return False
    a.job.terminate()
    scene = bpy.data.scenes.get(a.scene_name)
    if scene is not None:
        scene.recgs.status = "CANCELLING"
        _ui_update(scene.recgs)
    return True


# -- following a job (main thread) ------------------------------------------------------------

def pump() -> Optional[float]:
    """Apply the events that arrived; the ``bpy.app.timers`` function (returns the next
    interval, or None when the job has ended and everything has been applied)."""
    global _active
    a = _active
    if a is None:
        return None
    scene = bpy.data.scenes.get(a.scene_name)
    for ev in a.job.poll():
        if scene is not None:
            try:
                _apply(a, scene.recgs, ev)
            except Exception as exc:  # never let the timer die with the job still running
                scene.recgs.message = f"{ev.get('event')} event: {exc}"
                print(f"RecGS: {scene.recgs.message}", file=sys.stderr)
    if not a.job.finished:
        return TIMER_INTERVAL_S
    _active = None
    try:
        if scene is not None:
            _finish(a, scene)
    finally:
        _ui_end()
    return None


def wait(poll_s: float = 0.2, timeout: Optional[float] = None) -> str:
    """Follow the job to its end from a plain loop (batch mode). Returns the final status."""
    import time

    a = _active
    t0 = time.monotonic()
    while pump() is not None:
        if timeout is not None and time.monotonic() - t0 > timeout:
            cancel()
            timeout = None
        time.sleep(poll_s)
    scene = bpy.data.scenes.get(a.scene_name) if a else None
    return scene.recgs.status if scene else "IDLE"


def _apply(a: ActiveJob, s, ev: dict) -> None:
    kind = ev["event"]
    if a.job.kind in PHASE_SPANS:
        if kind == "progress":
            lo, span = PHASE_SPANS[a.job.kind].get(ev.get("phase"), (0.0, 1.0))
            done, total = ev.get("done", 0), max(1, ev.get("total", 1))
            s.phase = f"{ev.get('phase', '')} {done}/{total}"
            if ev.get("chosen") is not None:
                s.phase += f", {ev['chosen']} chosen"
            s.progress = min(1.0, lo + span * done / total)
            s.elapsed = float(ev.get("elapsed") or 0.0)
        elif kind == "start" and a.job.kind == "video":
            s.message = (f"{ev.get('codec')} {ev.get('width')}x{ev.get('height')}, {ev.get('duration_s')} s"
                         + (", continuing the last import" if ev.get("resumed") else ""))
        elif kind == "done" and ev.get("status") == "cancelled":
            s.message = "cancelled; Import Video again continues where it stopped"
        elif kind == "done" and a.job.kind == "video":
            s.message = (f"{ev.get('chosen')} frames of {ev.get('frame_count')} chosen, registered "
                         f"{ev.get('registered')}, {ev.get('points')} points")
        elif kind == "done":
            s.message = (f"registered {ev.get('registered')}/{ev.get('images')} photos, "
                         f"{ev.get('points')} points")
    elif kind == "reading":
        s.phase = f"reading images {ev.get('done', 0)}/{ev.get('total', 0)}"
    elif kind == "plan":
        s.plan = "\n".join(str(line) for line in ev.get("lines", []))
    elif kind == "start":
        s.iteration, s.gaussians = int(ev.get("iteration") or 0), int(ev.get("gaussians") or 0)
    elif kind == "progress":
        s.phase = str(ev.get("phase", ""))
        s.iteration = int(ev.get("iteration") or 0)
        s.gaussians = int(ev.get("gaussians") or 0)
        s.elapsed = float(ev.get("elapsed") or 0.0)
        eta = ev.get("eta")
        s.eta = float(eta) if eta is not None else -1.0
        if ev.get("psnr_test") is not None:
            s.psnr_test = float(ev["psnr_test"])
        if eta is not None and s.elapsed + eta > 0:
            s.progress = min(1.0, s.elapsed / (s.elapsed + eta))
        elif s.max_minutes > 0:
            s.progress = min(1.0, s.elapsed / (60 * s.max_minutes))
    elif kind == "checkpoint":
        s.gaussians = int(ev.get("gaussians") or s.gaussians)
        obj = bpy.data.objects.get(a.object_name)
        if obj is None:
            s.message = f"{a.object_name}: object is gone; the job's model is in {ev.get('ply')}"
        else:
            note = live_update(obj, ev["ply"])
            s.message = note or f"viewport updated at iteration {ev.get('iteration')}"
    elif kind == "done":
        s.iteration = int(ev.get("iteration") or ev.get("iterations") or s.iteration)
        if ev.get("psnr_test") is not None:
            s.psnr_test = float(ev["psnr_test"])
        if ev.get("status") == "cancelled":
            s.message = f"cancelled at iteration {s.iteration}; checkpoint saved (Resume continues)"
        else:
            s.message = f"finished ({ev.get('reason', 'done')}) after {s.iteration} iterations"
    elif kind == "error":
        s.message = str(ev.get("message", "error"))
    _ui_update(s)


def live_update(obj, ply) -> str:
    """Replace the object's Gaussians with the PLY's (object transform kept). Returns a note
    ("" when updated)."""
    from ..core.io.ply import read_gaussian_ply

    if obj.mode == "EDIT":
        return f"{obj.name} is in Edit Mode: viewport not updated (the job goes on)"
    g = read_gaussian_ply(ply)
    gobj.write_mesh(obj.data, g)
    obj["recgs_synced"] = jobs.gaussian_signature(g)
    return add_preview(obj)


def _finish(a: ActiveJob, scene) -> None:
    global last_failure
    s = scene.recgs
    status, msg = a.job.outcome()
    s.status = {"done": "DONE", "cancelled": "CANCELLED"}.get(status, "FAILED")
    if status == "failed":
        s.message = msg.splitlines()[0] if msg else "failed"
        last_failure = msg
        print(f"RecGS: the {a.job.kind} job failed: {msg}", file=sys.stderr)
    elif a.job.kind in ("sfm", "video") and status == "done":
        s.progress = 1.0
        try:
            layer = bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]
            obj, imported = import_survey(scene, layer, a.scene_dir, "images", 0)
            warning = add_preview(obj)
            s.message = f"{s.message}; {imported}" + (f" ({warning})" if warning else "")
        except (RecGSError, OSError, ImportError) as exc:
            s.status, s.message = "FAILED", f"reconstructed, but the import failed: {exc}"
    elif status == "done":
        s.progress = 1.0
    _ui_update(s)


# -- progress in the UI (status bar, window-manager progress, redraws) -------------------------

def _windows():
    wm = bpy.context.window_manager
    return list(wm.windows) if wm is not None and not bpy.app.background else []


def _ui_begin() -> None:
    if _windows():
        bpy.context.window_manager.progress_begin(0, 1000)


def _ui_end() -> None:
    wins = _windows()
    if wins:
        bpy.context.window_manager.progress_end()
    for win in wins:
        try:
            win.workspace.status_text_set(None)
        except (AttributeError, RuntimeError):
            pass
    _redraw(wins)


def status_line(s) -> str:
    if s.job_kind in PHASE_SPANS:
        what = "video import" if s.job_kind == "video" else "reconstruct"
        return f"RecGS {what}: {s.phase}, {format_seconds(s.elapsed)}"
    parts = [f"RecGS {s.status.lower()}: {s.phase}", f"iteration {s.iteration}", f"{s.gaussians:,} Gaussians"]
    if s.psnr_test >= 0:
        parts.append(f"held-out PSNR {s.psnr_test:.2f} dB")
    parts.append(f"{format_seconds(s.elapsed)} elapsed")
    if s.eta >= 0:
        parts.append(f"~{format_seconds(s.eta)} left")
    return ", ".join(parts)


def format_seconds(t: float) -> str:
    t = int(round(max(0.0, t)))
    return f"{t // 3600}:{t // 60 % 60:02d}:{t % 60:02d}" if t >= 3600 else f"{t // 60}:{t % 60:02d}"


def _ui_update(s) -> None:
    wins = _windows()
    if not wins:
        return
    bpy.context.window_manager.progress_update(int(1000 * s.progress))
    text = status_line(s) if s.status in ("RUNNING", "CANCELLING") else None
    for win in wins:
        try:
            win.workspace.status_text_set(text)
        except (AttributeError, RuntimeError):
            pass
    _redraw(wins)


def _redraw(wins) -> None:
    for win in wins:
        for area in win.screen.areas:
            if area.type in ("VIEW_3D", "STATUSBAR", "PROPERTIES"):
                area.tag_redraw()


# -- handlers: end jobs cleanly when another file is opened ------------------------------------

def stop_active(timeout: float = jobs.STOP_TIMEOUT_S) -> None:
    """Stop the followed job (checkpoint written), apply its last events, forget it."""
    global _active
    if _active is None:
        return
    _active.job.stop(timeout)
    pump()
    _active = None


@persistent
def _on_load_pre(*_args) -> None:
    stop_active()
    jobs.stop_all()


@persistent
def _on_load_post(*_args) -> None:
    for scene in bpy.data.scenes:
        s = getattr(scene, "recgs", None)
        if s is not None and s.status in ("RUNNING", "CANCELLING"):
            s.status = "CANCELLED"
            s.message = "the job was stopped when the file was closed; Resume continues from its checkpoint"


# -- operators ----------------------------------------------------------------------------------

def _run(op, fn, *args) -> set:
    try:
        op.report({"INFO"}, fn(*args))
    except (RecGSError, OSError, ValueError) as exc:
        op.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    return {"FINISHED"}


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


def _job_out(context) -> Path:
    obj = context.active_object
    s = context.scene.recgs
    try:
        scene_dir = scene_dir_for(s, obj)
    except WorkflowError:
        scene_dir = None
    out = out_dir_for(s, obj, scene_dir)
    if out is None or not out.is_dir():
        raise WorkflowError("No training output yet: Train first (or set the Output Folder)")
    return out


class RECGS_OT_export_images(bpy.types.Operator):
    """Copy the caustic-free photos written by the last caustic-removal job to a folder"""

    bl_idname = "recgs.export_images"
    bl_label = "Export Caustic-Free Images"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH")
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        return _run(self, self._export, context)

    def _export(self, context) -> str:
        src = _job_out(context) / "decaustic"
        files = sorted(p for p in src.glob("*") if p.is_file()) if src.is_dir() else []
        if not files:
            raise WorkflowError(f"{src}: no caustic-free images; train with a caustic-removal mode "
                                "(RecGS, 2D Filter, Joint) first")
        if not self.directory:
            raise WorkflowError("Choose a folder to export the images to")
        dst = make_folder(Path(bpy.path.abspath(self.directory)), "folder")
        for p in files:
            copy_file(p, dst / p.name, "image")
        return f"Exported {len(files)} caustic-free images to {dst}"


class RECGS_OT_open_report(bpy.types.Operator):
    """Open the last job's report (report.md, else metrics.json) in a Text Editor"""

    bl_idname = "recgs.open_report"
    bl_label = "Open Report"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return _run(self, self._open, context)

    def _open(self, context) -> str:
        out = _job_out(context)
        path = next((p for p in (out / "report.md", out / "metrics.json") if p.is_file()), None)
        if path is None:
            raise WorkflowError(f"{out}: no report.md or metrics.json yet (they are written when a job ends)")
        text = bpy.data.texts.get(REPORT_TEXT) or bpy.data.texts.new(REPORT_TEXT)
        text.from_string(path.read_text(encoding="utf-8"))
        text.filepath = str(path)
        shown = _show_text(context, text)
        return f"Opened {path}" + ("" if shown else f" as the text '{REPORT_TEXT}' (open it in a Text Editor)")


def _show_text(context, text) -> bool:
    if context.window is None or bpy.app.background:
        return False
    for area in context.screen.areas:
        if area.type == "TEXT_EDITOR":
            area.spaces.active.text = text
            return True
    try:  # a new window showing the text
        bpy.ops.wm.window_new()
        area = bpy.context.window_manager.windows[-1].screen.areas[0]
        area.type = "TEXT_EDITOR"
        area.spaces.active.text = text
        return True
    except (RuntimeError, IndexError, AttributeError):
        return False


classes = (RECGS_OT_train, RECGS_OT_resume, RECGS_OT_cancel, RECGS_OT_reconstruct, RECGS_OT_import_video,
           RECGS_OT_export_images, RECGS_OT_open_report)


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.app.handlers.load_pre.append(_on_load_pre)
    bpy.app.handlers.load_post.append(_on_load_post)


def unregister() -> None:
    stop_active()
    if bpy.app.timers.is_registered(pump):
        bpy.app.timers.unregister(pump)
    for lst, fn in ((bpy.app.handlers.load_pre, _on_load_pre), (bpy.app.handlers.load_post, _on_load_post)):
        while fn in lst:
            lst.remove(fn)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

