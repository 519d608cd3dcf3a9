"""Background jobs (``python -m recgs_addon train|sfm|video ...``) followed from Blender.

This module does not touch ``bpy``: the sidebar's timer (``job_follow.pump``) and the batch
script both drive a :class:`Job` from Blender's main thread. A job is a separate process of
the same Python (``sys.executable``, which inside Blender is Blender's own Python) with
``PYTHONPATH`` set to the folder holding the package, so it also runs from an installed
extension. Two reader threads only move text: stdout JSON lines into a ``queue.Queue``,
stderr lines into a bounded tail (shown when the job crashes). Every live job is stopped
cleanly (SIGTERM, then a wait; the trainer checkpoints and exits) when Python exits.
"""
from __future__ import annotations

import atexit
import hashlib
import importlib.util
import json
import os
import queue
import subprocess
import sys
import threading
from collections import deque
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

#: The folder holding the package (what PYTHONPATH must contain) and the package's name.
PACKAGE_DIR = Path(__file__).resolve().parents[1]
PACKAGE_PARENT = PACKAGE_DIR.parent
PACKAGE_NAME = PACKAGE_DIR.name

#: Lines of a job's stderr kept for error messages.
STDERR_TAIL_LINES = 40
#: Events kept in ``Job.history``.
HISTORY_EVENTS = 2000
#: Seconds a stopping job gets to write its checkpoint before it is killed.
STOP_TIMEOUT_S = 30.0

_live: "set[Job]" = set()
_live_lock = threading.Lock()


#: The Python that runs jobs (``None``: this one) and the training engine folder it sees;
#: set by :func:`configure` (``engine.configure_jobs`` from the add-on's preferences).
_worker_python: Optional[str] = None
_engine: Optional[Path] = None


def configure(python: Optional[str] = None, engine: Optional[Path] = None) -> None:
    global _worker_python, _engine
    _worker_python, _engine = (python or None), engine


def worker_python() -> str:
    return _worker_python or sys.executable


def job_env() -> dict:
    """The environment of a job: the package's folder, the training engine and the
    site-packages Blender put on ``sys.path`` (bundled wheels) first on PYTHONPATH."""
    from ..engine_install import worker_env
    return worker_env(PACKAGE_PARENT, _engine, same_python=_worker_python is None)


def missing_modules(names: Iterable[str]) -> list[str]:
    """The modules of ``names`` that a job cannot import: looked up in this Python and the
    engine folder, or asked of the chosen worker Python."""
    names = list(names)
    if _worker_python is not None:
        code = "import importlib.util as u, sys; print(' '.join(n for n in sys.argv[1:] if u.find_spec(n) is None))"
        try:
            r = subprocess.run([_worker_python, "-c", code, *names], capture_output=True, text=True,
                               env=job_env(), timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            return names
        return r.stdout.split() if r.returncode == 0 else names
    missing = []
    for name in names:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError, AttributeError):
            found = False
        if not found and _engine is not None:
            found = (_engine / name).is_dir() or (_engine / f"{name}.py").is_file()
        if not found:
            missing.append(name)
    return missing


def command(*args: str) -> list[str]:
    """``[python, -m, recgs_addon, *args]`` for the worker Python."""
    return [worker_python(), "-m", PACKAGE_NAME, *map(str, args)]


def train_command(scene_dir, out_dir, options: dict, init_ply=None, resume: bool = False) -> list[str]:
    """The ``train`` command line. ``options`` maps trainer option names (``max_minutes``,
    ``budget``, ...) to values; ``None`` and ``False`` leave an option out, ``True`` gives a
    bare flag."""
    argv = ["train", str(scene_dir), "--out", str(out_dir)]
    for key, value in options.items():
        if value is None or value is False:
            continue
        flag = "--" + key.replace("_", "-")
        argv += [flag] if value is True else [flag, str(value)]
    if init_ply is not None:
        argv += ["--init-ply", str(init_ply)]
    if resume:
        argv.append("--resume")
    return command(*argv)


def sfm_command(photo_dir, scene_dir, link: bool = False, overwrite: bool = False) -> list[str]:
    argv = ["sfm", str(photo_dir), "--out", str(scene_dir)]
    return command(*argv, *(["--link"] if link else []), *(["--overwrite"] if overwrite else []))


def video_command(clip, scene_dir, frames: int, every_s: float = 0.0, max_side: Optional[int] = None) -> list[str]:
    """The ``video`` command line: a spacing ``every_s`` > 0 replaces the count ``frames``."""
    argv = ["video", str(clip), "--out", str(scene_dir)]
    argv += ["--every", str(every_s)] if every_s > 0 else ["--frames", str(frames)]
    if max_side is not None:
        argv += ["--max-side", str(max_side)]
    return command(*argv)


def gaussian_signature(g) -> str:
    """``"COUNT:SHA1"`` of a GaussianSet's arrays as float32: equal sets, equal signatures."""
    h = hashlib.sha1()
    for a in (g.means, g.log_scales, g.quats, g.logit_opacities, g.sh):
        a = np.ascontiguousarray(a, dtype=np.float32)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return f"{len(g)}:{h.hexdigest()}"


class Job:
    """One running job. Call :meth:`poll` from one thread (Blender's main thread) to get the
    events that arrived; nothing here blocks except :meth:`wait` and :meth:`stop`."""

    def __init__(self, kind: str, argv: list[str], cwd=None, echo_stderr: bool = False):
        self.kind = kind
        self.argv = list(argv)
        self.echo_stderr = echo_stderr
        self.events: "queue.Queue[dict]" = queue.Queue()
        self.stderr_tail: deque[str] = deque(maxlen=STDERR_TAIL_LINES)
        self.last: dict[str, dict] = {}  # the last event of each kind seen by poll()
        self.history: deque[dict] = deque(maxlen=HISTORY_EVENTS)  # events seen by poll()
        self.cancel_requested = False
        self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, cwd=cwd,
                                     env=job_env(), text=True, encoding="utf-8", errors="replace", bufsize=1)
        self._threads = [threading.Thread(target=self._read_stdout, daemon=True, name=f"recgs-{kind}-out"),
                         threading.Thread(target=self._read_stderr, daemon=True, name=f"recgs-{kind}-err")]
        for t in self._threads:
            t.start()
        with _live_lock:
            _live.add(self)

    # -- reader threads: text only ------------------------------------------------------------
    def _read_stdout(self) -> None:
        for line in self.proc.stdout:
            line = line.strip()
            if not line:
                continue
            try:
                ev = json.loads(line)
            except ValueError:
                ev = None
            if isinstance(ev, dict) and "event" in ev:
                self.events.put(ev)
            else:
                self.stderr_tail.append(line)

    def _read_stderr(self) -> None:
        for line in self.proc.stderr:
            self.stderr_tail.append(line.rstrip("\n"))
            if self.echo_stderr:
                sys.stderr.write(line)
                sys.stderr.flush()

    # -- main thread ----------------------------------------------------------------------------
    def poll(self) -> list[dict]:
        """The events that arrived since the last call (in order)."""
        out = []
        while True:
            try:
                ev = self.events.get_nowait()
            except queue.Empty:
                break
            self.last[ev["event"]] = ev
            self.history.append(ev)
            out.append(ev)
        return out

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    @property
    def finished(self) -> bool:
        """The process has ended and every line it wrote has been read and polled."""
        if self.proc.poll() is None or any(t.is_alive() for t in self._threads):
            return False
        if self.events.empty():
            with _live_lock:
                _live.discard(self)
            return True
        return False

    @property
    def returncode(self) -> Optional[int]:
        return self.proc.poll()

    def terminate(self) -> None:
        """Ask the job to stop (SIGTERM): the trainer writes its checkpoint and exits 0 with a
        ``done`` event of status ``cancelled``."""
        self.cancel_requested = True
        if self.proc.poll() is None:
            self.proc.terminate()

    def wait(self, timeout: Optional[float] = None) -> Optional[int]:
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None
        for t in self._threads:
            t.join(5.0)
        return self.proc.returncode

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> Optional[int]:
        """Terminate and wait up to ``timeout`` seconds, then kill."""
        self.terminate()
        if self.wait(timeout) is None:
            self.proc.kill()
            self.wait(5.0)
        with _live_lock:
            _live.discard(self)
        return self.proc.returncode

    def outcome(self) -> tuple[str, str]:
        """``(status, message)`` once finished: status ``done``, ``cancelled`` or ``failed``."""
        done, error = self.last.get("done"), self.last.get("error")
        code = self.proc.returncode
        if done is not None and code == 0:
            return done.get("status", "done"), ""
        if error is not None:
            return "failed", error.get("message", "the job failed")
        if self.cancel_requested and code is not None and code < 0:
            return "cancelled", "stopped before its first checkpoint"
        tail = "\n".join(list(self.stderr_tail)[-12:])
        return "failed", f"the {self.kind} job exited with code {code}" + (f":\n{tail}" if tail else "")


def live_jobs() -> list[Job]:
    with _live_lock:
        return [j for j in _live if j.running]


def stop_all(timeout: float = STOP_TIMEOUT_S) -> None:
    """Stop every live job (used at exit and when Blender opens another file)."""
    jobs = live_jobs()
    for j in jobs:
        j.terminate()
    for j in jobs:
        j.stop(timeout)


atexit.register(stop_all)
