"""Time importing a large COLMAP model into Blender (bpy module), stage by stage.

    .venv/bin/python benchmarks/bench_import.py [--points 200000] [--images 20]

Writes a synthetic model (every point seen by two images) in a temporary folder, then times
the core load (pycolmap read + checks + bulk point export), the initial Gaussians (kNN
scales), and the whole `recgs.import_colmap` operator in a fresh Blender session, and the
PLY export of the result. The goal is under 10 s for 200k points on a 2-core machine.
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


def write_big_model(root: Path, n_points: int, n_images: int, w=64, h=48) -> None:
    import pycolmap

    from recgs_addon.core.io.images import write_image

    rng = np.random.default_rng(0)
    txt = root / "txt"
    txt.mkdir(parents=True)
    f = 50.0
    (txt / "cameras.txt").write_text(f"1 PINHOLE {w} {h} {f} {f} {w / 2} {h / 2}\n")
    pts = np.c_[rng.uniform(-1, 1, (n_points, 2)), rng.uniform(-0.1, 0.1, n_points)]
    first = rng.integers(0, n_images, n_points)
    second = (first + 1 + rng.integers(0, n_images - 1, n_points)) % n_images
    lines, obs_index = [], {}
    for i in range(n_images):
        ids = np.nonzero((first == i) | (second == i))[0]
        obs_index[i] = ids
        xy = rng.uniform(0, w, (len(ids), 2))
        lines.append(f"{i + 1} 1 0 0 0 {0.01 * i} 0 3 1 img_{i:03d}.png")
        row = np.c_[xy, ids.astype(np.float64)]
        lines.append(" ".join(f"{a:.3f} {b:.3f} {int(c)}" for a, b, c in row))
    (txt / "images.txt").write_text("\n".join(lines) + "\n")
    # position of each point's observation within its images' point lists
    k_first = np.empty(n_points, np.int64)
    k_second = np.empty(n_points, np.int64)
    for i in range(n_images):
        ids = obs_index[i]
        pos = np.arange(len(ids))
        m1 = first[ids] == i
        k_first[ids[m1]] = pos[m1]
        k_second[ids[~m1]] = pos[~m1]
    cols = rng.integers(0, 256, (n_points, 3))
    table = np.c_[np.arange(n_points), pts, cols, np.zeros(n_points), first + 1, k_first, second + 1, k_second]
    with open(txt / "points3D.txt", "w") as fh:
        np.savetxt(fh, table, fmt="%d %.6f %.6f %.6f %d %d %d %.1f %d %d %d %d")
    rec = pycolmap.Reconstruction(str(txt))
    (root / "sparse/0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse/0"))
    for i in range(n_images):
        write_image(root / "images" / f"img_{i:03d}.png", np.full((h, w, 3), 0.5, np.float32))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--images", type=int, default=20)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="recgs_bench_") as tmp:
        root = Path(tmp) / "big"
        t0 = time.perf_counter()
        write_big_model(root, args.points, args.images)
        print(f"wrote a {args.points}-point, {args.images}-image model in {time.perf_counter() - t0:.1f} s")

        from recgs_addon.core.io.colmap import load_scene
        from recgs_addon.core.model.gaussians import init_from_points

        t0 = time.perf_counter()
        scene = load_scene(root)
        t_load = time.perf_counter() - t0
        t0 = time.perf_counter()
        g = init_from_points(scene.points, scene.colors)
        t_init = time.perf_counter() - t0

        import bpy

        from recgs_addon import blender as addon

        bpy.ops.wm.read_factory_settings(use_empty=True)
        addon.register()
        t0 = time.perf_counter()
        bpy.ops.recgs.import_colmap(directory=str(root))
        t_op = time.perf_counter() - t0
        obj = bpy.context.active_object
        assert len(obj.data.vertices) == args.points == len(g)
        t0 = time.perf_counter()
        bpy.ops.recgs.export_ply(filepath=str(Path(tmp) / "out.ply"))
        t_exp = time.perf_counter() - t0
        addon.unregister()
    print(f"core load_scene (pycolmap read, checks, points): {t_load:6.2f} s")
    print(f"initial Gaussians (kNN scales):                  {t_init:6.2f} s")
    print(f"recgs.import_colmap operator, end to end:        {t_op:6.2f} s   (goal < 10 s)")
    print(f"recgs.export_ply of {args.points} Gaussians:          {t_exp:6.2f} s")


if __name__ == "__main__":
    main()
