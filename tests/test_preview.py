"""EEVEE preview (Geometry Nodes point instances) and the selection operators, headless."""
import os
import types
from pathlib import Path

import numpy as np
import pytest

from test_ply import random_gaussians

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def session(bpy_session):
    """bpy_session with the preview registered (whether or not the add-on's register does it)."""
    from recgs_addon.blender import preview

    mine = not hasattr(bpy.types.Object, "recgs_preview")
    if mine:
        preview.register()
    try:
        yield bpy
    finally:
        if mine:
            preview.unregister()


def _gaussian_object(g, name="G"):
    from recgs_addon.blender import gaussian_object as gobj

    obj = gobj.create_gaussian_object(name, g, bpy.context.scene.collection)
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    return obj


def _evaluated(obj):
    """(number of instances, number of points) of the object's evaluated geometry (viewport)."""
    dg = bpy.context.evaluated_depsgraph_get()
    geo = obj.evaluated_get(dg).evaluated_geometry()
    inst = geo.instances_pointcloud()
    pc = geo.pointcloud
    return (len(inst.points) if inst else 0), (len(pc.points) if pc else 0)


def _read(attrs, name, width=1, prop="value"):
    a = attrs[name]
    buf = np.empty(len(a.data) * width, np.float32)
    a.data.foreach_get(prop, buf)
    return buf.reshape(len(a.data), width) if width > 1 else buf


def test_ensure_builds_modifier_group_and_materials(session):
    from recgs_addon.blender import preview, preview_nodes

    obj = _gaussian_object(random_gaussians(n=200, degree=1))
    mod = preview.ensure_preview(obj)
    assert mod.name == preview.MODIFIER_NAME and mod.type == "NODES"
    assert mod.node_group.name == preview_nodes.NODE_GROUP_NAME
    kinds = {n.bl_idname for n in mod.node_group.nodes}
    assert {"GeometryNodeInstanceOnPoints", "GeometryNodeMeshIcoSphere", "GeometryNodeMeshToPoints",
            "FunctionNodeQuaternionToRotation"} <= kinds
    assert [m.name for m in obj.data.materials] == [preview.SPLAT_MATERIAL, preview.POINT_MATERIAL]
    assert bpy.data.materials[preview.SPLAT_MATERIAL].surface_render_method == "DITHERED"
    assert preview.preview_mode(obj) == "ELLIPSOIDS"
    assert obj.recgs_preview.mode == "ELLIPSOIDS"
    assert obj.recgs_preview.display_ratio == 1.0  # small objects show everything
    assert _evaluated(obj) == (200, 0)


def test_ensure_is_idempotent_and_keeps_settings(session):
    from recgs_addon.blender import preview

    obj = _gaussian_object(random_gaussians(n=50, degree=0))
    preview.ensure_preview(obj, mode="POINTS", display_ratio=0.5)
    preview.ensure_preview(obj)
    preview.ensure_preview(obj)
    assert len(obj.modifiers) == 1
    assert len(bpy.data.node_groups) == 1
    assert sorted(m.name for m in bpy.data.materials) == sorted([preview.SPLAT_MATERIAL, preview.POINT_MATERIAL])
    assert len(obj.data.materials) == 2
    assert preview.preview_mode(obj) == "POINTS"
    assert preview.get_input(obj, "Display Ratio") == pytest.approx(0.5)
    obj.modifiers.new("Weld", "WELD")  # added after the preview: the preview is moved back last
    preview.ensure_preview(obj)
    assert [m.name for m in obj.modifiers] == ["Weld", preview.MODIFIER_NAME]
    # A second object shares the node group and the materials.
    other = _gaussian_object(random_gaussians(n=20, degree=0, seed=1), "H")
    preview.ensure_preview(other)
    assert other.modifiers[0].node_group == preview.preview_modifier(obj).node_group
    assert len(bpy.data.node_groups) == 1 and len(bpy.data.materials) == 2
    with pytest.raises(ValueError, match="not a Gaussian object"):
        bpy.ops.mesh.primitive_cube_add()
        preview.ensure_preview(bpy.context.active_object)


def test_large_object_starts_with_a_display_ratio(session):
    from recgs_addon.blender import preview

    n = 4000
    old = preview.DEFAULT_VIEWPORT_GAUSSIANS
    preview.DEFAULT_VIEWPORT_GAUSSIANS = 1000
    try:
        obj = _gaussian_object(random_gaussians(n=n, degree=0))
        preview.ensure_preview(obj)
    finally:
        preview.DEFAULT_VIEWPORT_GAUSSIANS = old
    assert preview.get_input(obj, "Display Ratio") == pytest.approx(0.25)


def test_display_ratio_keeps_a_deterministic_fraction(session):
    from recgs_addon.blender import preview

    n = 4000
    obj = _gaussian_object(random_gaussians(n=n, degree=0))
    preview.ensure_preview(obj, display_ratio=1.0)
    assert _evaluated(obj) == (n, 0)
    counts = {}
    for mode, idx in (("ELLIPSOIDS", 0), ("POINTS", 1)):
        for ratio in (0.25, 0.1):
            preview.ensure_preview(obj, mode=mode, display_ratio=ratio)
            c = _evaluated(obj)[idx]
            assert abs(c - ratio * n) < 5 * np.sqrt(n * ratio * (1 - ratio)), (mode, ratio, c)
            assert _evaluated(obj)[idx] == c  # deterministic
            counts[mode, ratio] = c
    assert counts["ELLIPSOIDS", 0.25] == counts["POINTS", 0.25]  # same Gaussians in both modes
    obj.recgs_preview.display_ratio = 0.0
    assert _evaluated(obj) == (0, 0)


def test_min_opacity_hides_transparent_gaussians(session):
    from recgs_addon.blender import preview
    from recgs_addon.core.model.gaussians import sigmoid

    g = random_gaussians(n=500, degree=0)
    obj = _gaussian_object(g)
    preview.ensure_preview(obj, display_ratio=1.0)
    obj.recgs_preview.min_opacity = 0.6
    assert _evaluated(obj)[0] == int((sigmoid(g.logit_opacities) >= 0.6).sum())


def test_modes_switch_and_attributes_match_numpy(session):
    """Instances carry T(mean) R S and the scene-linear DC colour; points carry the radius."""
    from recgs_addon.blender import preview
    from recgs_addon.core.model.cameras import quat_to_rotmat
    from recgs_addon.core.model.gaussians import SH_C0, sigmoid

    g = random_gaussians(n=300, degree=2)
    g.quats[0] = 0.0  # a zero quaternion is the identity, as in the rasterizer
    obj = _gaussian_object(g)
    preview.ensure_preview(obj, mode="ELLIPSOIDS", display_ratio=1.0)
    dg = bpy.context.evaluated_depsgraph_get()
    geo = obj.evaluated_get(dg).evaluated_geometry()
    inst = geo.instances_pointcloud()
    assert len(inst.points) == 300 and geo.pointcloud is None
    names = {a.name for a in inst.attributes}
    assert not any(x.startswith(("f_rest_", "f_dc_", "scale_", "rot_")) for x in names)  # not copied
    m = _read(inst.attributes, "instance_transform", 16).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    q = g.quats.astype(np.float64).copy()
    q[0] = (1, 0, 0, 0)
    expect = quat_to_rotmat(q) * np.exp(g.log_scales.astype(np.float64))[:, None, :]
    assert np.abs(m[:, :3, :3] - expect).max() < 1e-5
    assert np.abs(m[:, :3, 3] - g.means).max() < 1e-6
    c = np.maximum(SH_C0 * g.sh[:, 0, :].astype(np.float64) + 0.5, 0.0)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    assert np.abs(_read(inst.attributes, "recgs_color", 4, "color")[:, :3] - lin).max() < 1e-5
    assert np.abs(_read(inst.attributes, "recgs_alpha") - sigmoid(g.logit_opacities)).max() < 1e-6

    obj.recgs_preview.mode = "POINTS"
    obj.recgs_preview.point_size = 2.0
    assert preview.preview_mode(obj) == "POINTS"
    dg = bpy.context.evaluated_depsgraph_get()
    geo = obj.evaluated_get(dg).evaluated_geometry()
    assert geo.instances_pointcloud() is None and len(geo.pointcloud.points) == 300
    radius = _read(geo.pointcloud.attributes, "radius")
    assert np.allclose(radius, 2.0 * np.exp(g.log_scales.astype(np.float64).mean(1)), rtol=1e-5)
    assert geo.pointcloud.materials[0].name == preview.POINT_MATERIAL

    obj.recgs_preview.mode = "ELLIPSOIDS"
    assert _evaluated(obj) == (300, 0)


def test_preview_follows_edits(session):
    """Deleting vertices and changing attributes show without calling ensure_preview again."""
    import bmesh

    from recgs_addon.blender import preview

    obj = _gaussian_object(random_gaussians(n=100, degree=0))
    preview.ensure_preview(obj, display_ratio=1.0)
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    bmesh.ops.delete(bm, geom=[v for v in bm.verts if v.index < 30], context="VERTS")
    bmesh.update_edit_mesh(obj.data)
    assert _evaluated(obj)[0] == 70  # the preview shows in Edit Mode too
    bpy.ops.object.mode_set(mode="OBJECT")
    obj.data.attributes["f_dc_0"].data.foreach_set("value", np.full(70, 10.0, np.float32))
    obj.data.update()
    dg = bpy.context.evaluated_depsgraph_get()
    geo = obj.evaluated_get(dg).evaluated_geometry()
    red = _read(geo.instances_pointcloud().attributes, "recgs_color", 4, "color")[:, 0]
    assert np.allclose(red, ((0.28209479 * 10 + 0.5 + 0.055) / 1.055) ** 2.4, rtol=1e-5)


def test_remove_preview(session):
    from recgs_addon.blender import preview

    obj = _gaussian_object(random_gaussians(n=10, degree=0))
    preview.ensure_preview(obj)
    preview.remove_preview(obj)
    assert len(obj.modifiers) == 0 and len(obj.data.materials) == 0
    assert preview.preview_mode(obj) is None
    assert _evaluated(obj) == (0, 0)


def test_save_and_reload_keeps_preview(tmp_path, session):
    from recgs_addon.blender import preview, preview_nodes

    obj = _gaussian_object(random_gaussians(n=400, degree=1))
    preview.ensure_preview(obj, mode="ELLIPSOIDS", display_ratio=0.5)
    obj.recgs_preview.extent = 2.0
    bpy.data.materials[preview.SPLAT_MATERIAL].surface_render_method = "BLENDED"
    count = _evaluated(obj)[0]
    path = tmp_path / "preview.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    obj = bpy.data.objects["G"]
    mod = preview.preview_modifier(obj)
    assert mod is not None and mod.node_group.name == preview_nodes.NODE_GROUP_NAME
    assert obj.recgs_preview.display_ratio == pytest.approx(0.5)
    assert obj.recgs_preview.extent == pytest.approx(2.0)
    assert [m.name for m in obj.data.materials] == [preview.SPLAT_MATERIAL, preview.POINT_MATERIAL]
    assert _evaluated(obj)[0] == count
    preview.ensure_preview(obj)  # the artist's choice of blending survives an update
    assert bpy.data.materials[preview.SPLAT_MATERIAL].surface_render_method == "BLENDED"
    assert len(bpy.data.node_groups) == 1


def test_outdated_node_group_is_rebuilt_in_place(session):
    from recgs_addon.blender import preview, preview_nodes

    obj = _gaussian_object(random_gaussians(n=30, degree=0))
    preview.ensure_preview(obj)
    ng = bpy.data.node_groups[preview_nodes.NODE_GROUP_NAME]
    ng["recgs_preview_version"] = 0
    ng.nodes.clear()
    preview.ensure_preview(obj)
    assert len(bpy.data.node_groups) == 1 and ng.get("recgs_preview_version") == preview_nodes.VERSION
    assert _evaluated(obj)[0] == 30


# --------------------------------------------------------------------------------------
# Selection operators
# --------------------------------------------------------------------------------------

def _selected(obj):
    sel = np.empty(len(obj.data.vertices), bool)
    obj.data.vertices.foreach_get("select", sel)
    return sel


def _sizes_object():
    from recgs_addon.core.model.gaussians import GaussianSet

    rng = np.random.default_rng(3)
    n = 1000
    log_scales = np.log(rng.uniform(0.01, 0.05, (n, 3)))
    huge = rng.random(n) < 0.03
    log_scales[huge, rng.integers(0, 3, huge.sum())] = np.log(2.0)
    g = GaussianSet(rng.normal(size=(n, 3)), log_scales, rng.normal(size=(n, 4)),
                    rng.normal(0, 3, n), rng.normal(size=(n, 1, 3)))
    return g, _gaussian_object(g)


@pytest.mark.parametrize("edit_mode", [False, True], ids=["object", "edit"])
def test_select_by_opacity(session, edit_mode):
    from recgs_addon.core.model.gaussians import sigmoid

    g, obj = _sizes_object()
    o = sigmoid(g.logit_opacities)
    if edit_mode:
        bpy.ops.object.mode_set(mode="EDIT")
    assert bpy.ops.recgs.select_opacity(threshold=0.2, side="BELOW") == {"FINISHED"}
    assert obj.mode == ("EDIT" if edit_mode else "OBJECT")
    bpy.ops.object.mode_set(mode="OBJECT")  # read the selection back from the mesh
    assert np.array_equal(_selected(obj), o < 0.2)
    if edit_mode:
        bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.recgs.select_opacity(threshold=0.9, side="ABOVE", action="ADD")
    bpy.ops.object.mode_set(mode="OBJECT")
    assert np.array_equal(_selected(obj), (o < 0.2) | (o > 0.9))
    bpy.ops.recgs.select_opacity(threshold=0.1, side="BELOW", action="SUBTRACT")
    assert np.array_equal(_selected(obj), ((o >= 0.1) & (o < 0.2)) | (o > 0.9))


def test_select_by_size_uses_world_units(session):
    g, obj = _sizes_object()
    size = np.exp(g.log_scales.astype(np.float64)).max(1)
    bpy.ops.recgs.select_size(threshold=0.04, side="ABOVE")
    assert np.array_equal(_selected(obj), size > 0.04)
    obj.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    bpy.ops.recgs.select_size(threshold=0.04, side="BELOW")
    assert np.array_equal(_selected(obj), 2.0 * size < 0.04)


def test_select_cleanup_then_delete(session):
    from recgs_addon.blender import gaussian_object as gobj
    from recgs_addon.core.model.gaussians import sigmoid

    g, obj = _sizes_object()
    size = np.exp(g.log_scales.astype(np.float64)).max(1)
    expect = (sigmoid(g.logit_opacities) < 0.05) | (size > 10 * np.median(size))
    assert 10 < expect.sum() < 500
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.recgs.select_cleanup(min_opacity=0.05, size_factor=10.0)
    bpy.ops.mesh.delete(type="VERT")
    bpy.ops.object.mode_set(mode="OBJECT")
    kept = gobj.read_mesh(obj.data)
    assert len(kept) == (~expect).sum()
    assert np.array_equal(kept.means, g.means[~expect])


def test_draw_panel_runs(session):
    """draw_panel only touches existing properties and operators (a stub layout records them)."""
    from recgs_addon.blender import preview

    calls = []

    class Layout:
        def __getattr__(self, name):
            if name in ("column", "row", "box"):
                return lambda *a, **k: self
            return lambda *a, **k: calls.append((name, a, k)) or types.SimpleNamespace()

    obj = _gaussian_object(random_gaussians(n=10, degree=0))
    ctx = types.SimpleNamespace(active_object=obj, scene=bpy.context.scene)
    preview.draw_panel(Layout(), ctx)
    preview.ensure_preview(obj)
    preview.draw_panel(Layout(), ctx)
    for name, args, _ in calls:
        if name == "prop":
            assert hasattr(args[0], args[1]), args[1]
        if name == "operator":
            mod, op = args[0].split(".")
            assert hasattr(getattr(bpy.ops, mod), op), args[0]
    assert sum(1 for c in calls if c[0] == "operator") >= 5


# --------------------------------------------------------------------------------------
# EEVEE against the core renderer
# --------------------------------------------------------------------------------------

def _eevee_scene():
    """A few hundred Gaussians of varied colour, opacity, size and shape on a bumpy patch."""
    from conftest import look_at_pose
    from recgs_addon.core.model.cameras import Camera
    from recgs_addon.core.model.gaussians import GaussianSet, logit, rgb_to_sh_dc

    rng = np.random.default_rng(0)
    n = 300
    means = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-0.2, 0.2, (n, 1))]
    g = GaussianSet(means, np.log(rng.uniform(0.02, 0.12, (n, 3))), rng.normal(size=(n, 4)),
                    logit(rng.uniform(0.2, 0.95, n)), rgb_to_sh_dc(rng.uniform(0.05, 0.95, (n, 3)))[:, None, :])
    R, t = look_at_pose([0.3, -0.4, 2.6], [0, 0, 0], up=(0, 1, 0))
    return g, Camera("view.png", 128, 96, 100.0, 100.0, 64.0, 48.0, R, t)


@pytest.mark.slow
@pytest.mark.parametrize("method, samples", [("BLENDED", 4), ("DITHERED", 16)])
def test_eevee_render_matches_core_renderer(tmp_path, session, method, samples):
    """Blended converges in a few samples; dithered (the viewport default) needs more."""
    import torch

    from recgs_addon.blender import preview
    from recgs_addon.blender.cameras import apply_render_settings, create_camera_object
    from recgs_addon.core.io.images import read_image, write_image
    from recgs_addon.core.render.rasterizer import render

    g, cam = _eevee_scene()
    with torch.no_grad():
        core = render(*(torch.tensor(a, dtype=torch.float32) for a in
                        (g.means, g.log_scales, g.quats, g.logit_opacities, g.sh)),
                      torch.tensor(cam.viewmat, dtype=torch.float32), torch.tensor(cam.K, dtype=torch.float32),
                      cam.width, cam.height).rgb.clamp(0, 1).numpy()
    scene = bpy.context.scene
    obj = _gaussian_object(g)
    apply_render_settings(scene, create_camera_object(cam, scene.collection))
    preview.ensure_preview(obj, mode="ELLIPSOIDS", display_ratio=0.01)  # renders use every Gaussian
    preview.match_trainer_colour(scene)
    preview.use_eevee(scene, samples)
    bpy.data.materials[preview.SPLAT_MATERIAL].surface_render_method = method
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(tmp_path / "eevee.png")
    try:
        bpy.ops.render.render(write_still=True)
    except RuntimeError as exc:
        pytest.skip(f"EEVEE cannot render here (no usable OpenGL/EGL): {exc}")
    if not (tmp_path / "eevee.png").exists():
        pytest.skip("EEVEE wrote no image (no usable OpenGL/EGL)")
    eevee = read_image(tmp_path / "eevee.png")[..., :3]
    assert eevee.shape == core.shape
    r = float(np.corrcoef(eevee.ravel(), core.ravel())[0, 1])
    print(f"EEVEE preview ({method}, {samples} samples) vs core renderer: Pearson r = {r:.4f}")
    if os.environ.get("RECGS_DOC_IMAGES") and method == "BLENDED":  # refresh the images shown in benchmarks/RESULTS.md#preview-agreement
        write_image(ROOT / "docs/images/preview_eevee.png", eevee)
        write_image(ROOT / "docs/images/preview_core.png", core)
    assert core.max() > 0.5 and eevee.max() > 0.5  # the Gaussians are in view
    assert r >= 0.9, r


def test_use_eevee_picks_this_blenders_eevee_and_its_samples(bpy_session):
    from recgs_addon.blender import preview

    scene = bpy_session.context.scene
    scene.render.engine = "CYCLES"
    preview.use_eevee(scene, 3)
    assert scene.render.engine in ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT") and scene.eevee.taa_render_samples == 3
