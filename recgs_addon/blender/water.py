"""The fitted water in Blender: a world volume that puts it back in an EEVEE or Cycles render,
and the sidebar's switch between the seabed's true colour and the view as seen underwater.

A training job that modelled the water writes ``medium.json`` beside its PLY (core/outputs/
exports.py); :func:`load_water` reads it into ``scene.recgs.water`` (the coefficients as JSON, so
they travel with the .blend) and builds the world ``RecGS Water``. Its volume is a homogeneous
absorption (the direct signal's attenuation, per channel) plus emission (the veil of backscattered
light): along a ray of length ``r`` that gives ``J exp(-a r) + E / a (1 - exp(-a r))``. The fitted
model's backscatter builds up at its own rate ``b`` (``veil (1 - exp(-b r))``); one homogeneous
volume has one rate, so the emission is chosen to match the fitted veil exactly at the survey's
median range (and closely around it). Scene units are the survey's (Blender's world is COLMAP's).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import bpy

#: Name of the world the water lives in.
WATER_WORLD = "RecGS Water"


def volume_settings(medium: dict) -> dict:
    """Blender volume settings for fitted coefficients (:meth:`Medium.values` layout): the
    Volume Absorption node's colour and density and the Emission's colour and strength."""
    att = [max(float(v), 1e-6) for v in medium["attenuation"]]
    back = [max(float(v), 0.0) for v in medium["backscatter"]]
    veil = [float(v) for v in medium["veil"]]
    r = float(medium.get("length") or 1.0)
    density = max(att)
    # Volume Absorption: absorption coefficient = density * (1 - colour)
    colour = [1.0 - a / density for a in att]
    # emission E per channel: E / a (1 - exp(-a r)) = veil (1 - exp(-b r)) at the median range r
    emission = [a * v * (1.0 - math.exp(-b * r)) / (1.0 - math.exp(-a * r)) for a, b, v in zip(att, back, veil)]
    strength = max(max(emission), 1e-9)
    return {"absorption_colour": colour, "absorption_density": density,
            "emission_colour": [e / strength for e in emission], "emission_strength": strength}


def water_world(medium: dict):
    """The world ``RecGS Water`` with the water's volume (made or updated); its surface is the
    veil's colour, what a camera sees where no seabed is."""
    world = bpy.data.worlds.get(WATER_WORLD) or bpy.data.worlds.new(WATER_WORLD)
    if bpy.app.version < (5, 0, 0) or world.node_tree is None:   # 5.0 on: worlds always use nodes
        world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
    emit = nt.nodes.new("ShaderNodeEmission")
    add = nt.nodes.new("ShaderNodeAddShader")
    v = volume_settings(medium)
    absorb.inputs["Color"].default_value = (*v["absorption_colour"], 1.0)
    absorb.inputs["Density"].default_value = v["absorption_density"]
    emit.inputs["Color"].default_value = (*v["emission_colour"], 1.0)
    emit.inputs["Strength"].default_value = v["emission_strength"]
    bg.inputs["Color"].default_value = (*[float(c) for c in medium["veil"]], 1.0)
    nt.links.new(absorb.outputs[0], add.inputs[0])
    nt.links.new(emit.outputs[0], add.inputs[1])
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    add.name = "water"
    return world


def show_water(scene, underwater: bool) -> None:
    """Connect (``underwater``) or cut the water world's volume."""
    world = bpy.data.worlds.get(WATER_WORLD)
    if world is None or world.node_tree is None:
        return
    nt = world.node_tree
    out = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeOutputWorld")
    for link in list(out.inputs["Volume"].links):
        nt.links.remove(link)
    if underwater:
        nt.links.new(nt.nodes["water"].outputs[0], out.inputs["Volume"])


def load_water(scene, out_dir: Path) -> str:
    """After a training job: read ``OUT/medium.json`` into the scene and build the water world
    (true colour shown). Returns a note for the job's message ("" when the run had no water)."""
    path = Path(out_dir) / "medium.json"
    try:
        medium = json.loads(path.read_text(encoding="utf-8")).get("coefficients") if path.is_file() else None
    except (OSError, ValueError) as exc:
        return f"{path}: not read ({exc})"
    s = scene.recgs
    if not medium:
        s.water = ""
        return ""
    s.water = json.dumps(medium)
    water_world(medium)
    show_water(scene, s.water_view == "UNDERWATER")
    return "water modelled: true colour shown (switch to As Seen Underwater in the sidebar)"


def on_water_view(settings, context) -> None:
    """``scene.recgs.water_view``'s update: show or hide the water and use its world."""
    scene = context.scene
    if not settings.water:
        return
    world = bpy.data.worlds.get(WATER_WORLD) or water_world(json.loads(settings.water))
    scene.world = world
    show_water(scene, settings.water_view == "UNDERWATER")
