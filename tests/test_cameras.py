"""The pinhole camera (core/model/cameras.py): which points a view sees, where and how far."""
from __future__ import annotations

import numpy as np

from recgs_addon.core.model.cameras import Camera, quat_to_rotmat


def test_in_view_gives_the_pixels_and_ranges_points_were_made_from():
    """Points made from chosen pixels and distances along their rays come back at those pixels
    and distances; points behind the camera or outside the image are not seen."""
    rs = np.random.default_rng(3)
    q = rs.normal(size=4)
    cam = Camera("v.png", 320, 240, 280.0, 290.0, 161.5, 118.0, quat_to_rotmat(q / np.linalg.norm(q)),
                 np.array([0.3, -0.2, 1.1]))
    u = np.array([0.01, 10.25, 160.0, 319.9, 200.0, 50.0, 400.0, -3.0])
    v = np.array([0.01, 239.5, 120.0, 5.0, 100.0, 60.0, 100.0, 20.0])
    dist = np.array([1.0, 2.5, 3.0, 0.7, 4.0, 2.0, 2.0, 2.0])
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], 1)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    pc = ray * dist[:, None]
    pc[5] *= -1.0                                   # behind the camera
    world = (pc - cam.t) @ cam.R                    # camera to world: R^T (p - t)
    seen, su, sv, rng = cam.in_view(world)
    assert seen.tolist() == [0, 1, 2, 3, 4]
    assert np.allclose(su, u[:5], atol=1e-9) and np.allclose(sv, v[:5], atol=1e-9)
    assert np.allclose(rng, dist[:5], rtol=1e-12)
