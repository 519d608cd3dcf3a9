"""The Blender layer, headless with the bpy module: import/export operators, cameras, sync."""
import numpy as np
import pytest

from conftest import write_colmap_scene
from test_ply import assert_same, random_gaussians

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def _scene_state(bpy):
    return (sorted(o.name for o in bpy.data.objects), sorted(c.name for c in bpy.data.collections),
            len(bpy.data.meshes), len(bpy.data.cameras))


@pytest.mark.parametrize("params", [[60.0, 66.0, 30.3, 26.1], [70.0, 58.5, 35.9, 21.2]],
                         ids=["fy>fx", "fx>fy"])
def test_blender_cameras_project_like_pycolmap(tmp_path, bpy_session, params):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from recgs_addon.blender.cameras import apply_render_settings

    root = tmp_path / "s"
    rec = write_colmap_scene(root, params=params, n_points=120)
    assert bpy.ops.recgs.import_colmap(directory=str(root)) == {"FINISHED"}
    scene = bpy.context.scene
    worst, n = 0.0, 0
    for image in rec.images.values():
        cam_obj = bpy.data.objects[image.name]
        apply_render_settings(scene, cam_obj)
        W, H = scene.render.resolution_x, scene.render.resolution_y
        cam = rec.camera(image.camera_id)
        for p2d in image.points2D:
            if not p2d.has_point3D():
                continue
            xyz = rec.point3D(p2d.point3D_id).xyz
            ref = cam.img_from_cam(image.cam_from_world() * xyz)
            v = world_to_camera_view(scene, cam_obj, Vector(xyz))
            uv = np.array([v.x * W, (1.0 - v.y) * H])
            worst = max(worst, float(np.abs(uv - ref).max()))
            n += 1
    assert n > 100
    assert worst < 0.05, worst


def test_import_colmap_builds_collection(colmap_scene, bpy_session):
    root, rec = colmap_scene
    assert bpy.ops.recgs.import_colmap(directory=str(root)) == {"FINISHED"}
    coll = bpy.data.collections["RecGS survey"]
    cams = [o for o in coll.all_objects if o.type == "CAMERA"]
    assert sorted(o.name for o in cams) == sorted(im.name for im in rec.images.values())
    obj = bpy.context.active_object
    assert obj.name == "survey Gaussians" and len(obj.data.vertices) == rec.num_points3D()
    for name in ["f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                 "rot_0", "rot_1", "rot_2", "rot_3"]:
        a = obj.data.attributes[name]
        assert a.domain == "POINT" and a.data_type == "FLOAT"
    assert bpy.context.scene.camera is not None


def test_ply_object_ply_bit_identical(tmp_path, bpy_session):
    from recgs_addon.core.io.ply import write_gaussian_ply

    src = tmp_path / "in.ply"
    write_gaussian_ply(src, random_gaussians(n=300, degree=3))
    assert bpy.ops.recgs.import_ply(filepath=str(src)) == {"FINISHED"}
    assert bpy.ops.recgs.export_ply(filepath=str(tmp_path / "out.ply")) == {"FINISHED"}
    assert (tmp_path / "out.ply").read_bytes() == src.read_bytes()


def test_export_opens_in_blenders_own_ply_reader(tmp_path, bpy_session):
    """Blender's native importer (an independent reader) finds every property by its INRIA name."""
    from recgs_addon.core.io.ply import gaussians_to_records, write_gaussian_ply

    g = random_gaussians(n=40, degree=1)
    src = tmp_path / "in.ply"
    write_gaussian_ply(src, g)
    bpy.ops.recgs.import_ply(filepath=str(src))
    bpy.ops.recgs.export_ply(filepath=str(tmp_path / "out.ply"))
    bpy.ops.wm.ply_import(filepath=str(tmp_path / "out.ply"))
    native = bpy.context.selected_objects[0]
    assert native.name == "out"
    rec = gaussians_to_records(g)
    pos = np.empty(3 * len(g), np.float32)
    native.data.attributes["position"].data.foreach_get("vector", pos)
    assert np.array_equal(pos.reshape(-1, 3), g.means)
    for name in rec.dtype.names:
        if name in ("x", "y", "z", "nx", "ny", "nz"):
            continue
        buf = np.empty(len(g), np.float32)
        native.data.attributes[name].data.foreach_get("value", buf)
        assert np.array_equal(buf, rec[name]), name


def test_edits_are_honoured_by_export(tmp_path, bpy_session):
    """Deleting vertices (as in Edit Mode) removes exactly those Gaussians, values unchanged."""
    import bmesh

    from recgs_addon.core.io.ply import read_gaussian_ply, write_gaussian_ply

    g = random_gaussians(n=100, degree=2)
    write_gaussian_ply(tmp_path / "in.ply", g)
    bpy.ops.recgs.import_ply(filepath=str(tmp_path / "in.ply"))
    obj = bpy.context.active_object
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    drop = [v for v in bm.verts if v.index % 2 == 0]
    bmesh.ops.delete(bm, geom=drop, context="VERTS")
    bmesh.update_edit_mesh(obj.data)
    bpy.ops.recgs.export_ply(filepath=str(tmp_path / "out.ply"))  # still in Edit Mode
    bpy.ops.object.mode_set(mode="OBJECT")
    assert_same(g.subset(np.arange(100) % 2 == 1), read_gaussian_ply(tmp_path / "out.ply"))


def test_export_bakes_similarity_transform(tmp_path, bpy_session):
    """Exported moved/rotated/scaled Gaussians render like the unmoved ones from the moved camera."""
    from mathutils import Euler, Matrix

    from recgs_addon.core.model.gaussians import GaussianSet
    from recgs_addon.core.io.ply import read_gaussian_ply, write_gaussian_ply
    from reference_render import reference_render

    rng = np.random.default_rng(4)
    n = 40
    g = GaussianSet(np.concatenate([rng.uniform(-0.6, 0.6, (n, 2)), rng.uniform(2.5, 3.5, (n, 1))], 1),
                    np.log(rng.uniform(0.03, 0.15, (n, 3))), rng.normal(size=(n, 4)),
                    rng.normal(1.0, 1.0, n), rng.normal(0.0, 0.4, (n, 16, 3)))
    write_gaussian_ply(tmp_path / "in.ply", g)
    bpy.ops.recgs.import_ply(filepath=str(tmp_path / "in.ply"))
    obj = bpy.context.active_object
    s = 1.7
    M = Matrix.Translation((0.4, -1.2, 2.0)) @ Euler((0.3, -0.5, 1.1)).to_matrix().to_4x4() @ Matrix.Scale(s, 4)
    obj.matrix_world = M
    bpy.ops.recgs.export_ply(filepath=str(tmp_path / "moved.ply"))
    moved = read_gaussian_ply(tmp_path / "moved.ply")

    K = np.array([[40.0, 0, 17.3], [0, 44.0, 13.1], [0, 0, 1]])
    view = np.eye(4)
    Mn = np.array(M, dtype=np.float64)
    Rm = Mn[:3, :3] / s
    view2 = np.eye(4)  # the camera moved with the object: x_cam' = s x_cam
    view2[:3, :3] = view[:3, :3] @ Rm.T
    view2[:3, 3] = s * view[:3, 3] - view[:3, :3] @ Rm.T @ Mn[:3, 3]
    args = dict(K=K, width=36, height=28, near=0.01)
    a = reference_render(g.means, g.log_scales, g.quats, g.logit_opacities, g.sh, view, **args)
    b = reference_render(moved.means, moved.log_scales, moved.quats, moved.logit_opacities, moved.sh,
                         view2, **args)
    assert a["alpha"].max() > 0.5  # the scene is in view
    assert np.abs(a["rgb"] - b["rgb"]).max() < 2e-4
    assert np.abs(s * a["depth"] - b["depth"]).max() < 1e-3


def test_export_refuses_non_uniform_scale(tmp_path, bpy_session):
    from recgs_addon.core.io.ply import write_gaussian_ply

    write_gaussian_ply(tmp_path / "in.ply", random_gaussians(n=10, degree=1))
    bpy.ops.recgs.import_ply(filepath=str(tmp_path / "in.ply"))
    bpy.context.active_object.scale = (1.0, 2.0, 1.0)
    with pytest.raises(RuntimeError, match="non-uniform scale"):
        bpy.ops.recgs.export_ply(filepath=str(tmp_path / "out.ply"))
    assert not (tmp_path / "out.ply").exists()


def test_export_without_gaussian_object_reports(tmp_path, bpy_session):
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="Select a Gaussian object"):
        bpy.ops.recgs.export_ply(filepath=str(tmp_path / "out.ply"))


def _garble(path):
    path.write_text("# header\nthis is not a colmap line\n")


def _resize_image(path):
    from recgs_addon.core.io.images import write_image

    write_image(path, np.zeros((40, 50, 3), np.float32))


def _unsupported_model(root):
    p = root / "sparse/0/cameras.txt"
    p.write_text("1 EQUIRECTANGULAR 64 48 64 48\n")


BAD_INPUTS = {  # case -> (text model?, scene kwargs, how to break it, expected message)
    "missing cameras.bin": (False, {}, lambda r: (r / "sparse/0/cameras.bin").unlink(), "cameras.bin: file is missing"),
    "missing images.bin": (False, {}, lambda r: (r / "sparse/0/images.bin").unlink(), "images.bin: file is missing"),
    "missing points3D.bin": (False, {}, lambda r: (r / "sparse/0/points3D.bin").unlink(), "points3D.bin: file is missing"),
    "truncated cameras.bin": (False, {}, lambda r: (r / "sparse/0/cameras.bin").write_bytes(
        (r / "sparse/0/cameras.bin").read_bytes()[:40]), "cameras.bin: file is truncated"),
    "truncated images.bin": (False, {}, lambda r: (r / "sparse/0/images.bin").write_bytes(
        (r / "sparse/0/images.bin").read_bytes()[:100]), "images.bin: file is truncated"),
    "truncated points3D.bin": (False, {}, lambda r: (r / "sparse/0/points3D.bin").write_bytes(
        (r / "sparse/0/points3D.bin").read_bytes()[:-9]), "points3D.bin: file is truncated"),
    "garbage images.txt": (True, {}, lambda r: _garble(r / "sparse/0/images.txt"), "images.txt"),
    "image missing": (False, {}, lambda r: (r / "images/img_001.png").unlink(), "img_001.png: image file is missing"),
    "unreadable image": (False, {}, lambda r: (r / "images/img_001.png").write_bytes(b"nope"),
                         "img_001.png: cannot read image"),
    "image size disagrees": (False, {}, lambda r: _resize_image(r / "images/img_002.png"),
                             "img_002.png: image is 50x40 but its COLMAP camera 1 is 64x48"),
    "unsupported camera model": (True, {}, _unsupported_model, "uses the EQUIRECTANGULAR model"),
    "empty point cloud": (False, {"n_points": 0}, lambda r: None, "the model has no 3D points"),
    "image names a missing camera": (True, {}, lambda r: (r / "sparse/0/images.txt").write_text(
        (r / "sparse/0/images.txt").read_text().replace(" 1 img_000.png", " 7 img_000.png")),
        r"images.txt: line 5: image 1 \('img_000.png'\) names camera 7, which cameras.txt does not have"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_colmap_input_reports_and_leaves_scene(tmp_path, bpy_session, case):
    text, kwargs, breaker, message = BAD_INPUTS[case]
    root = tmp_path / "relevé 1"
    write_colmap_scene(root, binary=not text, **kwargs)
    bpy.ops.mesh.primitive_cube_add()
    before = _scene_state(bpy)
    breaker(root)
    with pytest.raises(RuntimeError, match=message) as info:
        bpy.ops.recgs.import_colmap(directory=str(root))
    assert str(root) in str(info.value)
    assert _scene_state(bpy) == before


def test_import_colmap_non_ascii_path_with_spaces(tmp_path, bpy_session):
    root = tmp_path / "fonds marins ñ é"
    write_colmap_scene(root, names=["vue ß 1.png", "vue ß 2.png"])
    assert bpy.ops.recgs.import_colmap(directory=str(root)) == {"FINISHED"}
    assert "vue ß 1.png" in bpy.data.objects
    out = tmp_path / "export é.ply"
    bpy.ops.recgs.export_ply(filepath=str(out))
    assert out.exists()


def test_bad_ply_reports_and_leaves_scene(tmp_path, bpy_session):
    p = tmp_path / "nuage de points é.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n0 0 0\n")
    before = _scene_state(bpy)
    with pytest.raises(RuntimeError, match="nuage de points é.ply: not a 3D Gaussian Splatting PLY"):
        bpy.ops.recgs.import_ply(filepath=str(p))
    assert _scene_state(bpy) == before


def test_ply_with_only_nan_rows_reports_and_leaves_scene(tmp_path, bpy_session):
    from recgs_addon.core.io.ply import write_gaussian_ply

    g = random_gaussians(n=10, degree=0)
    g.logit_opacities[:] = np.nan
    write_gaussian_ply(tmp_path / "void.ply", g)
    before = _scene_state(bpy)
    with pytest.raises(RuntimeError, match="void.ply: all 10 Gaussians have NaN or Inf values"):
        bpy.ops.recgs.import_ply(filepath=str(tmp_path / "void.ply"))
    assert _scene_state(bpy) == before


def test_ply_with_nan_rows_warns_and_imports_rest(tmp_path, bpy_session):
    from recgs_addon.core.io.ply import write_gaussian_ply

    g = random_gaussians(n=10, degree=0)
    g.log_scales[3, 1] = np.nan
    write_gaussian_ply(tmp_path / "nan.ply", g)
    assert bpy.ops.recgs.import_ply(filepath=str(tmp_path / "nan.ply")) == {"FINISHED"}
    assert len(bpy.context.active_object.data.vertices) == 9


def test_import_colmap_without_folder_reports(bpy_session):
    with pytest.raises(RuntimeError, match="Choose a scene folder"):
        bpy.ops.recgs.import_colmap(directory="")


def test_os_errors_are_reported_not_raised(tmp_path, bpy_session, monkeypatch):
    """A file-system failure inside the core (here: a PLY that cannot be opened) is a report."""
    from recgs_addon.core.io import ply as plymod
    from recgs_addon.core.io.ply import write_gaussian_ply

    write_gaussian_ply(tmp_path / "g.ply", random_gaussians(n=5, degree=0))

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied", str(tmp_path / "g.ply"))

    monkeypatch.setattr(plymod, "read_ply_elements", denied)
    before = _scene_state(bpy)
    with pytest.raises(RuntimeError, match="Permission denied"):
        bpy.ops.recgs.import_ply(filepath=str(tmp_path / "g.ply"))
    assert _scene_state(bpy) == before


# --- the .blend, written whole or not at all ----------------------------------------------------

def _blend_objects(path):
    """Object names in a saved .blend (read without opening it)."""
    with bpy.data.libraries.load(str(path)) as (data_from, _):
        return sorted(data_from.objects)


def test_blend_saved_through_a_temporary_and_the_previous_kept_on_failure(tmp_path, bpy_session, monkeypatch):
    """The .blend the import and batch commands write appears whole or not at all, like every
    other output: a save that fails (a full disk when the file is renamed into place, or
    Blender's own write failing half way) leaves the previous file as it was, no temporary
    and no Blender '@' file, and says so naming the file. No .blend1 backup appears."""
    import errno
    import os

    from recgs_addon.blender import blendfile
    from recgs_addon.core.io.atomic import OutputError

    path = tmp_path / "scene.blend"
    bpy.ops.mesh.primitive_cube_add()
    blendfile.save_blend(path)
    bpy.ops.mesh.primitive_uv_sphere_add()
    blendfile.save_blend(path)                                # over the first one
    assert _blend_objects(path) == ["Cube", "Sphere"] and sorted(p.name for p in tmp_path.iterdir()) == ["scene.blend"]
    assert bpy.data.filepath == ""                            # a copy: the session keeps its own name
    before = path.read_bytes()
    bpy.ops.mesh.primitive_monkey_add()

    def full_disk(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OutputError, match=r"scene.blend: could not write the .blend file: the disk is full "
                                          r"\(the previous one is kept\)"):
        blendfile.save_blend(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["scene.blend"]

    class HalfWritten:      # Blender writes NAME@, then fails
        class ops:
            class wm:
                @staticmethod
                def save_as_mainfile(filepath, **kw):
                    with open(f"{filepath}@", "wb") as f:
                        f.write(b"BLENDER-v500 cut short")
                    raise RuntimeError(f"Error: Cannot write file {filepath}@: No space left on device\n")
    monkeypatch.setattr(blendfile, "bpy", HalfWritten)
    with pytest.raises(OutputError, match=r"scene.blend: could not write the .blend file: Cannot write file "
                                          r".*scene.blend: No space left on device \(the previous one is kept\)"):
        blendfile.save_blend(path)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["scene.blend"]


def test_export_operator_on_a_full_disk_reports_and_keeps_the_previous_export(tmp_path, bpy_session, monkeypatch):
    """Export 3DGS PLY when the disk fills half way: the operator reports the full disk in the
    UI (RuntimeError headless), the previous export still reads, no temporary is left."""
    import builtins

    from recgs_addon.core.io.ply import read_gaussian_ply, write_gaussian_ply
    from test_reliability import DiskFullAfter, leftovers

    write_gaussian_ply(tmp_path / "in.ply", random_gaussians(n=2000, degree=1))
    assert bpy.ops.recgs.import_ply(filepath=str(tmp_path / "in.ply")) == {"FINISHED"}
    out = tmp_path / "exports" / "model.ply"
    write_gaussian_ply(out, random_gaussians(n=7, degree=0))
    monkeypatch.setattr(builtins, "open", DiskFullAfter(out.parent, 5000))
    with pytest.raises(RuntimeError, match=r"model.ply: could not write the PLY: the disk is full \(the previous one is kept\)"):
        bpy.ops.recgs.export_ply(filepath=str(out))
    monkeypatch.undo()
    assert len(read_gaussian_ply(out)) == 7 and leftovers(out.parent) == []
