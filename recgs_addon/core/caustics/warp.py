"""Moving pixels between frames: a frame's pixels back-projected at their depth, projected into
another frame, and that frame sampled there (the geometry of ``geometry.py``, ``light.py`` and
``passes.py``).

Shapes: images (H, W, 3) float32, depth (H, W). Cameras: ``viewmat`` (4, 4) world-to-camera
(OpenCV axes), ``K`` (3, 3), pixel centres at +0.5.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def backproject(depth: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) world points of the pixel centres at camera-space depth ``depth`` (H, W)."""
    h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5,
                          torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5,
                          indexing="ij")
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    cam = torch.stack([x, y, depth], -1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return (cam - t) @ R   # R^T (cam - t), row vectors


def project(points, view):
    """(grid (1, H, W, 2) of ``grid_sample`` coordinates, z (H, W)) of ``points`` (H, W, 3) in
    ``view`` (``viewmat``, ``K``, and ``depth`` for its size)."""
    R, t, K = view["viewmat"][:3, :3], view["viewmat"][:3, 3], view["K"]
    cam = points @ R.T + t
    z = cam[..., 2]
    zs = z.clamp_min(1e-6)
    hh, ww = view["depth"].shape
    u = K[0, 0] * cam[..., 0] / zs + K[0, 2]
    v = K[1, 1] * cam[..., 1] / zs + K[1, 2]
    return torch.stack([2 * u / ww - 1, 2 * v / hh - 1], -1).unsqueeze(0), z


def inside(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W) bool: the ``grid_sample`` coordinates ``grid`` (1, H, W, 2) lie half a pixel or more
    inside an image of ``height x width`` (:func:`within`)."""
    return within(grid[0], height, width)


def within(g: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(...) bool: the ``grid_sample`` coordinates ``g`` (..., 2) lie half a pixel or more inside
    an image of ``height x width``, where a bilinear sample mixes its pixels only (nearer the
    edge it mixes in the padding around them: a dark seam along the other frame's edge)."""
    return (g[..., 0].abs() <= 1 - 1 / width) & (g[..., 1].abs() <= 1 - 1 / height)


def sample(image, grid, mode):
    """``image`` (H', W', C) or (H', W') at ``grid``: (H, W, C) or (H, W)."""
    x = image.unsqueeze(-1) if image.dim() == 2 else image
    out = F.grid_sample(x.permute(2, 0, 1).unsqueeze(0), grid.to(x.dtype), mode=mode, align_corners=False)
    out = out[0].permute(1, 2, 0)
    return out[..., 0] if image.dim() == 2 else out
