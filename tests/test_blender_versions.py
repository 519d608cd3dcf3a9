"""The add-on in stock Blenders: bpy 4.2 LTS, 4.5 LTS, 5.0 (Python 3.11) and 5.2 (Python 3.13).

For each version, a virtual environment holding only bpy and the numpy it brings (made once and
kept in the per-user cache, ``$RECGS_CACHE_DIR/bpy-venvs`` or ``~/.cache/recgs/bpy-venvs``;
pip's own cache keeps the bpy wheels), this platform's extension zip built with Blender's
builder (``scripts/build_extension.py``), and ``tests/blender_scripts/stock_blender.py`` in a
fresh user profile: install with Blender's extension installer, enable, import the sample
survey, EEVEE preview, delete Gaussians, export (edits honoured), disable and enable twice.
On 4.2.23, 4.5.15 and 5.0.1 it also renders a small EEVEE frame, clicks *Install Training
Engine* (pip, torch 2.13.0 CPU; refused first with online access off), trains 50 steps in the
background with progress and cancels a second run.
On 5.2.3 (Python 3.13: torch 2.13.0 CPU has no cp313 wheel on this machine's index) it chooses
the test runner's Python, which holds torch, as the preferences' *Python with torch* instead,
and trains and cancels the same way in that worker process.

    .venv/bin/python -m pytest -m stock_blender tests/test_blender_versions.py

Behind the ``stock_blender`` marker (downloads ~1.5 GB of bpy wheels the first time, minutes
per version); CI runs it after the slow checks when time allows.
"""
import glob
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "blender_scripts" / "stock_blender.py"

pytestmark = pytest.mark.stock_blender

#: bpy version -> (Python it needs, extra pins, what else the session does)
VERSIONS = {
    "4.2.23": ("3.11", ["numpy==1.26.4"], ["--render", "--engine", "ok", "--train-steps", "50"]),
    "4.5.15": ("3.11", [], ["--render", "--engine", "ok", "--train-steps", "50"]),
    "5.0.1": ("3.11", [], ["--render", "--engine", "ok", "--train-steps", "50"]),
    # torch 2.13.0 CPU has no cp313 wheel this machine can reach: 5.2 trains with the other
    # engine the add-on offers, an existing Python with torch chosen in its preferences (this one).
    "5.2.3": ("3.13", [], ["--render", "--worker-python", sys.executable, "--train-steps", "50"]),
}


def cache_root() -> Path:
    base = os.environ.get("RECGS_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "recgs")
    return Path(base) / "bpy-venvs"


def find_python(version: str):
    """A CPython ``version`` (3.11 / 3.13) that runs: in pyenv's versions, or on PATH. A pyenv
    shim on PATH answers ``which`` for every version pyenv has, but runs only the active ones,
    so every candidate is tried before it is used."""
    root = os.environ.get("PYENV_ROOT") or os.path.expanduser("~/.pyenv")
    found = sorted(glob.glob(os.path.join(root, "versions", f"{version}.*", "bin", f"python{version}")))
    for exe in [*reversed(found), shutil.which(f"python{version}")]:
        if exe and subprocess.run([exe, "-c", "pass"], capture_output=True).returncode == 0:
            return exe
    return None


def bpy_venv(bpy_version: str) -> Path:
    py_version, pins, _ = VERSIONS[bpy_version]
    venv = cache_root() / f"bpy-{bpy_version}"
    python = venv / "bin" / "python"
    ok = venv / ".recgs-ok"
    if ok.exists() and python.exists():
        return python
    base = find_python(py_version)
    if base is None:
        pytest.skip(f"no Python {py_version} here for bpy {bpy_version}")
    if venv.exists():
        shutil.rmtree(venv)
    subprocess.run([base, "-m", "venv", str(venv)], check=True)
    res = subprocess.run([str(python), "-m", "pip", "install", "-q", f"bpy=={bpy_version}", *pins],
                         capture_output=True, text=True)
    if res.returncode:
        pytest.skip(f"bpy {bpy_version} not installable here: {res.stderr.strip().splitlines()[-1:]}")
    ok.write_text("bpy + numpy only\n")
    return python


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory) -> Path:
    """This platform's zip, built with the bundled wheels (fetched once into the wheel cache)."""
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "build_extension.py")], cwd=ROOT,
                         capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    zips = sorted((ROOT / "dist").glob("recgs-*-linux_x64.zip")) if sys.platform.startswith("linux") else []
    if not zips:
        pytest.skip("this platform's zip was not built (the test runs on linux-x64)")
    return zips[-1]


@pytest.mark.parametrize("bpy_version", list(VERSIONS))
def test_stock_blender_session(bpy_version, extension_zip, tmp_path):
    python = bpy_venv(bpy_version)
    extra = VERSIONS[bpy_version][2]
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "profile"),
               RECGS_CACHE_DIR=str(tmp_path / "recgs-cache"))
    env.pop("PYTHONPATH", None)
    env.pop("RECGS_ENGINE_DIR", None)
    # The engine install uses pip's configured index; PyTorch's CPU index is not reachable here.
    env.setdefault("RECGS_ENGINE_PIP_ARGS", "")
    try:
        res = subprocess.run([str(python), str(SCRIPT), str(extension_zip), str(ROOT / "data" / "sample"),
                              str(tmp_path / "out"), *extra], env=env, capture_output=True, text=True,
                             timeout=3000, cwd=tmp_path)
    finally:
        # The engine this Blender run installed (torch, numba: ~1.5 GB) goes at once, so the
        # versions' installs never sit on the disk together.
        shutil.rmtree(tmp_path / "recgs-cache" / "engine", ignore_errors=True)
    steps = [json.loads(line[5:]) for line in res.stdout.splitlines() if line.startswith("STEP ")]
    fails = [line for line in res.stdout.splitlines() if line.startswith("FAIL ")]
    for s in steps:
        print(f"bpy {bpy_version} {s['step']}: {s['seconds']} s, {s['detail']}")
    assert not fails and res.returncode == 0 and res.stdout.rstrip().endswith("ALL-OK"), \
        "\n".join(fails) or (res.stdout[-3000:] + res.stderr[-3000:])
    done = {s["step"] for s in steps}
    assert {"install", "import", "preview", "delete", "export", "disable_enable"} <= done
    if "--engine" in extra:
        assert {"engine_offline", "engine", "train", "cancel"} <= done
    if "--worker-python" in extra:
        assert {"worker_python", "train", "cancel"} <= done
