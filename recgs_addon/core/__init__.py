"""Blender-free core of RecGS: scene loading, images, Gaussians, PLY, rendering maths.

Nothing under this package imports ``bpy``; it runs from plain Python and is tested
without Blender. The Blender layer (``recgs_addon.blender``) converts between Blender
data and the plain arrays defined here.
"""
