"""The "RecGS" tab of the 3D viewport's sidebar (N panel).

Scene (folder, Import COLMAP, Reconstruct from Photos, Import Video), Training (settings, Train / Cancel /
Resume, live figures; Advanced folded away), Output (Export PLY, caustic-free images,
report) and Preview (drawn by ``preview.draw_panel``). Panels only draw: every action is an
operator, every figure comes from ``scene.recgs`` (written by ``job_follow.pump``).
"""
from __future__ import annotations

import bpy

from . import gaussian_object as gobj
from . import engine, job_follow, job_progress, preview
from ..core.caustics.config import CAUSTIC_MODES


class _RecGSPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "RecGS"


class VIEW3D_PT_recgs(_RecGSPanel, bpy.types.Panel):
    bl_label = "RecGS"
    bl_idname = "VIEW3D_PT_recgs"

    def draw(self, context):
        layout = self.layout
        s = context.scene.recgs
        obj = context.active_object
        if obj is not None and gobj.is_gaussian_object(obj):
            layout.label(text=f"{obj.name}: {len(obj.data.vertices):,} Gaussians", icon="OUTLINER_OB_POINTCLOUD")
        else:
            layout.label(text="No Gaussian object selected", icon="INFO")
        if s.status != "IDLE":
            layout.label(text=f"Last job: {s.status.title()}", icon=_STATUS_ICONS.get(s.status, "NONE"))


_STATUS_ICONS = {"RUNNING": "PLAY", "CANCELLING": "PAUSE", "DONE": "CHECKMARK", "CANCELLED": "PAUSE",
                 "FAILED": "ERROR"}


class VIEW3D_PT_recgs_scene(_RecGSPanel, bpy.types.Panel):
    bl_label = "Scene"
    bl_idname = "VIEW3D_PT_recgs_scene"
    bl_parent_id = "VIEW3D_PT_recgs"

    def draw(self, context):
        layout = self.layout
        s = context.scene.recgs
        busy = job_follow.is_running()
        col = layout.column()
        col.prop(s, "scene_dir")
        col.prop(s, "images")
        row = col.row()
        row.enabled = not busy
        row.operator_context = "EXEC_DEFAULT"
        op = row.operator("recgs.import_colmap", text="Import COLMAP", icon="IMPORT")
        op.directory = s.scene_dir
        op.images = s.images
        box = layout.box()
        box.label(text="No COLMAP model yet?")
        box.prop(s, "photo_dir")
        box.prop(s, "link_photos")
        row = box.row()
        row.enabled = not busy
        row.operator("recgs.reconstruct", icon="CAMERA_DATA")
        box.separator()
        box.prop(s, "video_path")
        row = box.row(align=True)
        sub = row.row(align=True)
        sub.active = s.video_every <= 0
        sub.prop(s, "video_frames")
        row.prop(s, "video_every")
        box.prop(s, "video_max_side")
        row = box.row()
        row.enabled = not busy
        row.operator("recgs.import_video", icon="FILE_MOVIE")


class VIEW3D_PT_recgs_training(_RecGSPanel, bpy.types.Panel):
    bl_label = "Training"
    bl_idname = "VIEW3D_PT_recgs_training"
    bl_parent_id = "VIEW3D_PT_recgs"

    def draw(self, context):
        layout = self.layout
        s = context.scene.recgs
        busy = job_follow.is_running()
        col = layout.column()
        col.enabled = not busy
        col.prop(s, "mode")
        col.prop(s, "max_minutes", text="Time Limit (min)")
        row = col.row(align=True)
        row.prop(s, "budget_auto", text="Auto Budget")
        sub = row.row(align=True)
        sub.enabled = not s.budget_auto
        sub.prop(s, "budget", text="Budget")
        col.prop(s, "downscale")
        col.prop(s, "max_side")
        sub = col.row()
        sub.active = s.mode in CAUSTIC_MODES
        sub.prop(s, "caustic_k")
        col.prop(s, "medium")
        col.prop(s, "lamp")
        col.prop(s, "blocks")
        if s.blocks > 1:
            col.prop(s, "cluster")
        if s.water:
            layout.row().prop(s, "water_view", expand=True)
        if not busy and not engine.engine_ready():
            engine.draw_engine(layout)
        row = layout.row(align=True)
        row.scale_y = 1.4
        if busy:
            row.operator("recgs.cancel", icon="CANCEL")
        else:
            row.operator("recgs.train", icon="PLAY")
            row.operator("recgs.resume", icon="FILE_REFRESH")
        draw_progress(layout, s)


def draw_progress(layout, s) -> None:
    """Phase, iteration, held-out PSNR, Gaussians, elapsed and remaining time, last message."""
    if s.status == "IDLE":
        return
    box = layout.box()
    box.label(text=f"{s.status.title()}: {s.phase}" if s.phase else s.status.title(),
              icon=_STATUS_ICONS.get(s.status, "NONE"))
    if s.status in ("RUNNING", "CANCELLING"):
        box.prop(s, "progress", text="Progress", slider=True)
    col = box.column(align=True)
    if s.job_kind in job_progress.PHASE_SPANS:
        col.label(text=f"Elapsed: {job_progress.format_seconds(s.elapsed)}")
    else:
        col.label(text=f"Iteration: {s.iteration:,}")
        col.label(text="Held-out PSNR: " + (f"{s.psnr_test:.2f} dB" if s.psnr_test >= 0 else "not measured yet"))
        col.label(text=f"Gaussians: {s.gaussians:,}")
        col.label(text=f"Elapsed: {job_progress.format_seconds(s.elapsed)}, remaining: "
                       + (job_progress.format_seconds(s.eta) if s.eta >= 0 else "unknown"))
    if s.plan and s.job_kind == "train":
        col = box.column(align=True)
        for line in s.plan.splitlines():
            col.label(text=line)
    if s.message:
        col = box.column()
        col.alert = s.status == "FAILED"
        col.label(text=s.message, icon="ERROR" if s.status == "FAILED" else "INFO")


class VIEW3D_PT_recgs_advanced(_RecGSPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_idname = "VIEW3D_PT_recgs_advanced"
    bl_parent_id = "VIEW3D_PT_recgs_training"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        s = context.scene.recgs
        col = layout.column()
        col.enabled = not job_follow.is_running()
        for name in ("preset", "iterations", "sh_degree", "seed", "holdout_every", "checkpoint_every",
                     "device", "eager", "out_dir"):
            col.prop(s, name)


class VIEW3D_PT_recgs_output(_RecGSPanel, bpy.types.Panel):
    bl_label = "Output"
    bl_idname = "VIEW3D_PT_recgs_output"
    bl_parent_id = "VIEW3D_PT_recgs"

    def draw(self, context):
        col = self.layout.column(align=True)
        col.operator_context = "INVOKE_DEFAULT"
        col.operator("recgs.export_ply", text="Export PLY", icon="EXPORT")
        col.operator("recgs.export_images", icon="IMAGE_DATA")
        col.operator("recgs.open_report", icon="TEXT")


class VIEW3D_PT_recgs_preview(_RecGSPanel, bpy.types.Panel):
    bl_label = "Preview"
    bl_idname = "VIEW3D_PT_recgs_preview"
    bl_parent_id = "VIEW3D_PT_recgs"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        box = self.layout.box()
        preview.draw_panel(box, context)


classes = (VIEW3D_PT_recgs, VIEW3D_PT_recgs_scene, VIEW3D_PT_recgs_training, VIEW3D_PT_recgs_advanced,
           VIEW3D_PT_recgs_output, VIEW3D_PT_recgs_preview)
