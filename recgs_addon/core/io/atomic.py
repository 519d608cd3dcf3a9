"""Outputs appear whole or not at all.

:func:`atomic_path` hands a writer a temporary name beside the final one (same folder, so
the rename cannot cross file systems; same suffix, so format-sniffing writers like
OpenImageIO pick the right format), then flushes it to disk and renames it over the final
name. If the writer fails, the temporary file is removed and the previous file under the
final name, if any, is untouched. An ``OSError`` (a full disk, a read-only folder) becomes an
:class:`OutputError` that names the file and says what happened.
"""
from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import RecGSError


class OutputError(RecGSError):
    """An output (PLY, checkpoint, image, report) could not be written."""


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:      # Windows cannot open a folder; its rename is durable enough
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def describe(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1)):
        return "the disk is full"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return "no permission to write there"
    return exc.strerror or str(exc)


def make_folder(folder: str | os.PathLike, what: str = "output folder") -> Path:
    """Create ``folder`` (and its parents) if needed; :class:`OutputError` naming it when it is
    a file or cannot be created."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: is a file, not a folder (choose another {what})")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the {what}: {describe(exc)}") from exc
    return folder


@contextmanager
def atomic_path(path: str | os.PathLike, what: str = "file") -> Iterator[Path]:
    """``with atomic_path(p) as tmp: write(tmp)``: ``p`` is replaced only when the block ends
    without an exception (``what`` names the output in messages: "checkpoint", "PLY", ...)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    make_folder(path.parent, "folder")
    try:
        yield tmp
        with open(tmp, "rb+") as f:   # the writer may have closed it: flush what it wrote
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        kept = " (the previous one is kept)" if path.exists() else ""
        raise OutputError(f"{path}: could not write the {what}: {describe(exc)}{kept}") from exc
    finally:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        except OSError:
            pass


def copy_file(src: str | os.PathLike, dst: str | os.PathLike, what: str = "file") -> Path:
    """Copy ``src`` to ``dst`` through :func:`atomic_path` (a copy cut short by a full disk
    leaves the previous ``dst``, or none, and no partial file)."""
    import shutil

    dst = Path(dst)
    with atomic_path(dst, what) as tmp:
        shutil.copy2(src, tmp)
    return dst


def copy_tree(src: str | os.PathLike, dst: str | os.PathLike, what: str = "file") -> list[Path]:
    """Copy every file under ``src`` to the same place under ``dst`` with :func:`copy_file`."""
    src, dst = Path(src), Path(dst)
    return [copy_file(p, dst / p.relative_to(src), what) for p in sorted(src.rglob("*")) if p.is_file()]

