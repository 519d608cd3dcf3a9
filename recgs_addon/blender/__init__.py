"""The Blender layer: registration of settings, operators, sidebar panels and menu entries."""
from __future__ import annotations

import bpy

from . import engine, operators, panel, preview, properties, training


def register():
    engine.register()
    properties.register()
    for cls in operators.classes:
        bpy.utils.register_class(cls)
    training.register()
    preview.register()
    for cls in panel.classes:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_import)
    bpy.types.TOPBAR_MT_file_export.append(operators.menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(operators.menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_import)
    for cls in reversed(panel.classes):
        bpy.utils.unregister_class(cls)
    preview.unregister()
    training.unregister()
    for cls in reversed(operators.classes):
        bpy.utils.unregister_class(cls)
    properties.unregister()
    engine.unregister()
