"""The survey generator's Blender shading: a small node-tree builder, the caustic rig (one shared
'CausticGain' node group fed by one float image per shot) and the seabed materials (sand, rock,
rusty steel, painted concrete), each of whose base colour is multiplied by the caustic gain.

bpy is imported lazily (:func:`_bpy`), so that importing this module needs no Blender.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


# ---------------------------------------------------------------------------------------------
# Blender scene (bpy imported lazily so that the numpy parts can be used and tested without it)
# ---------------------------------------------------------------------------------------------

def _bpy():
    import bpy  # noqa: WPS433
    return bpy


class NodeBuilder:
    """Tiny helper to build shader node trees: arguments may be sockets or constants."""

    def __init__(self, tree):
        self.tree = tree
        self.nodes = tree.nodes
        self.links = tree.links

    def node(self, kind: str, **props):
        n = self.nodes.new(kind)
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def _set(self, sock, value):
        if hasattr(value, "is_output"):  # a socket
            self.links.new(value, sock)
        elif value is not None:
            sock.default_value = value

    @staticmethod
    def _sock(sockets, identifier):
        return next(s for s in sockets if s.identifier == identifier)

    def coords(self, kind: str = "Object"):
        return self.node("ShaderNodeTexCoord").outputs[kind]

    def position(self):
        return self.node("ShaderNodeNewGeometry").outputs["Position"]

    def noise(self, vec, scale, detail=2.0, rough=0.5, distortion=0.0, out="Fac"):
        n = self.node("ShaderNodeTexNoise")
        for name, v in (("Vector", vec), ("Scale", scale), ("Detail", detail), ("Roughness", rough),
                        ("Distortion", distortion)):
            self._set(n.inputs[name], v)
        return n.outputs[out]

    def voronoi(self, vec, scale, feature="F1", out="Distance", randomness=1.0):
        n = self.node("ShaderNodeTexVoronoi", feature=feature)
        self._set(n.inputs["Vector"], vec)
        self._set(n.inputs["Scale"], scale)
        self._set(n.inputs["Randomness"], randomness)
        return n.outputs[out]

    def wave(self, vec, scale, distortion=4.0, detail=2.0, direction="X"):
        n = self.node("ShaderNodeTexWave", wave_type="BANDS", bands_direction=direction)
        for name, v in (("Vector", vec), ("Scale", scale), ("Distortion", distortion), ("Detail", detail)):
            self._set(n.inputs[name], v)
        return n.outputs["Fac"]

    def ramp(self, fac, stops, interpolation="LINEAR"):
        n = self.node("ShaderNodeValToRGB")
        cr = n.color_ramp
        cr.interpolation = interpolation
        while len(cr.elements) < len(stops):
            cr.elements.new(0.5)
        for el, (pos, col) in zip(cr.elements, stops):
            el.position = pos
            el.color = (*col, 1.0) if len(col) == 3 else col
        self._set(n.inputs["Fac"], fac)
        return n.outputs["Color"]

    def mix(self, fac, a, b, blend="MIX"):
        n = self.node("ShaderNodeMix", data_type="RGBA", blend_type=blend)
        self._set(self._sock(n.inputs, "Factor_Float"), fac)
        self._set(self._sock(n.inputs, "A_Color"), a)
        self._set(self._sock(n.inputs, "B_Color"), b)
        return self._sock(n.outputs, "Result_Color")

    def math(self, op, a, b=None, c=None, clamp=False):
        n = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        for i, v in enumerate((a, b, c)):
            self._set(n.inputs[i], v)
        return n.outputs[0]

    def vmul(self, a, b):
        n = self.node("ShaderNodeVectorMath", operation="MULTIPLY")
        self._set(n.inputs[0], a)
        self._set(n.inputs[1], b)
        return n.outputs[0]

    def map_range(self, x, fmin, fmax, tmin, tmax, clamp=True):
        n = self.node("ShaderNodeMapRange", clamp=clamp)
        for i, v in enumerate((x, fmin, fmax, tmin, tmax)):
            self._set(n.inputs[i], v)
        return n.outputs[0]

    def bump(self, height, strength, distance, normal=None):
        n = self.node("ShaderNodeBump")
        self._set(n.inputs["Height"], height)
        self._set(n.inputs["Strength"], strength)
        self._set(n.inputs["Distance"], distance)
        self._set(n.inputs["Normal"], normal)
        return n.outputs["Normal"]


@dataclass
class CausticRig:
    """Handles to switch the caustics in every seabed material (one shared node group)."""

    group: object
    image_node: object
    enable_node: object
    images: list = field(default_factory=list)

    def set_shot(self, index: int | None) -> None:
        """Caustics of shot ``index`` on, or off (gain identically 1) when ``index`` is None."""
        if index is None:
            self.enable_node.outputs[0].default_value = 0.0
        else:
            self.image_node.image = self.images[index]
            self.enable_node.outputs[0].default_value = 1.0


def build_caustic_group(light_dir: np.ndarray, tile: float):
    """Node group 'CausticGain' -> float gain = 1 + enable * (texture(p projected along sun) - 1)."""
    bpy = _bpy()
    grp = bpy.data.node_groups.new("CausticGain", "ShaderNodeTree")
    grp.interface.new_socket("Gain", in_out="OUTPUT", socket_type="NodeSocketFloat")
    nb = NodeBuilder(grp)
    sep = nb.node("ShaderNodeSeparateXYZ")
    nb.links.new(nb.position(), sep.inputs[0])
    lx, ly, lz = (float(v) for v in light_dir)
    # point projected along the light direction onto z = 0, in tile units
    u = nb.math("MULTIPLY", nb.math("MULTIPLY_ADD", sep.outputs["Z"], -lx / lz, sep.outputs["X"]), 1.0 / tile)
    v = nb.math("MULTIPLY", nb.math("MULTIPLY_ADD", sep.outputs["Z"], -ly / lz, sep.outputs["Y"]), 1.0 / tile)
    comb = nb.node("ShaderNodeCombineXYZ")
    nb.links.new(u, comb.inputs[0])
    nb.links.new(v, comb.inputs[1])
    img = nb.node("ShaderNodeTexImage", interpolation="Linear", extension="REPEAT")
    nb.links.new(comb.outputs[0], img.inputs["Vector"])
    enable = nb.node("ShaderNodeValue")
    enable.outputs[0].default_value = 1.0
    red = nb.node("ShaderNodeSeparateColor")                 # the texture is grey: R = G = B = T
    nb.links.new(img.outputs["Color"], red.inputs[0])
    tex = nb.math("SUBTRACT", red.outputs[0], 1.0)
    gain = nb.math("MULTIPLY_ADD", tex, enable.outputs[0], 1.0)
    out = nb.node("NodeGroupOutput")
    nb.links.new(gain, out.inputs[0])
    return CausticRig(grp, img, enable)


def add_caustic_images(rig: CausticRig, gains: list[np.ndarray]) -> list[dict]:
    """One float, non-colour Blender image per shot; returns the measured stats of each texture."""
    bpy = _bpy()
    stats = []
    for i, g in enumerate(gains):
        res = g.shape[0]
        im = bpy.data.images.new(f"caustic_{i:03d}", res, res, alpha=False, float_buffer=True, is_data=True)
        rgba = np.repeat(g[..., None], 4, axis=-1).astype(np.float32)
        rgba[..., 3] = 1.0
        im.pixels.foreach_set(rgba.ravel())
        im.update()
        back = np.empty(res * res * 4, np.float32)
        im.pixels.foreach_get(back)
        back = back.reshape(res, res, 4)[..., 0].astype(np.float64)
        stats.append({"mean_gain": float(back.mean()), "min_gain": float(back.min()),
                      "max_gain": float(back.max())})
        rig.images.append(im)
    return stats


def _seabed_material(name: str, rig: CausticRig, build, gloss: float = 0.0) -> object:
    """Material whose base colour (from ``build(nb) -> (colour, roughness, normal)``) is x caustic
    gain. ``gloss`` in [0, 1]: a wet, polished surface (roughness towards 0.1, specular up), whose
    highlights follow the view, not the light's motion."""
    bpy = _bpy()
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    nb = NodeBuilder(nt)
    colour, rough, normal = build(nb)
    g = nb.node("ShaderNodeGroup")
    g.node_tree = rig.group
    base = nb.vmul(colour, g.outputs[0])
    bsdf = nb.node("ShaderNodeBsdfPrincipled")
    nb._set(bsdf.inputs["Base Color"], base)
    nb._set(bsdf.inputs["Roughness"], rough if not gloss else (1 - gloss) * rough + gloss * 0.1)
    nb._set(bsdf.inputs["Specular IOR Level"], 0.25 + 0.75 * gloss)
    nb._set(bsdf.inputs["Normal"], normal)
    out = nb.node("ShaderNodeOutputMaterial")
    nb.links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat


def sand_material(rig: CausticRig, seed: int, gloss: float = 0.0):
    """Sand / sediment: patchy colours, pebbles with dark crevices, grain, detritus, ripples."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        w = float(seed % 97) * 1.7
        shifted = nb.node("ShaderNodeVectorMath", operation="ADD")
        nb.links.new(p, shifted.inputs[0])
        shifted.inputs[1].default_value = (w, -w, 0.0)
        p = shifted.outputs[0]
        base = nb.ramp(nb.noise(p, 0.45, detail=3, rough=0.55), [
            (0.25, (0.33, 0.26, 0.15)), (0.45, (0.62, 0.52, 0.33)),
            (0.62, (0.74, 0.66, 0.47)), (0.80, (0.50, 0.48, 0.37))])
        # gravel: per-pebble brightness and dark crevices; dense in patches, sparse elsewhere
        cell = nb.node("ShaderNodeRGBToBW")
        nb.links.new(nb.voronoi(p, 16.0, out="Color"), cell.inputs[0])
        pebble = nb.vmul(base, nb.map_range(cell.outputs[0], 0.0, 1.0, 0.2, 1.7))
        crev = nb.map_range(nb.voronoi(p, 16.0, feature="DISTANCE_TO_EDGE"), 0.0, 0.06, 0.25, 1.0)
        pebble = nb.vmul(pebble, crev)
        mask = nb.map_range(nb.noise(p, 0.9, detail=3), 0.40, 0.58, 0.3, 1.0)
        col = nb.mix(mask, base, pebble)
        # fine grain
        col = nb.vmul(col, nb.map_range(nb.noise(p, 45.0, detail=2), 0.3, 0.7, 0.7, 1.25))
        # shell fragments (bright) and dark grains: small blobs at a random subset of cell centres
        sv = nb.node("ShaderNodeTexVoronoi", feature="F1")
        nb.links.new(p, sv.inputs["Vector"])
        sv.inputs["Scale"].default_value = 12.0
        sbw = nb.node("ShaderNodeRGBToBW")
        nb.links.new(sv.outputs["Color"], sbw.inputs[0])
        blob = nb.map_range(sv.outputs["Distance"], 0.25, 0.32, 1.0, 0.0)
        bright = nb.math("MULTIPLY", blob, nb.map_range(sbw.outputs[0], 0.70, 0.72, 0.0, 1.0))
        dark = nb.math("MULTIPLY", blob, nb.map_range(sbw.outputs[0], 0.30, 0.28, 0.0, 1.0))
        col = nb.mix(bright, col, (0.92, 0.90, 0.84, 1.0))
        col = nb.mix(dark, col, (0.04, 0.04, 0.03, 1.0))
        # dark detritus / algae patches
        spots = nb.map_range(nb.noise(p, 2.6, detail=3, rough=0.6), 0.56, 0.66, 0.0, 0.85)
        col = nb.mix(spots, col, (0.10, 0.13, 0.06, 1.0))
        # sand ripples: shading + slight colour modulation
        rip = nb.wave(p, 5.2, distortion=5.0, detail=3.0)
        col = nb.vmul(col, nb.map_range(rip, 0.0, 1.0, 0.85, 1.1))
        height = nb.math("MULTIPLY_ADD", nb.noise(p, 25.0, detail=2), 0.5, rip)   # ripples + grain
        normal = nb.bump(height, 0.4, 0.015)
        return col, 0.9, normal
    return _seabed_material("Sand", rig, build, gloss)


def tile_material(rig: CausticRig, size: float, grout: float, gloss: float = 0.0):
    """A floor of square tiles ``size`` metres wide (a pool, a harbour's slab) with grout lines
    ``grout`` of a tile wide, or (grout near 0.5) a grid of bars over sand-coloured ground: the
    repetitive texture a plane sweep can match a tile off."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        brick = nb.node("ShaderNodeTexBrick", offset=0.0, squash=1.0)
        nb.links.new(p, brick.inputs["Vector"])
        brick.inputs["Scale"].default_value = 1.0
        brick.inputs["Brick Width"].default_value = size
        brick.inputs["Row Height"].default_value = size
        brick.inputs["Mortar Size"].default_value = grout * size
        brick.inputs["Mortar Smooth"].default_value = 0.1
        brick.inputs["Color1"].default_value = (0.20, 0.42, 0.55, 1.0)
        brick.inputs["Color2"].default_value = (0.16, 0.36, 0.50, 1.0)
        brick.inputs["Mortar"].default_value = (0.75, 0.74, 0.68, 1.0)
        col = nb.vmul(brick.outputs["Color"], nb.map_range(nb.noise(p, 30.0, detail=2), 0.3, 0.7, 0.85, 1.1))
        dirt = nb.map_range(nb.noise(p, 1.5, detail=3), 0.55, 0.65, 0.0, 0.5)
        col = nb.mix(dirt, col, (0.35, 0.33, 0.25, 1.0))
        return col, 0.6, nb.bump(brick.outputs["Fac"], 0.2, 0.005)
    return _seabed_material("Tiles", rig, build, gloss)


def rock_material(rig: CausticRig, name: str, palette, crust):
    """Rough mottled rock with cracks, speckle and an encrusting-growth colour."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        col = nb.ramp(nb.noise(p, 2.5, detail=4, rough=0.6, distortion=0.3),
                      [(0.3, palette[0]), (0.5, palette[1]), (0.7, palette[2])])
        col = nb.vmul(col, nb.map_range(nb.noise(p, 30.0, detail=2), 0.3, 0.7, 0.7, 1.25))
        cracks = nb.map_range(nb.voronoi(p, 5.0, feature="DISTANCE_TO_EDGE"), 0.0, 0.04, 0.25, 1.0)
        col = nb.vmul(col, cracks)
        growth = nb.map_range(nb.noise(p, 3.5, detail=4), 0.55, 0.62, 0.0, 0.9)
        col = nb.mix(growth, col, (*crust, 1.0))
        h = nb.noise(p, 8.0, detail=4, rough=0.65)
        return col, 0.85, nb.bump(h, 0.6, 0.05)
    return _seabed_material(name, rig, build)


def rust_material(rig: CausticRig):
    """Rusty steel pipe with flaking rust and fouling."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        col = nb.ramp(nb.noise(p, 4.0, detail=6, rough=0.6), [
            (0.3, (0.16, 0.07, 0.03)), (0.5, (0.45, 0.18, 0.05)), (0.7, (0.62, 0.32, 0.10))])
        flakes = nb.map_range(nb.voronoi(p, 14.0, out="Distance"), 0.0, 0.5, 0.5, 1.2)
        col = nb.vmul(col, flakes)
        foul = nb.map_range(nb.noise(p, 2.0, detail=4), 0.55, 0.62, 0.0, 0.8)
        col = nb.mix(foul, col, (0.20, 0.28, 0.12, 1.0))
        h = nb.noise(p, 20.0, detail=3)
        return col, 0.7, nb.bump(h, 0.4, 0.02)
    return _seabed_material("Rust", rig, build)


def concrete_material(rig: CausticRig):
    """Concrete block with a painted yellow stripe, stains and pitting."""
    def build(nb: NodeBuilder):
        p = nb.coords("Object")
        sep = nb.node("ShaderNodeSeparateXYZ")
        nb.links.new(p, sep.inputs[0])
        col = nb.ramp(nb.noise(p, 6.0, detail=5), [(0.35, (0.30, 0.29, 0.26)), (0.65, (0.50, 0.48, 0.44))])
        pits = nb.map_range(nb.voronoi(p, 40.0, out="Distance"), 0.0, 0.15, 0.4, 1.0)
        col = nb.vmul(col, pits)
        stripe = nb.math("LESS_THAN", nb.math("ABSOLUTE", sep.outputs["X"]), 0.12)
        worn = nb.math("MULTIPLY", stripe, nb.map_range(nb.noise(p, 12.0, detail=3), 0.35, 0.5, 0.2, 1.0))
        col = nb.mix(worn, col, (0.85, 0.62, 0.05, 1.0))
        stain = nb.map_range(nb.noise(p, 3.0, detail=4), 0.56, 0.64, 0.0, 0.7)
        col = nb.mix(stain, col, (0.15, 0.17, 0.08, 1.0))
        return col, 0.9, nb.bump(nb.noise(p, 25.0, detail=3), 0.3, 0.01)
    return _seabed_material("Concrete", rig, build)
