"""The training engine: torch, numba and PyAV, installed on request into a per-user folder (no bpy here).

torch is too large to bundle in the extension zip, so the artist installs it with one click
(``blender/engine.py``): pip runs in a background process with ``--target`` pointing at
``ENGINE_ROOT/py3.X/site-packages.tmp``; only when pip succeeds *and* a fresh Python imports
torch from there is the folder renamed to ``site-packages`` (the old one, if any, is removed
after the swap). A failed, cancelled or interrupted install leaves nothing but a ``.tmp``
folder, which the next attempt deletes first. Blender's own Python never imports torch or numba: jobs
run in a worker process whose ``PYTHONPATH`` (:func:`worker_env`) holds the package, the
engine and the site-packages of the extensions' bundled wheels.

Instead of the engine, the artist may choose an existing Python that already has torch
(``worker_python``). Everything here is plain Python, testable without Blender.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

#: PyAV: video decoding for Import Video (``python -m recgs_addon video``, core/capture/video.py);
#: its wheels carry FFmpeg (Python 3.9+ stable ABI: one wheel serves Blender 4.2-5.2's Pythons).
PYAV_REQUIREMENT = "av==18.1.0"
#: What the engine always holds. torch 2.13.0 is the version the trainer is tested with.
ENGINE_REQUIREMENTS = ("torch==2.13.0", PYAV_REQUIREMENT)
#: numba: the rasterizer's compiler-free fast path (core/render/numba_kernels.py; LLVM ships in
#: its wheels, for Python 3.10-3.13 on Linux, Windows and macOS, x64 and arm64). Only the worker
#: imports it; without it training runs on eager torch (slower, same numbers).
NUMBA_REQUIREMENT = "numba==0.61.2"
#: Ray: optional, for training in blocks (``train --blocks N``, commands/blocks.py); installed only on
#: request (Install with Ray), as import, preview and plain training never need it.
RAY_REQUIREMENT = "ray==2.60.0"
#: The numpy versions numba 0.61.2 works with: [1.24, 2.3).
NUMBA_NUMPY = ((1, 24), (2, 3))
#: Extra pip arguments for the engine install, from the environment (e.g. a local index:
#: ``RECGS_ENGINE_PIP_ARGS="--index-url https://mirror/simple"``; set and empty: none). On Linux, PyPI's torch is
#: the CUDA build (several GB); the CPU build comes from PyTorch's own index, added by default.
PIP_ARGS_ENV = "RECGS_ENGINE_PIP_ARGS"
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
#: Environment variable naming an engine folder (``.../site-packages``) to use instead of the
#: per-user one: batch runs outside an installed extension, tests.
ENGINE_DIR_ENV = "RECGS_ENGINE_DIR"
MARKER = "recgs-engine.json"

#: pip output lines that mean the network (not the request) failed.
#: What an install takes on disk, in GB (torch CPU, numba, llvmlite, PyAV, and pip's unpacking).
ENGINE_DISK_GB = 2

_NETWORK_ERRORS = ("NewConnectionError", "Max retries exceeded", "Temporary failure in name resolution",
                   "Name or service not known", "Network is unreachable", "ConnectionError",
                   "ReadTimeoutError", "timed out", "SSLError", "ProxyError")


def py_tag() -> str:
    return f"py{sys.version_info.major}.{sys.version_info.minor}"


def engine_site(root: Path) -> Path:
    """The engine's site-packages for this Python under ``root`` (the per-user folder)."""
    return Path(root) / "engine" / py_tag() / "site-packages"


def installed_engine(root: Optional[Path]) -> Optional[Path]:
    """The engine folder to use: ``$RECGS_ENGINE_DIR``, else a complete install under ``root``."""
    env = os.environ.get(ENGINE_DIR_ENV)
    if env:
        return Path(env)
    if root is None:
        return None
    site = engine_site(root)
    return site if (site / MARKER).is_file() else None


def engine_info(site: Path) -> dict:
    try:
        return json.loads((site / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def update_reason(info: dict, wanted: Optional[Sequence[str]] = None) -> Optional[str]:
    """Why an installed engine (its :func:`engine_info`) should be installed again, or None:
    it lacks numba where this Python's numpy takes it (an engine from before numba was part of
    it: training then runs on eager torch, about 2.5x slower), it lacks PyAV (an engine from
    before Import Video), or its torch is not the pinned one. ``wanted``: the requirements now
    (default :func:`engine_requirements`)."""
    wanted = engine_requirements() if wanted is None else tuple(wanted)
    if any(r.startswith("numba==") for r in wanted) and not info.get("numba"):
        return "no numba: training runs on the slower eager path"
    if any(r.startswith("av==") for r in wanted) and not info.get("av"):
        return "no PyAV: Import Video needs it"
    pin = next((r.split("==", 1)[1] for r in wanted if r.startswith("torch==")), None)
    have = str(info.get("torch") or "?").split("+")[0]
    if pin is not None and have != pin:
        return f"torch {have}, this version of RecGS is made for {pin}"
    return None


def _site_dirs(path: Sequence[str]) -> list[str]:
    """The ``site-packages`` folders of ``path`` (Blender's, and the extensions' ``.local`` one
    holding the bundled wheels), which a child Python does not get by itself."""
    return [p for p in path if p and os.path.basename(os.path.normpath(p)) in ("site-packages", "dist-packages")
            and os.path.isdir(p)]


def worker_env(package_parent: Path, engine: Optional[Path], base: Optional[dict] = None,
               same_python: bool = True) -> dict:
    """The environment of a worker process: ``PYTHONPATH`` = the package's folder, the engine,
    then (for Blender's own Python) the site-packages Blender put on ``sys.path``; the user's
    site-packages off, so no stray torch shadows the engine."""
    env = dict(os.environ if base is None else base)
    parts = [str(package_parent)]
    if engine is not None:
        parts.append(str(engine))
    if same_python:
        parts += _site_dirs(sys.path)
    parts += [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(parts))
    env["PYTHONNOUSERSITE"] = "1"
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def _numpy_version() -> Optional[str]:
    try:
        import numpy
        return numpy.__version__
    except Exception:  # noqa: BLE001 - no (working) numpy here
        return None


def engine_requirements(numpy_version: Optional[str] = "") -> tuple:
    """What to install: torch, PyAV, and numba pinned to the numpy of the Python that installs (``""``:
    this one's; Blender's). pip ``--target`` installs dependencies again into the engine, which
    comes first on the worker's ``PYTHONPATH``: an engine numpy of another version would shadow
    Blender's there, the same version is harmless. numba is left out where that numpy is
    missing or outside numba's range (training then runs on eager torch)."""
    if numpy_version == "":
        numpy_version = _numpy_version()
    try:
        v = tuple(int(x) for x in re.match(r"(\d+)\.(\d+)", numpy_version or "").groups())
    except (AttributeError, ValueError):
        return ENGINE_REQUIREMENTS
    if not NUMBA_NUMPY[0] <= v < NUMBA_NUMPY[1]:
        return ENGINE_REQUIREMENTS
    return ENGINE_REQUIREMENTS + (NUMBA_REQUIREMENT, f"numpy=={numpy_version}")


def pip_command(target: Path, python: str = sys.executable, requirements: Optional[Sequence[str]] = None,
                extra: Optional[Sequence[str]] = None, platform: str = sys.platform) -> list[str]:
    """The pip command installing ``requirements`` (default :func:`engine_requirements`) into
    ``target``. Uses Blender's pip, or, where the Python has none, the pip wheel that
    ``ensurepip`` carries (runnable as is)."""
    if requirements is None:
        requirements = engine_requirements()
    base = [python, "-m", "pip"]
    try:
        import importlib.util
        has_pip = importlib.util.find_spec("pip") is not None
    except (ImportError, ValueError):
        has_pip = False
    if not has_pip and python == sys.executable:
        base = [python, str(_ensurepip_wheel()) + "/pip"]
    if extra is None:                      # the variable, when set (even empty), replaces the default
        env = os.environ.get(PIP_ARGS_ENV)
        extra = env.split() if env is not None else (
            ["--extra-index-url", TORCH_CPU_INDEX] if platform.startswith("linux") else [])
    cmd = base + ["install", "--target", str(target), "--no-input", "--disable-pip-version-check",
                  "--no-warn-script-location", "--only-binary=:all:", "--upgrade"]
    if _pip_has_raw_progress():
        cmd += ["--progress-bar", "raw"]
    return cmd + list(extra) + list(requirements)


def _ensurepip_wheel() -> Path:
    import ensurepip
    wheels = sorted((Path(ensurepip.__file__).parent / "_bundled").glob("pip-*.whl"))
    if not wheels:
        raise EngineError("Blender's Python has no pip (and no ensurepip wheel) to install the engine with")
    return wheels[-1]


def _pip_has_raw_progress() -> bool:
    """pip 24.1+ prints ``Progress N of M`` lines with ``--progress-bar raw``."""
    try:
        from importlib.metadata import version
        major, minor = (int(x) for x in version("pip").split(".")[:2])
        return (major, minor) >= (24, 1)
    except Exception:
        return False


class EngineError(Exception):
    """The engine could not be installed; the message is for the artist."""


@dataclass
class Progress:
    phase: str = "starting"
    fraction: float = 0.0            # of the current download, 0..1 (0 when unknown)
    package: str = ""
    lines: list = field(default_factory=list)


_RAW = re.compile(r"Progress (\d+) of (\d+)")


def parse_line(line: str, p: Progress) -> None:
    """Update ``p`` from one line of pip's output."""
    line = line.strip()
    if not line:
        return
    m = _RAW.search(line)
    if m:
        done, total = int(m.group(1)), int(m.group(2))
        p.fraction = done / total if total else 0.0
        return
    p.lines.append(line)
    del p.lines[:-40]
    if line.startswith("Collecting "):
        p.phase, p.package, p.fraction = "resolving", line.split()[1], 0.0
    elif line.startswith("Downloading "):
        p.phase, p.package, p.fraction = "downloading", line.split()[1].rsplit("/", 1)[-1], 0.0
    elif line.startswith("Installing collected packages"):
        p.phase, p.package, p.fraction = "installing", "", 0.0


def failure_message(returncode: int, lines: Sequence[str], folder: Optional[Path] = None) -> str:
    """A message for the artist from pip's exit code and last lines (``folder``: where it went)."""
    text = "\n".join(lines)
    if any(k in text for k in _NETWORK_ERRORS):
        return ("The training engine could not be downloaded: the network failed (check the connection "
                "or proxy, then try again)")
    if "No space left on device" in text:
        where = f" ({folder})" if folder else ""
        return (f"The training engine needs about {ENGINE_DISK_GB} GB free on the disk of the RecGS "
                f"user folder{where} and the temporary folder; free some space and try again, or "
                "choose a Python with torch in the RecGS preferences")
    last = next((ln for ln in reversed(lines) if ln.startswith("ERROR")), lines[-1] if lines else "")
    return f"Installing the training engine failed (pip exit code {returncode}): {last}"


class Installer:
    """One engine install, stepped by a caller's timer: :meth:`poll` never blocks.

    ``root`` is the per-user folder; ``command`` replaces pip (tests; ``{target}`` in it is the
    install folder). The install goes to ``site-packages.tmp`` next to the
    final folder; :meth:`poll` returns ``None`` while running, then ``"done"``, ``"failed"`` or
    ``"cancelled"`` (``message`` says why)."""

    def __init__(self, root: Path, python: str = sys.executable, requirements: Optional[Sequence[str]] = None,
                 extra: Optional[Sequence[str]] = None, command: Optional[list] = None):
        self.final = engine_site(root)
        self.tmp = self.final.with_name("site-packages.tmp")
        self.python = python
        self.requirements = list(engine_requirements() if requirements is None else requirements)
        self.progress = Progress()
        self.message = ""
        self.status: Optional[str] = None
        self.started = time.monotonic()
        shutil.rmtree(self.tmp, ignore_errors=True)       # a previous attempt's leftovers
        self.tmp.mkdir(parents=True)
        cmd = ([a.replace("{target}", str(self.tmp)) for a in command] if command
               else pip_command(self.tmp, python, self.requirements, extra))
        env = dict(os.environ, PYTHONNOUSERSITE="1", PIP_NO_INPUT="1", PYTHONUNBUFFERED="1")
        env.pop("PYTHONPATH", None)
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, env=env, text=True, encoding="utf-8",
                                     errors="replace", bufsize=1)
        import queue
        import threading
        self._lines: "queue.Queue[str]" = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True, name="recgs-engine-pip")
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._lines.put(line)

    def poll(self) -> Optional[str]:
        import queue
        while True:
            try:
                parse_line(self._lines.get_nowait(), self.progress)
            except queue.Empty:
                break
        if self.status is not None or self.proc.poll() is None or self._reader.is_alive():
            return self.status
        while not self._lines.empty():
            parse_line(self._lines.get_nowait(), self.progress)
        if self.proc.returncode != 0:
            self._fail(failure_message(self.proc.returncode, self.progress.lines, self.final.parent))
        else:
            self._finish()
        return self.status

    def cancel(self) -> None:
        if self.status is None:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.status, self.message = "cancelled", "Training engine install cancelled; nothing was installed"

    def _fail(self, message: str) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.status, self.message = "failed", message

    def _finish(self) -> None:
        """Check that a fresh Python imports torch from the new folder, then swap it in."""
        code = ("import json, torch\n"
                "try:\n    import numba; nb = numba.__version__\n"
                "except Exception:\n    nb = None   # optional: training then runs on eager torch\n"
                "try:\n    import av; pyav = av.__version__\n"
                "except Exception:\n    pyav = None   # Import Video then asks for an update\n"
                "try:\n    import ray; rv = ray.__version__\n"
                "except Exception:\n    rv = None   # optional: training in blocks asks for it\n"
                "print(json.dumps({'torch': torch.__version__, 'numba': nb, 'av': pyav, 'ray': rv, "
                "'file': torch.__file__}))")
        env = dict(os.environ, PYTHONPATH=str(self.tmp), PYTHONNOUSERSITE="1")
        r = subprocess.run([self.python, "-c", code], capture_output=True, text=True, env=env, timeout=300)
        if r.returncode != 0:
            tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
            return self._fail(f"The training engine installed but torch does not import: {tail}")
        info = json.loads(r.stdout.strip().splitlines()[-1])
        if not Path(info.pop("file")).resolve().is_relative_to(self.tmp.resolve()):
            return self._fail("The training engine install holds no torch (pip installed nothing)")
        info.update(python=sys.version.split()[0], requirements=self.requirements,
                    installed=time.strftime("%Y-%m-%d %H:%M:%S"))
        (self.tmp / MARKER).write_text(json.dumps(info, indent=1), encoding="utf-8")
        old = self.final.with_name("site-packages.old")
        shutil.rmtree(old, ignore_errors=True)
        if self.final.exists():
            os.replace(self.final, old)
        os.replace(self.tmp, self.final)
        shutil.rmtree(old, ignore_errors=True)
        self.status, self.message = "done", f"Training engine installed (torch {info['torch']})"


def uninstall(root: Path) -> None:
    """Remove this Python's engine (and any leftovers of an install)."""
    shutil.rmtree(engine_site(root).parent, ignore_errors=True)
