"""Command line: ``python -m recgs_addon COMMAND ...``.

This module only parses the command line and dispatches: each command's options and body
live in ``recgs_addon.commands`` (its docstring lists the commands): ``import`` and ``info``
in ``commands/scene.py``, ``train`` in ``commands/train.py``, ``render`` in
``commands/render.py``, ``sfm`` and ``video`` in ``commands/capture.py``.
"""
from __future__ import annotations

import argparse

from .commands import blocks, capture, render, scene, train


def build_parser() -> argparse.ArgumentParser:
    """The whole command line: one subparser per command (also read by tools/make_reference.py)."""
    p = argparse.ArgumentParser(prog="python -m recgs_addon", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    scene.add_import_arguments(sub.add_parser(
        "import", help="COLMAP survey -> scene.blend + point_cloud.ply + report",
        description="Import a COLMAP survey into a new .blend (a camera per photo and the "
                    "initial Gaussians) with the add-on's own operators, export the Gaussians "
                    "as a 3DGS PLY, and report the time taken and how far the Blender "
                    "cameras' projections are from COLMAP's. Needs the bpy module."))
    scene.add_info_arguments(sub.add_parser(
        "info", help="describe a 3DGS PLY file",
        description="Print what a Gaussian PLY holds (count, SH degree, bounds, mean opacity) "
                    "as JSON. No Blender needed."))
    train.add_train_arguments(sub.add_parser(
        "train", help="train Gaussians on a survey (JSON-lines progress)",
        description="Train 3D Gaussian Splatting on a survey, with or without caustic removal. Progress as JSON "
                    "lines on stdout and a readable line on stderr; writes checkpoint.pt, point_cloud.ply and "
                    "metrics.json to OUT. SIGTERM/SIGINT stop it after a checkpoint; --resume continues."))
    render.add_render_arguments(sub.add_parser(
        "render", help="render a PLY from a survey's cameras",
        description="Render a model from the survey's cameras (a PNG and a float EXR per view, in OUT) and "
                    "report each view's PSNR against its photo."))
    capture.add_sfm_arguments(sub.add_parser(
        "sfm", help="photos -> COLMAP model with pycolmap (JSON-lines progress)",
        description="Structure from motion with pycolmap: copies (or links) the photos to "
                    "OUT/images and writes the COLMAP model to OUT/sparse/0, ready for import "
                    "and train. Progress as JSON lines; SIGTERM/SIGINT stop it, and running "
                    "it again continues where it stopped."))
    capture.add_video_arguments(sub.add_parser(
        "video", help="video clip -> frames + COLMAP model (JSON-lines progress)",
        description="A video clip into a survey: a sharp frame each time the view has moved a step of the image "
                    "(near-duplicates and dark frames left out) into OUT/images with their time stamps in OUT/frames.json, then SfM "
                    "with sequential matching and one shared camera into OUT/sparse/0. Progress as JSON lines; "
                    "SIGTERM/SIGINT stop it, and running it again continues where it stopped."))
    return p


#: Each command's body, by name.
COMMANDS = {"import": scene.cmd_import, "info": scene.cmd_info, "train": blocks.train_command,
            "render": render.run_render, "sfm": capture.cmd_sfm, "video": capture.cmd_video}


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return COMMANDS[args.command](args)
