"""One job per output folder.

:func:`folder_lock` takes an exclusive lock on ``FOLDER/.recgs.lock`` for as long as a job
runs (``fcntl.flock`` on Linux and macOS, ``msvcrt.locking`` on Windows). The operating
system drops the lock when the process ends, however it ends, so a killed job never leaves
a folder locked; the file only says which process held it last.
"""
from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import RecGSError
from .atomic import OutputError, describe, make_folder

LOCK_NAME = ".recgs.lock"


class FolderBusyError(RecGSError):
    """Another job is writing to this folder."""


def _try_lock(fd: int) -> bool:
    if sys.platform == "win32":
        import msvcrt
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            return True
        except OSError:
            return False
    import fcntl
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError:
        return False


@contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold ``folder`` for this process; :class:`FolderBusyError` if another one holds it."""
    folder = make_folder(folder)
    path = folder / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise OutputError(f"{path}: cannot create the job's lock file: {describe(exc)}") from exc
    try:
        if not _try_lock(fd):
            try:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "another process"
            except OSError:
                holder = "another process"
            raise FolderBusyError(f"{folder}: another training job is writing to this folder ({holder}); "
                                  "wait for it to end, cancel it, or choose another output folder")
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"pid {os.getpid()}".encode())
        yield path
    finally:
        os.close(fd)   # releases the lock
