"""The scene commands: ``import`` (a COLMAP survey into a new .blend with the add-on's own
operators, needs bpy) and ``info`` (what a Gaussian PLY holds, no Blender needed)."""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

from ..core.options.scene import IMPORT_OPTIONS, INFO_OPTIONS


def add_import_arguments(p: argparse.ArgumentParser) -> None:
    """The ``import`` options, from their one declaration (core/options/scene.py)."""
    IMPORT_OPTIONS.add_to(p)


def add_info_arguments(p: argparse.ArgumentParser) -> None:
    INFO_OPTIONS.add_to(p)


def _blender_projection_error(bpy, cam_objs, points) -> dict:
    """Project the sparse points with each Blender camera's own matrices (as Blender renders)
    and with the core pinhole camera; return the largest and mean difference in pixels."""
    import numpy as np

    from ..blender.cameras import apply_render_settings, camera_from_object

    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    pts = np.c_[points.astype(np.float64), np.ones(len(points))]
    worst, total, count = 0.0, 0.0, 0
    for obj in cam_objs:
        cam = camera_from_object(obj)
        apply_render_settings(scene, obj)
        r = scene.render
        P = np.array(obj.calc_matrix_camera(depsgraph, x=r.resolution_x, y=r.resolution_y,
                                            scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
        V = np.array(obj.matrix_world.inverted())
        clip = pts @ (P @ V).T
        ndc = clip[:, :2] / clip[:, 3:4]
        uv_b = np.c_[(ndc[:, 0] + 1) / 2 * cam.width, (1 - ndc[:, 1]) / 2 * cam.height]
        uv_c, z = cam.project(points)
        ok = (z > 0) & (uv_c[:, 0] >= 0) & (uv_c[:, 0] < cam.width) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < cam.height)
        if ok.any():
            d = np.abs(uv_b[ok] - uv_c[ok]).max(axis=1)
            worst = max(worst, float(d.max()))
            total += float(d.sum())
            count += int(ok.sum())
    return {"max_px": worst, "mean_px": total / max(count, 1), "projections": count}


def cmd_import(args) -> int:
    try:
        import bpy
    except ImportError:
        print("error: the 'import' command needs the bpy module (pip install bpy==5.0.1) "
              "or running inside Blender", file=sys.stderr)
        return 2
    from .. import blender as addon
    from ..core.errors import RecGSError

    out = args.out
    if out.exists() and not out.is_dir():
        print(f"error: {out}: is a file, not a folder (choose another output folder)", file=sys.stderr)
        return 1
    t_start = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        try:  # the operator checks all input before it makes anything
            res = bpy.ops.recgs.import_colmap(directory=str(args.scene_dir), images=args.images,
                                              sh_degree=args.sh_degree)
        except RuntimeError as exc:
            print(f"error: {str(exc).removeprefix('Error: ').strip()}", file=sys.stderr)
            return 1
        t_import = time.perf_counter() - t_start
        if res != {"FINISHED"}:
            print(f"error: import failed: {res}", file=sys.stderr)
            return 1
        try:
            lines = _write_import_outputs(bpy, args, out, t_start, t_import)
        except RuntimeError as exc:   # an operator's error report (the export's full disk, ...)
            print(f"error: {str(exc).removeprefix('Error: ').strip()}", file=sys.stderr)
            return 1
        except RecGSError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    finally:
        addon.unregister()
    print("\n".join(lines))
    return 0


def _write_import_outputs(bpy, args, out: Path, t_start: float, t_import: float) -> list[str]:
    """point_cloud.ply, scene.blend and the report of an import, each written whole or not at
    all (core/io/atomic.py); returns the report's lines."""
    from ..blender.blendfile import save_blend
    from ..blender.gaussian_object import read_mesh
    from ..core.io.atomic import atomic_path, make_folder
    from ..core.io.ply import read_gaussian_ply

    make_folder(out)
    obj = bpy.context.active_object
    cam_objs = sorted((o for o in bpy.data.objects if o.type == "CAMERA"), key=lambda o: o.name)
    proj = _blender_projection_error(bpy, cam_objs, read_mesh(obj.data).means)
    undistorted = "recgs_undistorted_dir" in obj
    t0 = time.perf_counter()
    ply_path = out / "point_cloud.ply"
    bpy.ops.recgs.export_ply(filepath=str(ply_path))
    t_export = time.perf_counter() - t0
    bpy.context.scene.camera = cam_objs[0]
    blend_path = out / "scene.blend"
    t0 = time.perf_counter()
    save_blend(blend_path)
    t_save = time.perf_counter() - t0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = read_gaussian_ply(ply_path)
    report = {
        "scene_dir": str(args.scene_dir), "images": len(cam_objs), "gaussians": len(g),
        "sh_degree": g.sh_degree, "undistorted": undistorted,
        "seconds": {"import_operator": round(t_import, 3),
                    "export_ply": round(t_export, 3), "save_blend": round(t_save, 3),
                    "total": round(time.perf_counter() - t_start, 3)},
        "camera_projection_error_px": proj,
        "outputs": {"blend": str(blend_path), "ply": str(ply_path)},
    }
    with atomic_path(out / "report.json", "report") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    lines = [
        f"# RecGS import report: {args.scene_dir}", "",
        f"- {len(cam_objs)} cameras, {len(g)} initial Gaussians (SH degree {g.sh_degree})",
        f"- time: import operator {t_import:.2f} s (reading, checking, building), PLY export "
        f"{t_export:.2f} s, .blend save {t_save:.2f} s",
        f"- Blender cameras vs COLMAP cameras over {proj['projections']} point projections: "
        f"max {proj['max_px']:.2e} px, mean {proj['mean_px']:.2e} px",
        f"- wrote {blend_path} and {ply_path}", "",
        "Training, caustic removal and caustic-free images are not part of this command yet.",
    ]
    with atomic_path(out / "report.md", "report") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return lines


def cmd_info(args) -> int:
    from ..core.errors import RecGSError
    from ..core.io.ply import read_gaussian_ply

    try:
        g = read_gaussian_ply(args.ply)
    except RecGSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    import numpy as np

    lo, hi = (g.means.min(0), g.means.max(0)) if len(g) else (np.zeros(3), np.zeros(3))
    print(json.dumps({"file": str(args.ply), "gaussians": len(g), "sh_degree": g.sh_degree,
                      "bounds_min": lo.tolist(), "bounds_max": hi.tolist(),
                      "mean_opacity": float(g.opacities.mean()) if len(g) else None}, indent=2))
    return 0
