"""Shared fixtures: synthetic COLMAP surveys written with pycolmap, and a clean bpy session."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))


def look_at_pose(center, target, up=(0.0, 0.0, 1.0)):
    """COLMAP world-to-camera (R, t) for a camera at ``center`` looking at ``target``."""
    center, target, up = (np.asarray(v, dtype=np.float64) for v in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def write_colmap_scene(root, *, model="PINHOLE", params=None, width=64, height=48, n_images=4,
                       n_points=150, binary=True, names=None, write_images=True, seed=0,
                       sparse_sub="sparse/0"):
    """Write a small synthetic survey: ``root/images/*.png`` and a COLMAP model.

    Cameras look down at points scattered over z in [-0.3, 0.3] around the origin from
    about 3 m above. Every point is observed by every image it projects into.
    Returns the pycolmap.Reconstruction that was written.
    """
    import pycolmap

    from recgs_addon.core.io.images import write_image

    rng = np.random.default_rng(seed)
    root = Path(root)
    if params is None:
        params = {"PINHOLE": [60.0, 60.0, width / 2, height / 2],
                  "SIMPLE_PINHOLE": [60.0, width / 2, height / 2],
                  "SIMPLE_RADIAL": [60.0, width / 2, height / 2, 0.05],
                  "OPENCV": [60.0, 62.0, width / 2 + 1.5, height / 2 - 1.0, 0.05, -0.01, 0.001, 0.001],
                  }[model]
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    names = names or [f"img_{i:03d}.png" for i in range(n_images)]
    pts = np.concatenate([rng.uniform(-1.0, 1.0, (n_points, 2)), rng.uniform(-0.3, 0.3, (n_points, 1))], 1)
    poses = []
    for i, name in enumerate(names):
        c = np.array([-0.4 + 0.8 * i / max(1, len(names) - 1), 0.1 * np.sin(i), 3.0])
        R, t = look_at_pose(c, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
        poses.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    obs = [[] for _ in names]
    for i, pose in enumerate(poses):
        pc = (np.asarray(pose.matrix())[:, :3] @ pts.T).T + np.asarray(pose.matrix())[:, 3]
        uv = np.array([cam.img_from_cam(q) for q in pc]).reshape(-1, 2)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
        obs[i] = [(j, uv[j]) for j in np.nonzero(inside)[0]]
    for i, (name, pose) in enumerate(zip(names, poses)):
        kp = np.array([o[1] for o in obs[i]], dtype=np.float64).reshape(-1, 2)
        im = pycolmap.Image(name=name, keypoints=kp, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pose)
    colors = rng.integers(0, 256, (n_points, 3), dtype=np.uint8)
    for j in range(n_points):
        tr = pycolmap.Track()
        for i in range(len(names)):
            for k, (jj, _) in enumerate(obs[i]):
                if jj == j:
                    tr.add_element(i + 1, k)
        if tr.length() >= 1:
            rec.add_point3D(pts[j], tr, colors[j])
    model_dir = root / sparse_sub
    model_dir.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(model_dir))
    if write_images:
        for name in names:
            img = rng.random((height, width, 3)).astype(np.float32)
            write_image(root / "images" / name, img)
    return rec


@pytest.fixture
def colmap_scene(tmp_path):
    """A small PINHOLE survey in tmp_path/'survey'. Returns (path, reconstruction)."""
    root = tmp_path / "survey"
    rec = write_colmap_scene(root)
    return root, rec


@pytest.fixture
def bpy_session():
    """A factory-fresh Blender session with the add-on registered (unregistered afterwards)."""
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from recgs_addon import blender as addon

    addon.register()
    try:
        yield bpy
    finally:
        addon.unregister()


def write_rendered_scene(root, *, n_views=8, width=48, height=36, n_gauss=300, seed=0, noise=0.02,
                         heights=None, water=None, lamp=None, downward=False):
    """A survey whose images are renders of known Gaussians (so training can fit them exactly).

    Ground-truth Gaussians lie on a bumpy patch z ~ 0 seen from cameras ~2.5 m above (or at
    ``heights[i]``); the COLMAP model gets the true poses and, as sparse points, the true centres
    plus ``noise`` metres. With ``water`` (coefficients as :meth:`Medium.values` gives them) the
    photos are the renders seen through it (the trainer's own water model) and ``clean/`` holds
    the true colour; with ``lamp`` (a :class:`~recgs_addon.core.model.lamp.Lamp`) they are lit
    by it (the trainer's own lamp model), before any water. ``downward``: the cameras look
    straight down from a grid over the patch (a survey's rows) instead of at its centre from a
    circle. Returns the ground-truth GaussianSet.
    """
    import pycolmap
    import torch

    from recgs_addon.core.model.gaussians import GaussianSet, logit, rgb_to_sh_dc
    from recgs_addon.core.io.images import write_image
    from recgs_addon.core.render.rasterizer import render

    rng = np.random.default_rng(seed)
    root = Path(root)
    xy = rng.uniform(-1.0, 1.0, (n_gauss, 2))
    z = 0.15 * np.sin(2 * xy[:, :1]) * np.cos(3 * xy[:, 1:])
    means = np.c_[xy, z]
    cols = np.clip(0.5 + 0.35 * np.c_[np.sin(4 * xy[:, 0]), np.cos(5 * xy[:, 1]), np.sin(3 * xy.sum(1))]
                   + rng.normal(0, 0.05, (n_gauss, 3)), 0.02, 0.98)
    gt = GaussianSet(means, np.log(rng.uniform(0.04, 0.09, (n_gauss, 3))), rng.normal(size=(n_gauss, 4)),
                     logit(rng.uniform(0.7, 0.95, n_gauss)), rgb_to_sh_dc(cols)[:, None, :])
    fx = 0.9 * width
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=width, height=height,
                          params=[fx, fx, width / 2, height / 2], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        c = np.array([0.5 * np.cos(a), 0.4 * np.sin(a), 2.5 if heights is None else heights[i]])
        if downward:
            cols_ = int(np.ceil(np.sqrt(n_views)))
            gy_, gx_ = divmod(i, cols_)
            c[:2] = [-0.6 + 1.2 * gx_ / max(1, cols_ - 1), -0.5 + 1.0 * gy_ / max(1, (n_views - 1) // cols_)]
            R = np.diag([1.0, -1.0, -1.0])
            t = -R @ c
        else:
            R, t = look_at_pose(c, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
        name = f"view_{i:03d}.png"
        im = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = R, t
        K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]])
        with torch.no_grad():
            out = render(*(torch.tensor(a_, dtype=torch.float32) for a_ in
                           (gt.means, gt.log_scales, gt.quats, gt.logit_opacities, gt.sh)),
                         torch.tensor(view, dtype=torch.float32), torch.tensor(K, dtype=torch.float32),
                         width, height)
        rgb = out.rgb
        if water is not None or lamp is not None:
            write_image(root / "clean" / name, rgb.clamp(0, 1).numpy())
        if lamp is not None:
            from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
            from recgs_addon.core.model.medium import Medium, ray_lengths

            r = Medium.range_of(out.alpha, out.depth, ray_lengths(width, height, fx, fx, width / 2, height / 2))
            with torch.no_grad():
                g = lamp.gain(width, height, width / 2, height / 2, r).unsqueeze(-1)
                rgb = linear_to_srgb((srgb_to_linear(rgb.clamp(0, 1)) * g).clamp(0, 1))
        if water is not None:
            from recgs_addon.core.model.medium import Medium, ray_lengths

            with torch.no_grad():
                rgb = Medium.from_values(water).see(rgb, out.alpha, out.depth,
                                                    ray_lengths(width, height, fx, fx, width / 2, height / 2))
        write_image(root / "images" / name, rgb.clamp(0, 1).numpy())
    noisy = means + rng.normal(0, noise, means.shape)
    for j in range(n_gauss):
        rec.add_point3D(noisy[j], pycolmap.Track(), (cols[j] * 255).astype(np.uint8))
    (root / "sparse/0").mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(root / "sparse/0"))
    return gt
