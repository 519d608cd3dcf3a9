"""The preview's shared datablocks: the Geometry Nodes group "RecGS Preview" and the materials
"RecGS Splat" and "RecGS Point", built in Python and rebuilt in place when outdated (what they
compute is described in :mod:`.preview`)."""
from __future__ import annotations

import bpy

NODE_GROUP_NAME = "RecGS Preview"
SPLAT_MATERIAL = "RecGS Splat"
POINT_MATERIAL = "RecGS Point"
#: Bumped whenever the node group or a material changes; older ones are rebuilt in place.
VERSION = 1
#: Degree-0 SH constant (core.model.gaussians.SH_C0), written into the nodes.
SH_C0 = 0.28209479177387814
#: Default half-size of the instanced ellipsoid in standard deviations. The Gaussian is cut at
#: exp(-2.5^2 / 2) = 4.4 % of its peak. Measured against the trainer's render (docs/dev/preview.md):
#: correlation 0.979 / 0.978 / 0.974 / 0.971 for 2 / 2.5 / 3 / 4 (blended); smaller is faster (less
#: overdraw), but at 2 the 13.5 % step at the rim shows on large opaque Gaussians.
DEFAULT_EXTENT = 2.5
#: Smallest standard deviation given to an instance (metres), so that the instance matrix
#: stays invertible for the shader's object coordinates.
MIN_SIGMA = 1e-6
#: 3DGS rules copied by the splat shader: alpha clamped at 0.99 and skipped below 1/255.
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0

# Modifier inputs: (name, socket type, default, min, max, description).
_INPUTS = (
    ("Points", "NodeSocketBool", False, None, None, "Show points instead of ellipsoids"),
    ("Display Ratio", "NodeSocketFloat", 1.0, 0.0, 1.0, "Fraction of the Gaussians shown in the viewport"),
    ("Ratio in Renders", "NodeSocketBool", False, None, None,
     "Apply the display ratio to renders too (quick test renders)"),
    ("Extent", "NodeSocketFloat", DEFAULT_EXTENT, 0.5, 6.0,
     "Half-size of the ellipsoids in standard deviations"),
    ("Point Size", "NodeSocketFloat", 1.0, 0.0, 10.0, "Point radius in standard deviations"),
    ("Min Opacity", "NodeSocketFloat", 0.0, 0.0, 1.0, "Hide Gaussians below this opacity"),
    ("Splat Material", "NodeSocketMaterial", None, None, None, "Material of the ellipsoids"),
    ("Point Material", "NodeSocketMaterial", None, None, None, "Material of the points"),
)


# ---------------------------------------------------------------------------------------
# Node building helpers
# ---------------------------------------------------------------------------------------

class _Builder:
    """Small helper to add and link nodes with less noise."""

    def __init__(self, tree):
        self.tree = tree
        self.x = 0

    def node(self, idname, inputs=None, **props):
        n = self.tree.nodes.new(idname)
        for k, v in props.items():
            setattr(n, k, v)
        for key, v in (inputs or {}).items():
            sock = n.inputs[key]
            if isinstance(v, bpy.types.NodeSocket):
                self.tree.links.new(v, sock)
            else:
                sock.default_value = v
        n.location = (self.x, 0)
        self.x += 180
        return n

    def math(self, op, a, b=None, c=None):
        ins = {0: a}
        if b is not None:
            ins[1] = b
        if c is not None:
            ins[2] = c
        return self.node("ShaderNodeMath", ins, operation=op).outputs[0]

    def link(self, a, b):
        self.tree.links.new(a, b)


def _attr(b: _Builder, name: str, data_type: str = "FLOAT"):
    return b.node("GeometryNodeInputNamedAttribute", {"Name": name}, data_type=data_type).outputs["Attribute"]


def _store(b: _Builder, geometry, name: str, data_type: str, value):
    n = b.node("GeometryNodeStoreNamedAttribute", {"Geometry": geometry, "Name": name},
               data_type=data_type, domain="POINT")
    b.link(value, n.inputs["Value"])
    return n.outputs["Geometry"]


def _srgb_to_linear(b: _Builder, c):
    """sRGB EOTF of a non-negative float: c/12.92 below 0.04045, ((c+0.055)/1.055)^2.4 above."""
    low = b.math("DIVIDE", c, 12.92)
    high = b.math("POWER", b.math("MULTIPLY_ADD", c, 1.0 / 1.055, 0.055 / 1.055), 2.4)
    above = b.node("FunctionNodeCompare", {"A": c, "B": 0.04045}, data_type="FLOAT",
                   operation="GREATER_THAN").outputs["Result"]
    sw = b.node("GeometryNodeSwitch", {"Switch": above, "False": low, "True": high}, input_type="FLOAT")
    return sw.outputs[0]


def _set_menu(node, socket_name: str, value: str) -> None:
    """Set a menu input (Blender 5: socket) or the older node property of the same meaning."""
    if socket_name in node.inputs:
        node.inputs[socket_name].default_value = value
    else:  # Blender 4.2-4.x: a node property, upper-case identifier
        setattr(node, socket_name.lower().replace(" ", "_"), value.upper())


def _build_interface(ng) -> None:
    """Make the group's sockets exactly ``_INPUTS``, keeping the existing ones (and so their
    identifiers, under which modifiers store their values) where name and type match."""
    wanted = [("Geometry", "NodeSocketGeometry", "INPUT")]
    wanted += [(name, stype, "INPUT") for name, stype, *_ in _INPUTS]
    wanted += [("Geometry", "NodeSocketGeometry", "OUTPUT")]
    items = [i for i in ng.interface.items_tree if i.item_type == "SOCKET"]
    for item in items:
        if (item.name, item.socket_type, item.in_out) not in wanted:
            ng.interface.remove(item)
    have = {(i.name, i.socket_type, i.in_out): i for i in ng.interface.items_tree if i.item_type == "SOCKET"}
    for key in wanted:
        if key not in have:
            have[key] = ng.interface.new_socket(key[0], in_out=key[2], socket_type=key[1])
    for pos, key in enumerate(k for k in wanted if k[2] == "INPUT"):
        ng.interface.move(have[key], pos + 1)  # outputs are listed first
    for name, stype, default, lo, hi, desc in _INPUTS:
        s = have[(name, stype, "INPUT")]
        s.description = desc
        if default is not None:
            s.default_value = default
        if lo is not None:
            s.min_value, s.max_value = lo, hi


def _build_node_group(ng) -> None:
    ng.nodes.clear()
    _build_interface(ng)

    b = _Builder(ng)
    gi = b.node("NodeGroupInput")
    geo = gi.outputs["Geometry"]

    # Derived attributes, computed from the INRIA ones on the mesh points.
    rgb = []
    for i in range(3):
        c = b.math("MAXIMUM", b.math("MULTIPLY_ADD", _attr(b, f"f_dc_{i}"), SH_C0, 0.5), 0.0)
        rgb.append(_srgb_to_linear(b, c))
    colour = b.node("FunctionNodeCombineColor", {"Red": rgb[0], "Green": rgb[1], "Blue": rgb[2]}).outputs[0]
    geo = _store(b, geo, "recgs_color", "FLOAT_COLOR", colour)
    alpha = b.math("DIVIDE", 1.0, b.math("ADD", 1.0, b.math("EXPONENT", b.math("MULTIPLY", _attr(b, "opacity"), -1.0))))
    geo = _store(b, geo, "recgs_alpha", "FLOAT", alpha)
    logs = [_attr(b, f"scale_{i}") for i in range(3)]
    sig = [b.math("MAXIMUM", b.math("EXPONENT", s), MIN_SIGMA) for s in logs]
    geo = _store(b, geo, "recgs_scale", "FLOAT_VECTOR",
                 b.node("ShaderNodeCombineXYZ", {"X": sig[0], "Y": sig[1], "Z": sig[2]}).outputs[0])
    mean_log = b.math("DIVIDE", b.math("ADD", b.math("ADD", logs[0], logs[1]), logs[2]), 3.0)
    geo = _store(b, geo, "recgs_radius", "FLOAT", b.math("MAXIMUM", b.math("EXPONENT", mean_log), MIN_SIGMA))
    q = b.node("FunctionNodeQuaternionToRotation")  # normalises; a zero quaternion is the identity
    for i, key in enumerate("WXYZ"):
        b.link(_attr(b, f"rot_{i}"), q.inputs[key])
    geo = _store(b, geo, "recgs_rot", "QUATERNION", q.outputs[0])
    # Drop the raw attributes (up to 59 per vertex) so instancing does not copy them.
    for pattern in ("f_dc_*", "f_rest_*", "scale_*", "rot_*", "opacity"):
        rm = b.node("GeometryNodeRemoveAttribute", {"Geometry": geo, "Name": pattern})
        _set_menu(rm, "Pattern Mode", "Wildcard")
        geo = rm.outputs[0]

    # Which Gaussians are shown: a deterministic fraction in the viewport, opacity cut.
    rnd = b.node("FunctionNodeRandomValue", {"ID": b.node("GeometryNodeInputIndex").outputs[0], "Seed": 0},
                 data_type="BOOLEAN")
    b.link(gi.outputs["Display Ratio"], rnd.inputs["Probability"])
    all_in_render = b.node("FunctionNodeBooleanMath", {0: b.node("GeometryNodeIsViewport").outputs[0]},
                           operation="NOR")  # a render that ignores the ratio
    b.link(gi.outputs["Ratio in Renders"], all_in_render.inputs[1])
    in_render = all_in_render.outputs[0]
    # The boolean output: the 4th of four typed sockets up to Blender 5.0, the only one from 5.1
    # (whose sockets follow the data type).
    rnd_bool = next(o for o in rnd.outputs if o.type == "BOOLEAN" and getattr(o, "enabled", True))
    shown = b.node("FunctionNodeBooleanMath", {0: rnd_bool, 1: in_render}, operation="OR").outputs[0]
    opaque = b.node("FunctionNodeCompare", {"A": _attr(b, "recgs_alpha")}, data_type="FLOAT",
                    operation="GREATER_EQUAL")
    b.link(gi.outputs["Min Opacity"], opaque.inputs["B"])
    keep = b.node("FunctionNodeBooleanMath", {0: shown, 1: opaque.outputs["Result"]}, operation="AND").outputs[0]

    # Ellipsoids.
    ico = b.node("GeometryNodeMeshIcoSphere", {"Subdivisions": 1})
    b.link(gi.outputs["Extent"], ico.inputs["Radius"])
    ico_mat = b.node("GeometryNodeSetMaterial", {"Geometry": ico.outputs["Mesh"]})
    b.link(gi.outputs["Splat Material"], ico_mat.inputs["Material"])
    inst = b.node("GeometryNodeInstanceOnPoints", {
        "Points": geo, "Selection": keep, "Instance": ico_mat.outputs[0],
        "Rotation": _attr(b, "recgs_rot", "QUATERNION"), "Scale": _attr(b, "recgs_scale", "FLOAT_VECTOR")})
    # Points.
    radius = b.math("MULTIPLY", _attr(b, "recgs_radius"))
    b.link(gi.outputs["Point Size"], radius.node.inputs[1])
    pts = b.node("GeometryNodeMeshToPoints", {"Mesh": geo, "Selection": keep, "Radius": radius})
    pts_mat = b.node("GeometryNodeSetMaterial", {"Geometry": pts.outputs[0]})
    b.link(gi.outputs["Point Material"], pts_mat.inputs["Material"])

    sw = b.node("GeometryNodeSwitch", {"False": inst.outputs[0], "True": pts_mat.outputs[0]},
                input_type="GEOMETRY")
    b.link(gi.outputs["Points"], sw.inputs["Switch"])
    go = b.node("NodeGroupOutput")
    b.link(sw.outputs[0], go.inputs[0])
    ng["recgs_preview_version"] = VERSION


def _emptied(mat) -> "_Builder":
    """A builder over ``mat``'s node tree, emptied for a rebuild."""
    if mat.node_tree is None:  # Blender < 5 (use_nodes is deprecated in 5.0, always on)
        mat.use_nodes = True
    mat.node_tree.nodes.clear()
    return _Builder(mat.node_tree)


def _build_splat_material(mat) -> None:
    b = _emptied(mat)
    colour = b.node("ShaderNodeAttribute", attribute_type="INSTANCER", attribute_name="recgs_color")
    opacity = b.node("ShaderNodeAttribute", attribute_type="INSTANCER", attribute_name="recgs_alpha")
    p = b.node("ShaderNodeTexCoord").outputs["Object"]  # instance space: the Gaussian is N(0, I)
    view = b.node("ShaderNodeVectorTransform", {"Vector": b.node("ShaderNodeNewGeometry").outputs["Incoming"]},
                  vector_type="VECTOR", convert_from="WORLD", convert_to="OBJECT").outputs[0]
    v = b.node("ShaderNodeVectorMath", {0: view}, operation="NORMALIZE").outputs[0]
    pp = b.node("ShaderNodeVectorMath", {0: p, 1: p}, operation="DOT_PRODUCT").outputs["Value"]
    pv = b.node("ShaderNodeVectorMath", {0: p, 1: v}, operation="DOT_PRODUCT").outputs["Value"]
    b2 = b.math("SUBTRACT", pp, b.math("MULTIPLY", pv, pv))  # squared distance of the ray to the centre
    a = b.math("MULTIPLY", opacity.outputs["Fac"], b.math("EXPONENT", b.math("MULTIPLY", b2, -0.5)))
    a = b.math("MINIMUM", a, ALPHA_MAX)
    a = b.math("MULTIPLY", a, b.math("GREATER_THAN", a, ALPHA_MIN))
    emit = b.node("ShaderNodeEmission", {"Strength": 1.0})
    b.link(colour.outputs["Color"], emit.inputs["Color"])
    mix = b.node("ShaderNodeMixShader", {0: a, 1: b.node("ShaderNodeBsdfTransparent").outputs[0], 2: emit.outputs[0]})
    out = b.node("ShaderNodeOutputMaterial")
    b.link(mix.outputs[0], out.inputs["Surface"])
    mat.use_backface_culling = True  # one sample per viewing ray
    if mat.get("recgs_preview_version") is None:  # a new material; later the artist's choice
        mat.surface_render_method = "DITHERED"
    mat.diffuse_color = (0.8, 0.8, 0.8, 1.0)
    mat["recgs_preview_version"] = VERSION


def _build_point_material(mat) -> None:
    b = _emptied(mat)
    colour = b.node("ShaderNodeAttribute", attribute_type="GEOMETRY", attribute_name="recgs_color")
    emit = b.node("ShaderNodeEmission", {"Strength": 1.0})
    b.link(colour.outputs["Color"], emit.inputs["Color"])
    out = b.node("ShaderNodeOutputMaterial")
    b.link(emit.outputs[0], out.inputs["Surface"])
    mat["recgs_preview_version"] = VERSION


def _ensure_datablock(collection, name, builder, *args):
    block = collection.get(name)
    if block is None:
        block = collection.new(name, *args)
    if block.get("recgs_preview_version") != VERSION:
        builder(block)
    return block


def node_group():
    """The shared preview node group (built or rebuilt in place when missing or outdated)."""
    return _ensure_datablock(bpy.data.node_groups, NODE_GROUP_NAME, _build_node_group, "GeometryNodeTree")


def splat_material():
    return _ensure_datablock(bpy.data.materials, SPLAT_MATERIAL, _build_splat_material)


def point_material():
    return _ensure_datablock(bpy.data.materials, POINT_MATERIAL, _build_point_material)
