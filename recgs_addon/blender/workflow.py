"""What the workflow's requests share: the refusal they raise, the folders they work on, the
packages they check for, and how an operator reports them (``self.report``, never a raise)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import bpy

from ..core.errors import RecGSError
from . import jobs

#: Output folder inside the scene folder when the settings leave it empty.
DEFAULT_OUT = "recgs_out"


class WorkflowError(RecGSError):
    """A request the workflow refuses (shown to the artist with ``self.report``)."""


# -- paths ------------------------------------------------------------------------------------

def _abspath(p: str) -> Optional[Path]:
    return Path(bpy.path.abspath(p)) if p else None


def scene_dir_for(settings, obj=None) -> Path:
    """The survey folder: the sidebar's Scene Folder, else the one the object came from."""
    d = _abspath(settings.scene_dir) or (_abspath(obj.get("recgs_scene_dir", "")) if obj is not None else None)
    if d is None:
        raise WorkflowError("Set the Scene Folder (a folder with images/ and sparse/0), or import a "
                            "COLMAP survey first")
    if not d.is_dir():
        raise WorkflowError(f"{d}: scene folder is missing")
    if not (d / "sparse").is_dir():
        raise WorkflowError(f"{d}: no COLMAP model (sparse/0); use Reconstruct from Photos first")
    return d


def out_dir_for(settings, obj=None, scene_dir: Optional[Path] = None) -> Optional[Path]:
    """The job folder: the object's last one, else the Output Folder, else SCENE/recgs_out."""
    if obj is not None and obj.get("recgs_out_dir"):
        return Path(obj["recgs_out_dir"])
    if settings.out_dir:
        return _abspath(settings.out_dir)
    return scene_dir / DEFAULT_OUT if scene_dir is not None else None


def _check_modules(*names: str, what: str) -> None:
    missing = jobs.missing_modules(names)
    if missing:
        python = jobs.worker_python()
        which = "Blender's Python" if python == sys.executable else "the Python chosen in the RecGS preferences"
        raise WorkflowError(f"{what} needs the Python package(s) {', '.join(missing)} in {which} ({python}), "
                            "which runs RecGS jobs")


# -- operators ----------------------------------------------------------------------------------

def _run(op, fn, *args) -> set:
    try:
        op.report({"INFO"}, fn(*args))
    except (RecGSError, OSError, ValueError) as exc:
        op.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    return {"FINISHED"}
