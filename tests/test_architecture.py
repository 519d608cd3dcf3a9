"""The package's shape: the core never imports bpy, imports run one way down the pipeline's
layers, nothing imports in a circle (function-level imports included), and the extension
uses relative imports only. docs/architecture.md draws the layers these tests hold."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

PKG = ROOT / "recgs_addon"

#: Layers, bottom first. A module may import from its own layer or any layer below it.
#: ``core.errors`` is the base every layer shares. Everything under ``blender`` is one layer.
#: A module is in the layer of the longest prefix that names it (``commands.scene``, which
#: uses the Blender layer, sits above the rest of ``commands``).
LAYERS = [
    ("core.errors",),
    ("core.model",),
    ("core.io",),
    ("core.capture",),
    ("core.render",),
    ("core.train",),
    ("core.caustics",),
    ("core.options",),
    ("core.blocks",),
    ("core.outputs",),
    ("commands", "commands.events", "commands.train", "commands.render", "commands.capture", "commands.blocks",
     "engine_install"),
    ("blender",),
    ("commands.scene", "batch", "cli"),
    ("__main__",),
]
BLENDER_MODULES = ("bpy", "bmesh", "mathutils", "bpy_extras", "gpu", "blf")


def module_name(path: Path) -> str:
    """``recgs_addon/core/io/ply.py`` -> ``core.io.ply`` (package ``__init__`` -> the package)."""
    parts = list(path.relative_to(PKG).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> int:
    matches = [(len(p), rank) for rank, prefixes in enumerate(LAYERS) for p in prefixes
               if module == p or module.startswith(p + ".")]
    if matches:
        return max(matches)[1]
    if module in ("", "core"):
        return -1  # the package roots hold no code that imports
    raise AssertionError(f"module {module!r} is in no layer: add it to LAYERS and docs/architecture.md")


def imports_of(path: Path):
    """(imported module inside the package or None, top-level name, line) for every import
    in ``path``, at any depth (function-level imports included). ``from . import x`` names
    the submodule ``x`` where one exists."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = module_name(path).split(".")
    pkg = here if path.name == "__init__.py" else here[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                yield (a.name[len("recgs_addon."):] if top == "recgs_addon" else None), top, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                top = (node.module or "").split(".")[0]
                target = node.module[len("recgs_addon."):] if top == "recgs_addon" and node.module != "recgs_addon" else None
                yield target, top, node.lineno
                continue
            base = pkg[: len(pkg) - (node.level - 1)] if node.level > 1 else pkg
            mod = ".".join(base + (node.module.split(".") if node.module else []))
            for a in node.names:
                sub = f"{mod}.{a.name}" if mod else a.name
                exists = (PKG / Path(*sub.split("."))).with_suffix(".py").is_file() or (PKG / Path(*sub.split("."))).is_dir()
                yield (sub if exists else mod), "recgs_addon", node.lineno


def package_graph(files=None) -> dict:
    """module -> {imported module: first line}, inside recgs_addon."""
    graph = {}
    for path in files or sorted(PKG.rglob("*.py")):
        edges = graph.setdefault(module_name(path), {})
        for target, _top, line in imports_of(path):
            if target is not None and target != module_name(path):
                edges.setdefault(target, line)
    return graph


def find_cycle(graph: dict):
    """One import circle as a list of modules, or None."""
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in graph.get(m, {}):
            if state.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if t not in state:
                found = visit(t)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def layer_violations(graph: dict) -> list:
    bad = []
    for mod, edges in graph.items():
        for target, line in edges.items():
            if layer_of(target) > layer_of(mod):
                bad.append(f"{mod} (line {line}) imports {target}, a higher layer")
    return bad


def core_bpy_imports(files) -> list:
    return [f"{module_name(p)}:{line} imports {top}" for p in files
            for _t, top, line in imports_of(p) if top in BLENDER_MODULES or _t == "blender" or (_t or "").startswith("blender.")]


# --- the package as it is --------------------------------------------------------------------

def test_core_has_layer_subpackages():
    subs = [d.name for d in (PKG / "core").iterdir() if (d / "__init__.py").is_file()]
    assert len(subs) >= 4, subs
    assert not [p.name for p in (PKG / "core").glob("*.py") if p.name not in ("__init__.py", "errors.py")], \
        "core/ holds only layer sub-packages (and the shared errors module)"


def test_core_does_not_import_bpy_or_the_blender_layer():
    assert core_bpy_imports(sorted((PKG / "core").rglob("*.py"))) == []


def test_imports_run_down_the_layers():
    assert layer_violations(package_graph()) == []


def test_no_import_circle():
    assert find_cycle(package_graph()) is None


def test_no_absolute_imports_of_our_package():
    """An extension is installed under another name (bl_ext.<repo>.recgs): relative imports only."""
    for path in list(PKG.rglob("*.py")) + [ROOT / "__init__.py"]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            assert not any(n.split(".")[0] == "recgs_addon" for n in names), f"{path}:{node.lineno}"


# --- the checks catch what they are for ------------------------------------------------------

def _write(tmp_path, rel, text):
    p = tmp_path / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    return p


@pytest.mark.parametrize("line", ["import bpy", "from mathutils import Matrix", "from ...blender import preview",
                                  "def f():\n    import bpy\n"])
def test_a_core_module_importing_blender_fails(tmp_path, monkeypatch, line):
    """The check flags bpy (at any depth) or the Blender layer in a core module."""
    monkeypatch.setattr(sys.modules[__name__], "PKG", tmp_path)
    p = _write(tmp_path, "core/io/bad.py", line + "\n")
    _write(tmp_path, "blender/preview.py", "")
    assert core_bpy_imports([p])


def test_an_import_against_the_layers_fails(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "PKG", tmp_path)
    files = [_write(tmp_path, "core/io/ply.py", "def f():\n    from ..train import trainer\n"),
             _write(tmp_path, "core/train/trainer.py", "from ..io import ply\n")]
    bad = layer_violations(package_graph(files))
    assert bad == ["core.io.ply (line 2) imports core.train.trainer, a higher layer"]


def test_a_circle_is_found(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "PKG", tmp_path)
    files = [_write(tmp_path, "core/caustics/a.py", "from . import b\n"),
             _write(tmp_path, "core/caustics/b.py", "def f():\n    from .a import x\n")]
    assert find_cycle(package_graph(files)) in (["core.caustics.a", "core.caustics.b", "core.caustics.a"],
                                                 ["core.caustics.b", "core.caustics.a", "core.caustics.b"])


# --- what runs without Blender or torch ------------------------------------------------------

def test_core_imports_without_bpy_on_path():
    code = ("import sys; sys.modules['bpy'] = None\n"
            "import recgs_addon.core.io.colmap, recgs_addon.core.io.ply, recgs_addon.core.io.transform\n"
            "import recgs_addon.core.caustics.build, recgs_addon.core.outputs.report\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_import_path_does_not_need_scipy():
    """Stock Blender has no scipy: a survey's initial Gaussians come from numpy alone."""
    code = ("import sys; sys.modules['scipy'] = None; sys.modules['torch'] = None\n"
            "import numpy as np\n"
            "from recgs_addon.core.model.gaussians import init_from_points\n"
            "g = init_from_points(np.random.default_rng(0).random((500, 3)), np.zeros((500, 3), np.uint8))\n"
            "print('ok', len(g))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "ok 500" in r.stdout, r.stderr


def test_import_export_path_does_not_need_torch():
    """Blender's Python may lack torch: COLMAP/PLY import and export must work without it."""
    code = ("import sys; sys.modules['torch'] = None\n"
            "import recgs_addon.core.io.colmap, recgs_addon.core.io.ply, recgs_addon.core.io.transform\n"
            "import recgs_addon.core.model.gaussians, recgs_addon.core.io.images\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_modes_estimators_and_density_controls_are_listed_once():
    """The lists of modes, caustic modes, caustic estimators and density controls are written
    in the core's config alone; the command line, the panel and the report take them from
    there. A list, tuple or set literal anywhere else that names a whole one of them fails (a
    dict that maps each to its own code is dispatch, not a copy)."""
    from recgs_addon.core.caustics.config import CAUSTIC_MODES, ESTIMATORS, MODES
    from recgs_addon.core.train.strategies import STRATEGIES

    caustic_config = PKG / "core" / "caustics" / "config.py"
    families = {
        "modes": (set(MODES), caustic_config),
        "caustic modes": (set(CAUSTIC_MODES), caustic_config),
        "estimators": (set(ESTIMATORS) - {"auto"}, caustic_config),
        "density controls": (set(STRATEGIES), PKG / "core" / "train" / "strategies.py"),
    }
    copies = []
    for path in PKG.rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Tuple, ast.List, ast.Set)):
                continue
            words = {e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
            for family, (names, home) in families.items():
                if names <= words and path != home:
                    copies.append(f"{path.relative_to(ROOT)}:{node.lineno}: the {family} {sorted(names)}")
    assert not copies, "written outside the core's config:\n" + "\n".join(copies)


def test_what_blenders_process_imports_needs_no_torch():
    """Blender's own process (the sidebar, batch mode) reads the options and the trainer's
    settings but has no torch: importing them must not import it (nor numba)."""
    modules = ["recgs_addon.batch", "recgs_addon.commands.train", "recgs_addon.core.options.train",
               "recgs_addon.core.train.config"]
    code = ("import sys\n" + "".join(f"import {m}\n" for m in modules)
            + "try:\n    import bpy, recgs_addon.blender\nexcept ImportError:\n    pass\n"
            + "print(sorted(m for m in ('torch', 'numba') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], cwd=PKG.parent, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout
