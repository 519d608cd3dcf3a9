"""The options of the commands on a survey or a model: ``import`` (a COLMAP survey into a
.blend), ``info`` (what a PLY holds) and ``render`` (a model from a survey's cameras), and the
survey folder every command that reads one takes (:data:`SCENE_DIR`) and the plain-PyTorch
switch ``train`` and ``render`` share (:data:`EAGER`)."""
from __future__ import annotations

from pathlib import Path

from .table import Option, OptionTable, Setting

#: The survey folder (``import``, ``train``, ``render``; the sidebar's Scene Folder).
SCENE_DIR = Option("scene_dir", "Survey folder holding images/ and a COLMAP model in sparse/0", type=Path,
                   setting=Setting("Scene Folder", default=""))
#: Plain PyTorch instead of numba's kernels or torch.compile (``train``, ``render``; the sidebar's
#: Plain PyTorch).
EAGER = Option("--eager", "Plain PyTorch rasterizer: neither numba's kernels nor torch.compile (about 2.5x slower "
                          "steps; the reference the fast paths are tested against)", type=bool,
               setting=Setting("Plain PyTorch", default=False))
#: The image folder inside the survey (``import``; ``train`` declares its own, which takes paths too).
IMAGE_FOLDER = "images"

IMPORT_OPTIONS = OptionTable([
    SCENE_DIR,
    Option("--out", "Output folder (scene.blend, point_cloud.ply, report.md, report.json)", type=Path,
           required=True),
    Option("--images", "Image folder inside the scene", default=IMAGE_FOLDER),
    Option("--sh-degree", "Spherical-harmonic degree of the initial Gaussians (training raises it where it helps)",
           type=int, default=0, choices=tuple(range(4))),
])

INFO_OPTIONS = OptionTable([
    Option("ply", "A 3DGS PLY (INRIA layout)", type=Path),
])

RENDER_OPTIONS = OptionTable([
    Option("model", "A 3DGS PLY", type=Path),
    Option("scene_dir", "Survey whose cameras to render from", type=Path),
    Option("--out", "Output folder (a PNG and a float EXR per view)", type=Path, required=True),
    Option("--names", "Comma-separated image names (default: all)"),
    Option("--downscale", "Render at the photo size divided by N", type=int, default=1),
    Option("--images", f"Compare against this image folder (default {IMAGE_FOLDER}/)"),
    EAGER,
])
