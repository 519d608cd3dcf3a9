"""Blender extension entry point (the extension root is this folder).

The add-on lives in ``recgs_addon/``; this file only forwards registration so the same
package also runs from plain Python (``python -m recgs_addon``) and ``blender -b --python``.
"""

from .recgs_addon.blender import register, unregister  # noqa: F401
