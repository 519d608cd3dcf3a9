"""Print the RecGS sidebar as text, from a headless session (bpy has no UI to screenshot).

    python tools/panel_snapshot.py [--state idle|running|done] [--scene SCENE_DIR]
    blender -b --factory-startup --python tools/panel_snapshot.py -- [options]

Every panel's ``draw`` runs against a recording layout that notes each label, property (with
its current value) and button, indented by nesting; sub-panels follow their parent, marked
``(closed)`` when they start folded. ``--state running`` fills the job status with sample
figures and draws the panels as they look while a job runs. With ``--scene`` a COLMAP survey
is imported first (so a Gaussian object is selected).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _check_icon(icon: str) -> None:
    """Unknown icon names fail only when Blender draws the panel: catch them here."""
    import bpy

    if icon and icon != "NONE":
        known = bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items.keys()
        if icon not in known:
            raise ValueError(f"unknown icon {icon!r}")


class Recorder:
    """Stands in for ``bpy.types.UILayout``: records calls as indented lines."""

    def __init__(self, lines: list, depth: int = 0):
        self._lines, self._depth = lines, depth
        self.enabled = self.active = True

    def __setattr__(self, name, value):  # alert, scale_y, use_property_split, ...
        object.__setattr__(self, name, value)

    def _emit(self, text: str):
        state = "" if self.enabled and self.active else "  (greyed out)"
        self._lines.append("  " * self._depth + text + state)

    def _child(self, kind: str, indent: bool):
        if indent:
            self._lines.append("  " * self._depth + f"{kind}:")
        child = Recorder(self._lines, self._depth + (1 if indent else 0))
        child.enabled, child.active = self.enabled, self.active
        return _Inherit(child, self)

    def row(self, **kw):
        return self._child("row", False)

    def column(self, **kw):
        return self._child("column", False)

    def column_flow(self, **kw):
        return self._child("column", False)

    def grid_flow(self, **kw):
        return self._child("grid", False)

    def split(self, **kw):
        return self._child("split", False)

    def box(self):
        return self._child("box", True)

    def separator(self, **kw):
        self._lines.append("")

    def label(self, text="", icon="NONE", **kw):
        _check_icon(icon)
        self._emit(f"{text}" + (f"  [{icon}]" if icon and icon != "NONE" else ""))

    def prop(self, data, prop, text=None, icon="NONE", **kw):
        _check_icon(icon)
        rna = data.bl_rna.properties[prop]
        name = rna.name if text is None else text
        value = getattr(data, prop)
        if rna.type == "ENUM":
            items = {i.identifier: i.name for i in rna.enum_items}
            value = items.get(value, value)
        elif rna.type == "BOOLEAN":
            value = "[x]" if value else "[ ]"
        elif rna.type == "FLOAT":
            value = f"{value:.3g}"
        elif rna.type == "STRING":
            value = f'"{value}"'
        self._emit(f"{name}: {value}" if name else f"{value}")

    def operator(self, idname, text=None, icon="NONE", **kw):
        import bpy

        _check_icon(icon)
        mod, name = idname.split(".")
        rna_name = getattr(getattr(bpy.ops, mod), name).get_rna_type().name  # KeyError: not registered
        text = rna_name if text is None else text or f"{rna_name} (icon {icon})"
        self._emit(f"[ {text} ]  ({idname})")
        return _OperatorProps()

    def __getattr__(self, name):  # template_*, menu, ...: note the call
        if name.startswith("_"):
            raise AttributeError(name)

        def call(*args, **kw):
            self._emit(f"<{name} {kw.get('text', '')}>".replace(" >", ">"))
            return self._child(name, False)
        return call


class _Inherit:
    """A child layout: attributes set on it (enabled, active) apply to what it draws."""

    def __init__(self, child: Recorder, parent: Recorder):
        object.__setattr__(self, "_c", child)

    def __getattr__(self, name):
        return getattr(self._c, name)

    def __setattr__(self, name, value):
        if name in ("enabled", "active"):
            value = bool(value) and getattr(self._c, name)
        setattr(self._c, name, value)


class _OperatorProps:
    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)


SAMPLE_RUNNING = dict(status="RUNNING", job_kind="train", phase="densify", iteration=1750, gaussians=129015,
                      psnr_test=21.74, elapsed=99.0, eta=141.0, progress=0.41,
                      message="viewport updated at iteration 1700")
SAMPLE_DONE = dict(status="DONE", job_kind="train", phase="done", iteration=3000, gaussians=129003,
                   psnr_test=21.90, elapsed=224.0, eta=0.0, progress=1.0,
                   message="finished (plateau) after 3000 iterations")


def snapshot(context, running: bool = False) -> str:
    """The sidebar drawn into text (the add-on must be registered)."""
    import bpy

    from recgs_addon.blender import job_follow, panel

    lines: list[str] = []
    real = job_follow.is_running
    job_follow.is_running = lambda: running
    try:
        for cls in panel.classes:
            depth, parent = 0, getattr(cls, "bl_parent_id", "")
            while parent:
                depth += 1
                parent = getattr(getattr(bpy.types, parent), "bl_parent_id", "")
            closed = "DEFAULT_CLOSED" in getattr(cls, "bl_options", set())
            lines.append("  " * depth + f"== {cls.bl_label}" + (" (closed)" if closed else "") + " ==")
            if hasattr(cls, "poll") and not cls.poll(context):
                continue
            fake = type("P", (), {})()
            fake.layout = Recorder(lines, depth + 1)
            cls.draw(fake, context)
    finally:
        job_follow.is_running = real
    return "\n".join(lines)


def snapshots(scene: Path | None, states: list[str]) -> dict[str, str]:
    """The sidebar in each of ``states`` (idle, running, done), in a factory-fresh session
    with the add-on registered and, if given, the COLMAP survey ``scene`` imported first."""
    import bpy

    from recgs_addon import blender as addon

    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        if scene is not None:
            bpy.ops.recgs.import_colmap(directory=str(scene.resolve()))
        out = {}
        for state in states:
            s = bpy.context.scene.recgs
            for k, v in {"running": SAMPLE_RUNNING, "done": SAMPLE_DONE}.get(state, {}).items():
                setattr(s, k, v)
            out[state] = snapshot(bpy.context, running=state == "running")
        return out
    finally:
        addon.unregister()


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--state", choices=["idle", "running", "done"], default="idle")
    p.add_argument("--scene", type=Path, default=None, help="COLMAP survey to import first")
    args = p.parse_args(argv)
    print(snapshots(args.scene, [args.state])[args.state])
    return 0


if __name__ == "__main__":
    sys.exit(main())
