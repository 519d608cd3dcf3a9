"""Atomic checkpoint files: a crash or kill at any moment leaves either the previous
checkpoint or the new one, never a half-written file under the final name."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import RecGSError
from ..io.atomic import atomic_path

CHECKPOINT_VERSION = 1


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """Write ``state`` with torch.save to a temporary file, fsync it, then rename over ``path``."""
    with atomic_path(path, "checkpoint") as tmp:
        with open(tmp, "wb") as f:
            try:
                torch.save({"version": CHECKPOINT_VERSION, **state}, f)
            except RuntimeError as exc:   # torch's zip writer hides a failed write behind its own error
                cause = exc.__context__
                while cause is not None and not isinstance(cause, OSError):
                    cause = cause.__context__
                if cause is None:
                    raise
                raise cause from exc


def load_checkpoint(path: str | os.PathLike) -> dict:
    path = Path(path)
    if not path.is_file():
        raise RecGSError(f"{path}: no checkpoint to resume from")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling problem means a bad file
        raise RecGSError(f"{path}: checkpoint cannot be read ({exc})") from exc
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        raise RecGSError(f"{path}: not a RecGS checkpoint of version {CHECKPOINT_VERSION}")
    return state
