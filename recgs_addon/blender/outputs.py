"""A finished job's outputs: Export Caustic-Free Images (copies ``OUT/decaustic`` to a folder,
and ``OUT/truecolour`` to its ``truecolour`` subfolder where the job modelled the water)
and Open Report (``report.md``, else ``metrics.json``, in a Text Editor)."""
from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import StringProperty

from ..core.caustics.config import CAUSTIC_MODES
from ..core.io.atomic import copy_file, make_folder
from .workflow import WorkflowError, _run, out_dir_for, scene_dir_for

#: Name of the text datablock that Open Report fills.
REPORT_TEXT = "RecGS report"


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


def _metrics(out: Path) -> dict:
    """The job's ``metrics.json`` ({} where it has none or it does not parse)."""
    import json

    try:
        return json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


class RECGS_OT_export_images(bpy.types.Operator):
    """Copy the caustic-free photos written by the last caustic-removal job to a folder (and,
    where the job modelled the water, the photos in true colour to its truecolour subfolder)"""

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
        out = _job_out(context)
        src, true_src = out / "decaustic", out / "truecolour"
        files = sorted(p for p in src.glob("*") if p.is_file()) if src.is_dir() else []
        true = sorted(p for p in true_src.glob("*") if p.is_file()) if true_src.is_dir() else []
        if not files and not true:
            metrics = _metrics(out)
            dropped = metrics.get("caustics_dropped") or (
                "it ended before its first caustic estimate" if (metrics.get("config") or {}).get("mode")
                in CAUSTIC_MODES else None)
            if dropped:
                raise WorkflowError(f"{out}: the job took no light off ({dropped}), so its photos are caustic-free "
                                    "as they are and it wrote no copies of them")
            raise WorkflowError(f"{src}: no caustic-free images; train with a caustic-removal mode "
                                "(RecGS, 2D Filter, Joint) first")
        if not self.directory:
            raise WorkflowError("Choose a folder to export the images to")
        dst = make_folder(Path(bpy.path.abspath(self.directory)), "folder")
        for p in files:
            copy_file(p, dst / p.name, "image")
        if true:
            tdst = make_folder(dst / "truecolour", "folder")
            for p in true:
                copy_file(p, tdst / p.name, "image")
        parts = [f"{len(files)} caustic-free images"] if files else []
        if true:
            parts.append(f"{len(true)} in true colour (truecolour/)")
        return f"Exported {' and '.join(parts)} to {dst}"


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


classes = (RECGS_OT_export_images, RECGS_OT_open_report)
