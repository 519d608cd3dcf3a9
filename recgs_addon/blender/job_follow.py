"""The job Blender follows (one at a time): starting, cancelling, and applying its events.

Jobs run as separate processes (:mod:`.jobs`); Blender data is only touched on the main
thread, by :func:`pump` (a ``bpy.app.timers`` function in the UI, a plain loop in the batch
script). Each ``checkpoint`` event replaces the Gaussian object's mesh with the job's
``point_cloud.ply`` (live preview); the object's transform is kept. Only names are kept
between calls (undo invalidates Python references to Blender data).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import bpy
from bpy.app.handlers import persistent

from ..core.capture.video import describe_ranges
from ..core.errors import RecGSError
from . import gaussian_object as gobj
from . import jobs
from .job_progress import PHASE_SPANS, _ui_begin, _ui_end, _ui_update
from .operators import add_preview, import_survey
from .water import load_water
from .workflow import WorkflowError

#: Seconds between two runs of the timer that follows a job.
TIMER_INTERVAL_S = 0.25


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


def _check_free() -> None:
    if _active is not None:
        raise WorkflowError(f"A RecGS {_active.job.kind} job is already running: cancel it or wait")


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
            looks = ev.get("looks") or {}
            if looks:
                n = looks.get("registered", 0) + looks.get("unregistered", 0)
                s.message += f"; {n} look frames kept, {looks.get('registered', 0)} placed by their features"
            if ev.get("lost"):
                s.message += (f". Not registered: {describe_ranges(ev['lost'])} of the clip; the survey lacks what "
                              "only those frames saw (film it again slowly, or a smaller step on the command line)")
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
        s.progress = min(1.0, float(ev.get("fraction") or 0.0))   # the job's own share done
        if ev.get("blocks"):   # training in blocks: each block's step and score
            s.message = "; ".join(
                f"{b.get('block')}: " + ("done" if b.get("done") else f"it {b.get('iteration') or 0}")
                + (f", {b['psnr_test']:.2f} dB" if b.get("psnr_test") is not None else "") for b in ev["blocks"])
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
        if a.job.kind == "train":
            note = load_water(scene, Path(a.out_dir)) if a.out_dir else ""
            if note:
                s.message = f"{s.message}; {note}"
    _ui_update(s)


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


def register() -> None:
    """Install the load handlers (the operators are registered by :mod:`.training`)."""
    bpy.app.handlers.load_pre.append(_on_load_pre)
    bpy.app.handlers.load_post.append(_on_load_post)


def unregister() -> None:
    """Stop the followed job and its timer; remove the load handlers."""
    stop_active()
    if bpy.app.timers.is_registered(pump):
        bpy.app.timers.unregister(pump)
    for lst, fn in ((bpy.app.handlers.load_pre, _on_load_pre), (bpy.app.handlers.load_post, _on_load_post)):
        while fn in lst:
            lst.remove(fn)
