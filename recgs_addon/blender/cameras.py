"""Blender camera objects from core cameras (and back). The axis change lives in core.model.cameras."""
from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix

from ..core.model.cameras import Camera, blender_intrinsics, blender_matrix_from_pose


def create_camera_object(cam: Camera, collection) -> "bpy.types.Object":
    """A camera object named after the image, reproducing its intrinsics and pose.

    Resolution and pixel aspect are scene render settings in Blender, so they are also kept
    on the camera data (``recgs_resolution``, ``recgs_pixel_aspect``) and applied with
    :func:`apply_render_settings` when the camera is made active.
    """
    s = blender_intrinsics(cam)
    data = bpy.data.cameras.new(cam.name)
    data.sensor_fit = s["sensor_fit"]
    data.sensor_width = s["sensor_width"]
    data.lens = s["lens"]
    data.shift_x = s["shift_x"]
    data.shift_y = s["shift_y"]
    data.clip_start = 0.01
    data.clip_end = 1000.0
    data["recgs_resolution"] = (s["resolution_x"], s["resolution_y"])
    data["recgs_pixel_aspect"] = (s["pixel_aspect_x"], s["pixel_aspect_y"])
    data["recgs_intrinsics"] = (cam.fx, cam.fy, cam.cx, cam.cy)
    data["recgs_image_name"] = cam.name  # object names may be shortened by Blender
    obj = bpy.data.objects.new(cam.name, data)
    obj.matrix_world = Matrix(blender_matrix_from_pose(cam.R, cam.t).tolist())
    collection.objects.link(obj)
    return obj


def apply_render_settings(scene, cam_obj) -> None:
    """Make ``cam_obj`` the scene camera with its image's resolution and pixel aspect."""
    scene.camera = cam_obj
    data = cam_obj.data
    if "recgs_resolution" in data:
        w, h = data["recgs_resolution"]
        ax, ay = data["recgs_pixel_aspect"]
        r = scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = int(w), int(h), 100
        r.pixel_aspect_x, r.pixel_aspect_y = float(ax), float(ay)


def camera_from_object(cam_obj) -> Camera:
    """Core camera from a camera object created by :func:`create_camera_object` (follows moves)."""
    from ..core.model.cameras import pose_from_blender_matrix

    fx, fy, cx, cy = cam_obj.data["recgs_intrinsics"]
    w, h = cam_obj.data["recgs_resolution"]
    R, t = pose_from_blender_matrix(np.array(cam_obj.matrix_world, dtype=np.float64))
    return Camera(str(cam_obj.data.get("recgs_image_name", cam_obj.name)), int(w), int(h), fx, fy, cx, cy, R, t)
