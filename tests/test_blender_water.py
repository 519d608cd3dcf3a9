"""The fitted water in Blender (recgs_addon/blender/water.py): medium.json read after a job,
the world volume that puts the water back, checked in a Cycles render against the formula,
and the sidebar's switch."""
import json
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender

MEDIUM = {"attenuation": [0.5, 0.22, 0.34], "backscatter": [0.3, 0.34, 0.3], "veil": [0.012, 0.085, 0.065],
          "length": 3.0}


def _formula(j, r, m=MEDIUM):
    return [jc * math.exp(-a * r) + v * (1 - math.exp(-b * r))
            for jc, a, b, v in zip(j, m["attenuation"], m["backscatter"], m["veil"])]


def test_volume_matches_the_fitted_water_at_the_median_range():
    from recgs_addon.blender.water import volume_settings

    v = volume_settings(MEDIUM)
    absorb = [v["absorption_density"] * (1 - c) for c in v["absorption_colour"]]
    assert np.allclose(absorb, MEDIUM["attenuation"], rtol=1e-9)
    emission = [c * v["emission_strength"] for c in v["emission_colour"]]
    for r, tol in ((3.0, 1e-9), (1.5, 0.15), (5.0, 0.15)):   # exact at the median range, close around it
        vol = [e / a * (1 - math.exp(-a * r)) for e, a in zip(emission, absorb)]
        want = _formula([0, 0, 0], r)
        assert np.allclose(vol, want, rtol=tol), (r, vol, want)


def test_cycles_renders_the_water_in_front_of_a_plane(bpy_session, tmp_path):
    """An emissive plane of known colour 3 m in front of the camera, rendered by Cycles through
    the water world: the pixel is the formula's (the volume is homogeneous: no noise to speak of)."""
    from recgs_addon.blender.water import load_water

    scene = bpy.context.scene
    (tmp_path / "medium.json").write_text(json.dumps({"coefficients": MEDIUM}))
    assert "water modelled" in load_water(scene, tmp_path)
    assert scene.recgs.water and scene.recgs.water_view == "TRUE_COLOUR"
    world = bpy.data.worlds["RecGS Water"]
    scene.world = world
    scene.recgs.water_view = "UNDERWATER"          # the switch connects the volume
    out = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeOutputWorld")
    assert out.inputs["Volume"].is_linked
    bpy.ops.mesh.primitive_plane_add(size=50, location=(0, 0, -3.0))
    plane = bpy.context.active_object
    mat = bpy.data.materials.new("J")
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    em = nt.nodes.new("ShaderNodeEmission")
    j = (0.4, 0.3, 0.2)
    em.inputs["Color"].default_value = (*j, 1)
    nt.links.new(em.outputs[0], nt.nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
    plane.data.materials.append(mat)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location = (0, 0, 0)
    scene.camera = cam
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 256
    scene.cycles.device = "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 8
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    path = tmp_path / "water.exr"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(path))
    px = np.array(img.pixels[:]).reshape(8, 8, 4)[3:5, 3:5, :3].reshape(-1, 3).mean(0)
    want = _formula(j, 3.0)    # the centre pixels' ray is ~3 m long
    assert np.allclose(px, want, rtol=0.03, atol=2e-3), (px, want)
    scene.recgs.water_view = "TRUE_COLOUR"          # and cuts it again
    assert not out.inputs["Volume"].is_linked
