"""RecGS for Blender: 3D Gaussian Splatting of underwater surveys with caustics removed.

``recgs_addon.core`` is the Blender-free core (importable from plain Python);
``recgs_addon.blender`` is the thin Blender layer (operators, menus, object sync).
``python -m recgs_addon`` is the command-line entry point.
"""

__version__ = "0.1.0"
