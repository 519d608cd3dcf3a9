"""Operators: Import COLMAP, Import 3DGS PLY, Export 3DGS PLY.

They hold no numerics: they call the core, convert with gaussian_object/cameras, and report
every problem through ``self.report``. All input is checked before any Blender data is
created, so a failed import leaves the scene as it was.
"""
from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core.errors import RecGSError
from . import cameras as bcams
from . import gaussian_object as gobj


def _missing_dependency(exc: ImportError) -> str:
    return (f"RecGS needs the Python package '{exc.name}', which this Blender's Python lacks. The "
            "extension zip for your platform bundles it: reinstall the zip made for this system "
            "(README, 'Using it in Blender').")


def _make_active(view_layer, obj) -> None:
    """Select ``obj`` alone and make it the active object."""
    for o in view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    view_layer.objects.active = obj


class RECGS_OT_import_colmap(bpy.types.Operator):
    """Import a COLMAP survey (images/ and sparse/): one camera per image and the initial Gaussians"""

    bl_idname = "recgs.import_colmap"
    bl_label = "Import COLMAP Survey"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Scene Folder", subtype="DIR_PATH",
                              description="Folder holding images/ and sparse/0 (or sparse/)")
    images: StringProperty(name="Image Folder", default="images",
                           description="Image folder inside the scene folder (e.g. 'clean')")
    sh_degree: IntProperty(name="SH Degree", default=0, min=0, max=3,
                           description="Spherical-harmonic degree of the initial Gaussians "
                                       "(training raises it only where it helps)")
    filter_folder: BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if not self.directory:
            self.report({"ERROR"}, "Choose a scene folder (with images/ and sparse/)")
            return {"CANCELLED"}
        try:
            obj, msg = import_survey(context.scene, context.view_layer, bpy.path.abspath(self.directory),
                                     self.images, self.sh_degree)
        except ImportError as exc:
            self.report({"ERROR"}, _missing_dependency(exc))
            return {"CANCELLED"}
        except (RecGSError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, msg)
        warning = add_preview(obj)
        if warning:
            self.report({"WARNING"}, warning)
        return {"FINISHED"}


def import_survey(scene, view_layer, scene_dir, images: str = "images", sh_degree: int = 0):
    """Import a COLMAP survey into ``scene``: a collection with one camera per image and the
    Gaussian object, made active. Returns ``(object, message)``. Raises RecGSError, OSError
    or ImportError before anything is created."""
    from ..core.io.colmap import load_scene
    from ..core.model.gaussians import init_from_points

    t0 = time.perf_counter()
    scene_dir = Path(scene_dir)
    image_dir = Path(images) if os.path.isabs(images) else scene_dir / images
    survey = load_scene(scene_dir, image_dir=image_dir)
    g = init_from_points(survey.points, survey.colors, sh_degree=sh_degree)
    name = scene_dir.resolve().name or "survey"
    coll = bpy.data.collections.new(f"RecGS {name}")
    scene.collection.children.link(coll)
    cam_coll = bpy.data.collections.new(f"{name} cameras")
    coll.children.link(cam_coll)
    cam_objs = [bcams.create_camera_object(c, cam_coll) for c in survey.cameras]
    obj = gobj.create_gaussian_object(f"{name} Gaussians", g, coll)
    obj["recgs_scene_dir"] = str(scene_dir)
    obj["recgs_image_dir"] = str(image_dir)
    if survey.undistorted:
        obj["recgs_undistorted_dir"] = str(survey.image_dir)
    bcams.apply_render_settings(scene, cam_objs[0])
    _make_active(view_layer, obj)
    settings = getattr(scene, "recgs", None)
    if settings is not None:  # the sidebar shows the folder last imported
        settings.scene_dir = str(scene_dir)
        if not os.path.isabs(images):
            settings.images = images
    msg = (f"Imported {len(cam_objs)} cameras and {len(g)} Gaussians from {scene_dir} "
           f"in {time.perf_counter() - t0:.2f} s")
    if survey.undistorted:
        msg += f" (images undistorted to {survey.image_dir})"
    return obj, msg


def add_preview(obj) -> str:
    """Add the viewport preview to a Gaussian object; returns a warning ("" if it worked)."""
    from . import preview

    try:
        preview.ensure_preview(obj)
    except Exception as exc:  # the preview is a convenience: never fail an import for it
        return f"{obj.name}: viewport preview not added ({exc})"
    return ""


class RECGS_OT_import_ply(bpy.types.Operator, ImportHelper):
    """Import a 3D Gaussian Splatting PLY (INRIA layout or another tool's)"""

    bl_idname = "recgs.import_ply"
    bl_label = "Import 3DGS PLY"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})

    def execute(self, context):
        from ..core.io.ply import read_gaussian_ply

        path = Path(bpy.path.abspath(self.filepath))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                g = read_gaussian_ply(path)
        except (RecGSError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for w in caught:
            self.report({"WARNING"}, str(w.message))
        obj = gobj.create_gaussian_object(path.stem, g, context.collection)
        obj["recgs_source_ply"] = str(path)
        _make_active(context.view_layer, obj)
        self.report({"INFO"}, f"Imported {len(g)} Gaussians (SH degree {g.sh_degree}) from {path}")
        warning = add_preview(obj)
        if warning:
            self.report({"WARNING"}, warning)
        return {"FINISHED"}


class RECGS_OT_export_ply(bpy.types.Operator, ExportHelper):
    """Export the active Gaussian object as a standard 3DGS PLY (object transform baked in)"""

    bl_idname = "recgs.export_ply"
    bl_label = "Export 3DGS PLY"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})
    apply_transform: BoolProperty(name="Apply Object Transform", default=True,
                                  description="Bake the object's location, rotation and uniform "
                                              "scale into the Gaussians (SH rotated too)")

    def execute(self, context):
        from ..core.io.ply import write_gaussian_ply

        obj = context.active_object
        if obj is None or not gobj.is_gaussian_object(obj):
            self.report({"ERROR"}, "Select a Gaussian object (one imported by RecGS) to export")
            return {"CANCELLED"}
        try:
            with gobj.edits_flushed(obj):
                g = gobj.gaussians_from_object(obj, world=self.apply_transform)
            path = Path(bpy.path.abspath(self.filepath))
            write_gaussian_ply(path, g)
        except (RecGSError, ValueError, OSError) as exc:
            self.report({"ERROR"}, f"{obj.name}: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Exported {len(g)} Gaussians to {path}")
        return {"FINISHED"}


def menu_import(self, context):
    self.layout.operator(RECGS_OT_import_colmap.bl_idname, text="COLMAP Survey (RecGS)")
    self.layout.operator(RECGS_OT_import_ply.bl_idname, text="3D Gaussian Splatting (.ply)")


def menu_export(self, context):
    self.layout.operator(RECGS_OT_export_ply.bl_idname, text="3D Gaussian Splatting (.ply)")


classes = (RECGS_OT_import_colmap, RECGS_OT_import_ply, RECGS_OT_export_ply)
