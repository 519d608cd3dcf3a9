"""Saving a .blend the way every other output is written: whole or not at all.

Blender writes a .blend to ``NAME@`` and renames it, but a save over an existing file first
turns that file into ``NAME.blend1``, and a failed save can leave the ``@`` file behind.
:func:`save_blend` saves a copy under a temporary name in the same folder (through
:func:`~..core.io.atomic.atomic_path`) and renames it over the final name only once Blender
has written all of it: a full disk or a failing save leaves the previous file as it was and
no temporary, and says so naming the file.
"""
from __future__ import annotations

import os
from pathlib import Path

import bpy

from ..core.io.atomic import OutputError, atomic_path


def save_blend(path: str | os.PathLike) -> Path:
    """Save the open session as ``path`` (a copy: the session keeps its own file name).
    Raises :class:`OutputError` naming ``path`` when it cannot be written."""
    path = Path(path).resolve()
    kept = " (the previous one is kept)" if path.exists() else ""
    with atomic_path(path, ".blend file") as tmp:
        try:
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, check_existing=False)
        except RuntimeError as exc:
            message = str(exc).removeprefix("Error: ").strip()
            message = message.replace(f"{tmp}@", str(path)).replace(str(tmp), str(path))
            raise OutputError(f"{path}: could not write the .blend file: {message}{kept}") from None
        finally:
            Path(f"{tmp}@").unlink(missing_ok=True)   # Blender's own temporary, if it left one
    return path
