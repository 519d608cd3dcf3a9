"""The extension zip builds with Blender's own builder and installs into a fresh session."""
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from conftest import ROOT, write_colmap_scene

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def blender_ext_cli() -> Path:
    """Blender's extension command line (``blender --command extension`` in a full Blender)."""
    path = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core/bl_pkg/cli/blender_ext.py"
    assert path.is_file(), f"{path} not found"
    return path


def buildable_source(tmp: Path) -> Path:
    """The extension source for the builder. The manifest lists the pinned wheels that
    scripts/build_extension.py fetches into ./wheels/ (that needs the package index); where
    they are not all here, the builder would refuse, so the add-on itself is built from a copy
    whose manifest lists none (the wheel bundling is checked by build_extension.py --check)."""
    manifest = (ROOT / "blender_manifest.toml").read_text()
    listed = [line.strip().strip('",') for line in manifest.splitlines() if line.strip().startswith('"./wheels/')]
    if all((ROOT / w).is_file() for w in listed):
        return ROOT
    src = tmp / "source"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "data", "out", "wheels", "*.zip",
                                                              "__pycache__", "benchmarks", "docs", "tools", "tests"))
    begin, end = "# -- begin: written by scripts/build_extension.py", "# -- end: written by scripts/build_extension.py"
    head, rest = manifest.split(begin, 1)
    (src / "blender_manifest.toml").write_text(head + rest.split(end, 1)[1].lstrip("\n"))
    return src


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory):
    out = tmp_path_factory.mktemp("ext")
    src = buildable_source(tmp_path_factory.mktemp("src"))
    r = subprocess.run([sys.executable, str(blender_ext_cli()), "build", "--source-dir", str(src),
                        "--output-dir", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    zips = list(out.glob("recgs-*.zip"))
    assert len(zips) == 1, r.stdout
    return zips[0]


def test_manifest_validates(tmp_path):
    r = subprocess.run([sys.executable, str(blender_ext_cli()), "validate", str(buildable_source(tmp_path))],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_zip_holds_the_addon_only(extension_zip):
    names = zipfile.ZipFile(extension_zip).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "recgs_addon/core/io/ply.py" in names and "recgs_addon/blender/operators.py" in names
    # ".git" and ".venv" without a slash: in a git worktree (or submodule) .git is a file, and a
    # worktree's .venv may be a symlink
    for banned in ("tests/", "docs/", "data/", ".ci/", "tools/", "benchmarks/", ".venv", "scripts/", ".git"):
        assert not any(n.startswith(banned) for n in names), banned
    assert not any("__pycache__" in n for n in names)


def test_install_register_unregister_twice(extension_zip, tmp_path):
    scene = tmp_path / "survey"
    write_colmap_scene(scene)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    r = subprocess.run([sys.executable, str(ROOT / "tests/blender_scripts/install_extension.py"),
                        str(extension_zip), str(scene)],
                       capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0 and "EXTENSION-OK" in r.stdout, r.stdout[-3000:] + r.stderr[-3000:]
