"""EEVEE preview of a Gaussian object: a Geometry Nodes modifier built in Python.

The modifier "RecGS Preview" runs the node group "RecGS Preview" (one per file, shared by every
Gaussian object) on the object's mesh, whose vertices carry the INRIA attributes (see
:mod:`.gaussian_object`). Everything the preview shows is computed in nodes from those
attributes, so edits (deleted or moved vertices) and live training updates need no extra step:

* ``recgs_color``  (point colour, scene-linear): ``c = max(0, SH_C0 f_dc + 0.5)`` is the
  trainer's colour, in the sRGB-encoded space of the photos; the sRGB EOTF turns it into the
  scene-linear radiance Blender renders with. With the *Standard* view transform the render
  re-encodes it to sRGB, i.e. back to the trainer's space (:func:`match_trainer_colour`).
* ``recgs_alpha``  = sigmoid(opacity), ``recgs_scale`` = exp(scale_0..2) (the standard
  deviations, metres), ``recgs_rot`` = the normalised quaternion rot_0..3 (w, x, y, z; a zero
  quaternion is the identity), ``recgs_radius`` = the geometric mean of the deviations.

Modes:

* ``ELLIPSOIDS``: an ico sphere (subdivision 1) of radius *Extent* (in standard deviations,
  default 2.5) is instanced on every kept point, rotated by ``recgs_rot`` and scaled by
  ``recgs_scale``, so in the instance's own (object) coordinates the Gaussian is the unit
  isotropic one. The material "RecGS Splat" is emission (the trainer's colours are radiance, so
  no lighting) mixed with transparency by ``alpha = min(0.99, o exp(-b^2 / 2))``, where ``b``
  is the distance, in instance coordinates, from the instance centre to the viewing ray through
  the pixel: the peak of the 3D Gaussian along that ray, which is what 3DGS's projected 2D
  Gaussian is for an affine camera. ``b`` does not change along the ray, so the coarse mesh
  only has to cover the splat. Back faces are culled (one sample per ray). The surface render
  method is *Dithered* by default (stochastic transparency: order-independent, exact for
  intersecting Gaussians, drawn in instanced batches, so about 6x cheaper per Gaussian than
  blending; noisy until the samples accumulate) or *Blended* (EEVEE sorts the instances back
  to front like 3DGS's depth sort and draws them one by one: right after one sample, for
  final renders and small sets).
* ``POINTS``: the kept vertices become a point cloud of radius *Point Size* x ``recgs_radius``
  with the opaque material "RecGS Point": fast, no blending.

*Display Ratio* keeps a deterministic fraction of the Gaussians (a random boolean per vertex
index, fixed seed) in the viewport; renders use them all unless *Ratio in Renders* is set. *Min Opacity* hides
Gaussians below that opacity everywhere.

This module adds the modifier, reads and writes its inputs and holds the per-object settings
and the operators; :mod:`.preview_nodes` builds the node group and the materials.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, PointerProperty

from . import gaussian_object as gobj
from .preview_nodes import (DEFAULT_EXTENT, POINT_MATERIAL, SH_C0, SPLAT_MATERIAL, node_group, point_material,
                            splat_material)

MODIFIER_NAME = "RecGS Preview"
#: A new preview shows about this many Gaussians in the viewport (display ratio below 1 for
#: larger objects); renders always use every Gaussian.
DEFAULT_VIEWPORT_GAUSSIANS = 200_000

MODES = (("ELLIPSOIDS", "Ellipsoids", "Instanced ellipsoids shaded as Gaussians (what renders match)"),
         ("POINTS", "Points", "Opaque points: fast, for large objects and navigation"))


# ---------------------------------------------------------------------------------------
# Modifier access
# ---------------------------------------------------------------------------------------

def preview_modifier(obj):
    """The object's preview modifier, or None."""
    if obj is None:
        return None
    mod = obj.modifiers.get(MODIFIER_NAME)
    return mod if mod is not None and mod.type == "NODES" else None


def _identifier(ng, name: str) -> str:
    for item in ng.interface.items_tree:
        if item.item_type == "SOCKET" and item.in_out == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)


def _socket_value(mod, key: str):
    """Where a Geometry Nodes modifier keeps an input's value: Blender 5.2 (at least) has a
    typed struct per input (``mod.properties.inputs.<identifier>.value``); up to 5.0 the
    values are ID properties of the modifier (``mod[identifier]``). Returns the 5.2 struct,
    or None for the ID-property layout."""
    props = getattr(mod, "properties", None)
    inputs = getattr(props, "inputs", None) if props is not None else None
    return getattr(inputs, key, None) if inputs is not None else None


def get_input(obj, name: str, default=None):
    """A preview modifier input's value (``default`` without a preview)."""
    mod = preview_modifier(obj)
    if mod is None or mod.node_group is None:
        return default
    try:
        key = _identifier(mod.node_group, name)
    except KeyError:
        return default
    sock = _socket_value(mod, key)
    if sock is not None:
        return sock.value
    return mod.get(key, default)


def set_input(obj, name: str, value) -> None:
    mod = preview_modifier(obj)
    if mod is None:
        raise ValueError(f"'{obj.name}' has no preview; add it with ensure_preview")
    key = _identifier(mod.node_group, name)
    sock = _socket_value(mod, key)
    if sock is not None:
        if sock.value != value:
            sock.value = value
            obj.update_tag()
    elif mod.get(key) != value:
        mod[key] = value
        obj.update_tag()


def ensure_preview(obj, mode=None, display_ratio=None):
    """Add or update the preview modifier, node group and materials of a Gaussian object.

    Idempotent. ``mode`` ('ELLIPSOIDS' or 'POINTS') and ``display_ratio`` (0..1, viewport
    only) set those settings; None keeps the current ones (a new preview starts with
    ellipsoids and a ratio showing about :data:`DEFAULT_VIEWPORT_GAUSSIANS`). The modifier is
    kept last, so it sees every other modifier's output. Returns the modifier.
    """
    if not gobj.is_gaussian_object(obj):
        raise ValueError(f"'{getattr(obj, 'name', obj)}' is not a Gaussian object")
    if mode is not None and mode not in {m[0] for m in MODES}:
        raise ValueError(f"unknown preview mode {mode!r}")
    ng = node_group()
    mod = preview_modifier(obj)
    new = mod is None
    if new:
        mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
        mod.show_in_editmode = True
        mod.show_on_cage = False
    if mod.node_group is not ng:
        mod.node_group = ng
    while obj.modifiers[-1] != mod:  # stay last
        obj.modifiers.move(list(obj.modifiers).index(mod), len(obj.modifiers) - 1)
    if new:
        n = len(obj.data.vertices)
        set_input(obj, "Display Ratio", min(1.0, DEFAULT_VIEWPORT_GAUSSIANS / max(n, 1)))
    if get_input(obj, "Splat Material") is None:
        set_input(obj, "Splat Material", splat_material())
    if get_input(obj, "Point Material") is None:
        set_input(obj, "Point Material", point_material())
    if mode is not None:
        set_input(obj, "Points", mode == "POINTS")
    if display_ratio is not None:
        set_input(obj, "Display Ratio", float(min(max(display_ratio, 0.0), 1.0)))
    # Materials are also slots of the object, so the viewport and exporters list them.
    for mat in (get_input(obj, "Splat Material"), get_input(obj, "Point Material")):
        if mat is not None and mat.name not in obj.data.materials:
            obj.data.materials.append(mat)
    obj.update_tag()
    return mod


def remove_preview(obj) -> None:
    """Remove the preview modifier (the shared node group and materials stay in the file)."""
    mod = preview_modifier(obj)
    if mod is not None:
        obj.modifiers.remove(mod)
    for name in (SPLAT_MATERIAL, POINT_MATERIAL):
        i = obj.data.materials.find(name)
        if i >= 0:
            obj.data.materials.pop(index=i)


def preview_mode(obj):
    """'ELLIPSOIDS', 'POINTS', or None without a preview."""
    if preview_modifier(obj) is None:
        return None
    return "POINTS" if get_input(obj, "Points", False) else "ELLIPSOIDS"


def match_trainer_colour(scene) -> None:
    """Colour settings under which renders show the trainer's colours: the Standard view
    transform (plain sRGB encoding), no look, exposure 0, gamma 1, a black world."""
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    if scene.world is None:
        scene.world = bpy.data.worlds.new("RecGS Black")
    world = scene.world
    world.color = (0.0, 0.0, 0.0)
    if world.node_tree is not None:
        bg = next((n for n in world.node_tree.nodes if n.type == "BACKGROUND"), None)
        if bg is not None:
            bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)


def use_eevee(scene, samples: int) -> None:
    """Render ``scene`` with EEVEE at ``samples`` samples a pixel (the engine is named
    ``BLENDER_EEVEE_NEXT`` in Blender 4.2-4.x, ``BLENDER_EEVEE`` before and since)."""
    try:
        scene.render.engine = "BLENDER_EEVEE"
    except TypeError:
        scene.render.engine = "BLENDER_EEVEE_NEXT"
    scene.eevee.taa_render_samples = samples


# ---------------------------------------------------------------------------------------
# Per-object settings (a view of the modifier inputs: nothing is stored twice)
# ---------------------------------------------------------------------------------------

def _getter(name, default):
    def get(self):
        return get_input(self.id_data, name, default)
    return get


def _setter(name):
    def set_(self, value):
        obj = self.id_data
        if preview_modifier(obj) is None:
            ensure_preview(obj)
        set_input(obj, name, value)
    return set_


def _get_mode(self):
    return 1 if get_input(self.id_data, "Points", False) else 0


def _set_mode(self, value):
    ensure_preview(self.id_data, mode=MODES[value][0])


class RecGSPreviewSettings(bpy.types.PropertyGroup):
    """Preview settings of one Gaussian object (stored in its preview modifier)."""

    mode: EnumProperty(name="Mode", items=MODES, get=_get_mode, set=_set_mode,
                       description="How the viewport draws the Gaussians")
    display_ratio: FloatProperty(name="Display Ratio", min=0.0, max=1.0, subtype="FACTOR",
                                 get=_getter("Display Ratio", 1.0), set=_setter("Display Ratio"),
                                 description="Fraction of the Gaussians shown in the viewport "
                                             "(renders use all)")
    ratio_in_renders: BoolProperty(name="Ratio in Renders", get=_getter("Ratio in Renders", False),
                                   set=_setter("Ratio in Renders"),
                                   description="Apply the display ratio to renders too (quick test renders)")
    extent: FloatProperty(name="Extent", min=0.5, max=6.0, get=_getter("Extent", DEFAULT_EXTENT),
                          set=_setter("Extent"),
                          description="Half-size of the ellipsoids in standard deviations")
    point_size: FloatProperty(name="Point Size", min=0.0, max=10.0, get=_getter("Point Size", 1.0),
                              set=_setter("Point Size"),
                              description="Point radius in standard deviations")
    min_opacity: FloatProperty(name="Min Opacity", min=0.0, max=1.0, subtype="FACTOR",
                               get=_getter("Min Opacity", 0.0), set=_setter("Min Opacity"),
                               description="Hide Gaussians below this opacity")


def _active_gaussians(context):
    obj = context.active_object
    return obj if gobj.is_gaussian_object(obj) else None


class RECGS_OT_preview_add(bpy.types.Operator):
    """Add (or update) the EEVEE preview of the active Gaussian object"""

    bl_idname = "recgs.preview_add"
    bl_label = "Add Preview"
    bl_options = {"REGISTER", "UNDO"}

    mode: EnumProperty(name="Mode", items=MODES, default="ELLIPSOIDS")

    @classmethod
    def poll(cls, context):
        return _active_gaussians(context) is not None

    def execute(self, context):
        obj = _active_gaussians(context)
        ensure_preview(obj, mode=self.mode)
        self.report({"INFO"}, f"Preview of {len(obj.data.vertices)} Gaussians "
                              f"({self.mode.lower()}, display ratio {get_input(obj, 'Display Ratio'):.3g})")
        return {"FINISHED"}


class RECGS_OT_preview_remove(bpy.types.Operator):
    """Remove the EEVEE preview of the active Gaussian object"""

    bl_idname = "recgs.preview_remove"
    bl_label = "Remove Preview"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return preview_modifier(context.active_object) is not None

    def execute(self, context):
        remove_preview(context.active_object)
        return {"FINISHED"}


class RECGS_OT_match_trainer_colour(bpy.types.Operator):
    """Standard view transform and a black world, so renders show the trainer's colours"""

    bl_idname = "recgs.match_trainer_colour"
    bl_label = "Match Trainer Colours"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        match_trainer_colour(context.scene)
        return {"FINISHED"}


def draw_panel(layout, context) -> None:
    """Preview settings of the active object and the selection operators."""
    obj = _active_gaussians(context)
    if obj is None:
        layout.label(text="Select a Gaussian object", icon="INFO")
        return
    col = layout.column(align=True)
    if preview_modifier(obj) is None:
        col.operator(RECGS_OT_preview_add.bl_idname, icon="SHADING_RENDERED")
    else:
        s = obj.recgs_preview
        col.row(align=True).prop(s, "mode", expand=True)
        row = col.row(align=True)
        row.prop(s, "display_ratio")
        row.prop(s, "ratio_in_renders", text="", icon="RESTRICT_RENDER_OFF")
        col.prop(s, "extent" if s.mode == "ELLIPSOIDS" else "point_size")
        col.prop(s, "min_opacity")
        mat = get_input(obj, "Splat Material")
        if s.mode == "ELLIPSOIDS" and mat is not None and hasattr(mat, "surface_render_method"):
            col.prop(mat, "surface_render_method", text="Blending")
        row = col.row(align=True)
        row.operator(RECGS_OT_match_trainer_colour.bl_idname, icon="COLOR")
        row.operator(RECGS_OT_preview_remove.bl_idname, text="", icon="X")
    from . import select_ops

    select_ops.draw_select(layout.column(align=True), context)


from . import select_ops as _select_ops  # noqa: E402  (operators registered with the preview)

classes = (RecGSPreviewSettings, RECGS_OT_preview_add, RECGS_OT_preview_remove,
           RECGS_OT_match_trainer_colour) + _select_ops.classes


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.recgs_preview = PointerProperty(type=RecGSPreviewSettings)


def unregister() -> None:
    if hasattr(bpy.types.Object, "recgs_preview"):
        del bpy.types.Object.recgs_preview
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
