"""Install Training Engine: the one opt-in click that puts torch in the per-user folder.

The work is :class:`..engine_install.Installer` (pip in a background process, swapped into
place only when torch imports); this module adds what Blender needs around it: the add-on
preferences (engine status, the button, or an existing Python with torch), the operators, a
``bpy.app.timers`` function stepping the install with its progress in the status bar, and the
refusal when the artist has not allowed online access (Preferences > System > Network).
:func:`configure_jobs` tells :mod:`.jobs` which Python runs jobs and which engine it sees;
batch mode (``blender -b --python``) goes through the same function.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import bpy
from bpy.props import StringProperty

from .. import engine_install as ei
from . import jobs

#: The extension's package (``bl_ext.REPO.recgs``), or ``None`` outside an installed extension.
ADDON_PACKAGE = __package__.rsplit(".recgs_addon", 1)[0] if __package__.startswith("bl_ext.") else None
TIMER_INTERVAL_S = 0.5

_installer: Optional[ei.Installer] = None


_root: Optional[Path] = None


def engine_root() -> Optional[Path]:
    """The per-user folder of the extension (survives upgrades), or ``None`` outside one."""
    global _root
    if _root is None and ADDON_PACKAGE is not None:
        _root = Path(bpy.utils.extension_path_user(ADDON_PACKAGE, path="", create=True))
    return _root


def _prefs():
    if ADDON_PACKAGE is None:
        return None
    addon = bpy.context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def configure_jobs() -> None:
    """Point :mod:`.jobs` at the chosen worker Python and the installed engine."""
    prefs = _prefs()
    python = bpy.path.abspath(prefs.worker_python) if prefs is not None and prefs.worker_python else None
    jobs.configure(python=python, engine=ei.installed_engine(engine_root()))


def engine_ready() -> bool:
    """Cheap check for drawing: a worker Python is chosen, the engine is installed, or this
    Python has torch (development setups)."""
    import importlib.util
    return (jobs.worker_python() != sys.executable or ei.installed_engine(engine_root()) is not None
            or importlib.util.find_spec("torch") is not None)


def _redraw_status() -> None:
    for win in getattr(bpy.context.window_manager, "windows", []):
        for area in win.screen.areas:
            if area.type in {"STATUSBAR", "PREFERENCES", "VIEW_3D"}:
                area.tag_redraw()


def _step():
    """Timer: step the install; ``None`` (stop) once it has ended."""
    global _installer
    inst = _installer
    if inst is None:
        return None
    status = inst.poll()
    _redraw_status()
    if status is None:
        return TIMER_INTERVAL_S
    _installer = None
    print(f"RecGS: {inst.message}", file=sys.stderr if status == "failed" else sys.stdout)
    if status == "done":
        configure_jobs()
    _report(inst.message, "ERROR" if status == "failed" else "INFO")
    _redraw_status()
    return None


def _report(message: str, kind: str) -> None:
    """A message outside an operator: a popup in the UI, a line in the console in background."""
    if bpy.app.background:
        return
    def draw(self, _context):
        self.layout.label(text=message)
    bpy.context.window_manager.popup_menu(draw, title="RecGS", icon="ERROR" if kind == "ERROR" else "INFO")


def status_text() -> str:
    inst = _installer
    if inst is None:
        return ""
    p = inst.progress
    pct = f" {p.fraction * 100:.0f}%" if p.fraction else ""
    return f"RecGS engine: {p.phase} {p.package}{pct}".rstrip()


def draw_status(self, _context):
    if _installer is not None:
        p = _installer.progress
        if hasattr(self.layout, "progress"):
            self.layout.progress(factor=p.fraction, type="RING", text=status_text())
        else:
            self.layout.label(text=status_text())


class RECGS_OT_install_engine(bpy.types.Operator):
    """Download and install the training engine (PyTorch for the CPU, numba, and PyAV for Import
    Video: about 290 MB to download, 1.2 GB installed) into the extension's user folder. Needs online access"""
    bl_idname = "recgs.install_engine"
    bl_label = "Install Training Engine"

    with_ray: bpy.props.BoolProperty(
        name="With Ray", default=False,
        description="Include Ray, which training in blocks runs on (about 70 MB more to download)")

    def execute(self, context):
        global _installer
        if _installer is not None:
            self.report({"WARNING"}, "The training engine is already being installed")
            return {"CANCELLED"}
        if not bpy.app.online_access:
            self.report({"ERROR"}, "Online access is off: allow it in Preferences > System > Network, "
                                   "or choose a Python with torch in the RecGS preferences")
            return {"CANCELLED"}
        root = engine_root()
        if root is None:
            self.report({"ERROR"}, f"Not an installed extension: set {ei.ENGINE_DIR_ENV} to an engine folder")
            return {"CANCELLED"}
        try:
            _installer = ei.Installer(root, requirements=ei.engine_requirements()
                                      + ((ei.RAY_REQUIREMENT,) if self.with_ray else ()))
        except (OSError, ei.EngineError) as exc:
            self.report({"ERROR"}, f"Could not start the engine install: {exc}")
            return {"CANCELLED"}
        bpy.app.timers.register(_step, first_interval=TIMER_INTERVAL_S)
        self.report({"INFO"}, "Installing the training engine in the background (see the status bar)")
        return {"FINISHED"}


class RECGS_OT_cancel_engine_install(bpy.types.Operator):
    """Stop the engine install; nothing is left installed"""
    bl_idname = "recgs.cancel_engine_install"
    bl_label = "Cancel Engine Install"

    @classmethod
    def poll(cls, _context):
        return _installer is not None

    def execute(self, context):
        global _installer
        if _installer is not None:
            _installer.cancel()
            self.report({"INFO"}, _installer.message)
            _installer = None
        return {"FINISHED"}


class RECGS_OT_remove_engine(bpy.types.Operator):
    """Delete the installed training engine from your user folder"""
    bl_idname = "recgs.remove_engine"
    bl_label = "Remove Training Engine"

    def execute(self, context):
        root = engine_root()
        if root is not None and _installer is None:
            ei.uninstall(root)
        configure_jobs()
        return {"FINISHED"}


def draw_engine(layout) -> None:
    """The engine's status and buttons (preferences and sidebar)."""
    if _installer is not None:
        row = layout.row()
        row.label(text=status_text(), icon="SORTTIME")
        row.operator(RECGS_OT_cancel_engine_install.bl_idname, text="", icon="CANCEL")
        return
    site = ei.installed_engine(engine_root())
    if site is not None:
        info = ei.engine_info(site)
        outdated = ei.update_reason(info)
        row = layout.row()
        row.label(text=f"Training engine: torch {info.get('torch', '?')}", icon="ERROR" if outdated else "CHECKMARK")
        row.operator(RECGS_OT_remove_engine.bl_idname, text="", icon="TRASH")
        if outdated:   # an engine from an earlier version: one click installs the current one over it
            layout.label(text=outdated[:1].upper() + outdated[1:], icon="INFO")
            op = layout.operator(RECGS_OT_install_engine.bl_idname, text="Update Training Engine", icon="FILE_REFRESH")
            op.with_ray = bool(info.get("ray"))
        elif not info.get("ray"):   # training in blocks needs Ray: the engine again, with it
            op = layout.operator(RECGS_OT_install_engine.bl_idname, text="Add Ray (Train in Blocks)", icon="IMPORT")
            op.with_ray = True
    else:
        layout.operator(RECGS_OT_install_engine.bl_idname, icon="IMPORT")
        if not bpy.app.online_access:
            layout.label(text="Online access is off (Preferences > System > Network)", icon="INFO")


def _on_python_changed(_self, _context):
    configure_jobs()


class RECGS_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE or "recgs_addon"

    worker_python: StringProperty(
        name="Python with torch", subtype="FILE_PATH", default="", update=_on_python_changed,
        description="Optional: an existing Python (3.10+, with torch, numpy, OpenImageIO and pycolmap) that "
                    "runs training instead of Blender's Python with the training engine")

    def draw(self, _context):
        draw_engine(self.layout)
        self.layout.prop(self, "worker_python")


classes = (RECGS_OT_install_engine, RECGS_OT_cancel_engine_install, RECGS_OT_remove_engine,
           RECGS_AddonPreferences)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.STATUSBAR_HT_header.append(draw_status)
    configure_jobs()


def unregister():
    global _installer
    if _installer is not None:          # disabling mid-install: stop it, leave nothing behind
        _installer.cancel()
        _installer = None
    if bpy.app.timers.is_registered(_step):
        bpy.app.timers.unregister(_step)
    bpy.types.STATUSBAR_HT_header.remove(draw_status)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
