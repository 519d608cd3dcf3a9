"""A million Gaussians in Blender (bpy module): import, update, preview, selection.

    .venv/bin/python benchmarks/bench_million.py [--gaussians 1000000] [--sh-degree 3] [--render]

Writes two random Gaussian sets as INRIA PLYs, then in a fresh Blender session times:
the `recgs.import_ply` operator; updating the object from the second PLY (read + write_mesh,
as a training update does); ensure_preview; a viewport depsgraph evaluation of the preview in
POINTS and ELLIPSOIDS mode at display ratio 0.1 and 1.0 (what every edit or update costs before
drawing); entering Edit Mode; the floater selection. Goals: import and update each under 5 s.
``--render`` adds tiny (64x48, 1 sample) EEVEE renders with the display ratio applied (what
the viewport draws); they run on the CPU here (Mesa llvmpipe), so they only bound the cost.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def random_set(n: int, degree: int, seed: int):
    from recgs_addon.core.model.gaussians import GaussianSet

    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return GaussianSet(rng.uniform(-5, 5, (n, 3)).astype(np.float32),
                       np.log(rng.uniform(0.005, 0.05, (n, 3))).astype(np.float32),
                       rng.normal(size=(n, 4)).astype(np.float32), rng.normal(0, 2, n).astype(np.float32),
                       (0.3 * rng.normal(size=(n, k, 3))).astype(np.float32))


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def counts(bpy, obj):
    geo = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).evaluated_geometry()
    inst, pc = geo.instances_pointcloud(), geo.pointcloud
    return (len(inst.points) if inst else 0) + (len(pc.points) if pc else 0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=1_000_000)
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--render", action="store_true", help="also time tiny EEVEE renders (slow on a CPU)")
    args = ap.parse_args()
    n = args.gaussians
    rows = []

    def row(what, seconds, note=""):
        rows.append((what, seconds, note))
        print(f"{what:<48} {seconds:8.2f} s  {note}", flush=True)

    from recgs_addon.core.io.ply import read_gaussian_ply, write_gaussian_ply

    with tempfile.TemporaryDirectory(prefix="recgs_bench_") as tmp:
        a, b = Path(tmp) / "a.ply", Path(tmp) / "b.ply"
        t, _ = timed(lambda: (write_gaussian_ply(a, random_set(n, args.sh_degree, 0)),
                              write_gaussian_ply(b, random_set(n, args.sh_degree, 1))))
        print(f"wrote two {n}-Gaussian PLYs (SH degree {args.sh_degree}, {a.stat().st_size / 2**20:.0f} MiB "
              f"each) in {t:.1f} s", flush=True)

        import bpy

        from recgs_addon import blender as addon
        from recgs_addon.blender import gaussian_object as gobj
        from recgs_addon.blender import preview

        bpy.ops.wm.read_factory_settings(use_empty=True)
        addon.register()
        if not hasattr(bpy.types.Object, "recgs_preview"):
            preview.register()

        t, res = timed(lambda: bpy.ops.recgs.import_ply(filepath=str(a)))
        assert res == {"FINISHED"}
        obj = bpy.context.active_object
        row("import_ply operator", t, f"{len(obj.data.vertices)} vertices")

        t_read, g2 = timed(lambda: read_gaussian_ply(b))
        t_write, _ = timed(lambda: gobj.write_mesh(obj.data, g2))
        row("update from a second PLY (read + write_mesh)", t_read + t_write,
            f"read {t_read:.2f} s, write_mesh {t_write:.2f} s")

        t, _ = timed(lambda: preview.ensure_preview(obj, mode="POINTS", display_ratio=0.1))
        row("ensure_preview (first: builds group + materials)", t)
        t, _ = timed(lambda: preview.ensure_preview(obj))
        row("ensure_preview (again)", t)

        for mode in ("POINTS", "ELLIPSOIDS"):
            for ratio in (0.1, 1.0):
                preview.ensure_preview(obj, mode=mode, display_ratio=ratio)
                t, _ = timed(lambda: bpy.context.evaluated_depsgraph_get())
                row(f"evaluate preview {mode} ratio {ratio}", t, f"{counts(bpy, obj)} shown")

        preview.ensure_preview(obj, mode="ELLIPSOIDS", display_ratio=0.1)
        bpy.context.evaluated_depsgraph_get()
        t, _ = timed(lambda: (gobj.write_mesh(obj.data, g2), bpy.context.evaluated_depsgraph_get()))
        row("live update: write_mesh + evaluate (ELLIPSOIDS 0.1)", t)

        t, _ = timed(lambda: bpy.ops.recgs.select_cleanup())
        row("select floaters (Object Mode)", t)
        t, _ = timed(lambda: bpy.ops.object.mode_set(mode="EDIT"))
        row("enter Edit Mode", t)
        t, _ = timed(lambda: bpy.ops.recgs.select_opacity(threshold=0.1))
        row("select by opacity (Edit Mode)", t)
        t, _ = timed(lambda: bpy.ops.object.mode_set(mode="OBJECT"))
        row("leave Edit Mode", t)

        if args.render:
            from mathutils import Matrix

            scene = bpy.context.scene
            cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
            scene.collection.objects.link(cam)
            cam.matrix_world = Matrix.Translation((0, 0, 15))
            scene.camera = cam
            scene.render.engine = "BLENDER_EEVEE"
            scene.eevee.taa_render_samples = 1
            scene.render.resolution_x, scene.render.resolution_y = 64, 48
            scene.render.filepath = str(Path(tmp) / "r.png")
            obj.recgs_preview.ratio_in_renders = True  # what the viewport would draw
            for mode, ratio in (("POINTS", 1.0), ("POINTS", 0.1), ("ELLIPSOIDS", 0.1), ("ELLIPSOIDS", 0.01)):
                preview.ensure_preview(obj, mode=mode, display_ratio=ratio)
                t, _ = timed(lambda: bpy.ops.render.render(write_still=True))
                row(f"EEVEE render 64x48 {mode} ratio {ratio}", t, f"{counts(bpy, obj)} shown, CPU OpenGL")

        addon.unregister()

    print("\n| step | seconds | note |\n|---|---:|---|")
    for what, s, note in rows:
        print(f"| {what} | {s:.2f} | {note} |")


if __name__ == "__main__":
    main()
