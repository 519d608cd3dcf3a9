"""The core never imports bpy, and uses relative imports only (it must run as an extension)."""
import ast
import subprocess
import sys

from conftest import ROOT


def _imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, 0
        elif isinstance(node, ast.ImportFrom):
            yield node.module or "", node.level


def test_core_does_not_import_bpy():
    for path in (ROOT / "recgs_addon/core").rglob("*.py"):
        for name, _ in _imports(path):
            top = name.split(".")[0]
            assert top not in ("bpy", "bmesh", "mathutils", "bpy_extras"), f"{path} imports {name}"


def test_no_absolute_imports_of_our_package():
    for path in list((ROOT / "recgs_addon").rglob("*.py")) + [ROOT / "__init__.py"]:
        for name, level in _imports(path):
            assert not (level == 0 and name.split(".")[0] == "recgs_addon"), f"{path}: import {name}"


def test_core_imports_without_bpy_on_path():
    code = ("import sys; sys.modules['bpy'] = None\n"
            "import recgs_addon.core.colmap, recgs_addon.core.ply, recgs_addon.core.transform\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_import_export_path_does_not_need_torch():
    """Blender's Python may lack torch: COLMAP/PLY import and export must work without it."""
    code = ("import sys; sys.modules['torch'] = None\n"
            "import recgs_addon.core.colmap, recgs_addon.core.ply, recgs_addon.core.transform\n"
            "import recgs_addon.core.gaussians, recgs_addon.core.images\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr
