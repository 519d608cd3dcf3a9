"""Scene loading: formats, folder layouts, undistortion, and one clear error per bad input."""
import shutil

import numpy as np
import pytest

from conftest import write_colmap_scene
from recgs_addon.core.io.colmap import load_scene
from recgs_addon.core.errors import SceneError
from recgs_addon.core.io.images import read_image


def _check_matches(scene, rec):
    assert len(scene.cameras) == rec.num_reg_images()
    assert [c.name for c in scene.cameras] == sorted(c.name for c in scene.cameras)
    for cam in scene.cameras:
        im = rec.image(cam.image_id)
        m = np.asarray(im.cam_from_world().matrix())
        assert np.allclose(cam.R, m[:, :3]) and np.allclose(cam.t, m[:, 3])
    ref = np.array([p.xyz for p in rec.points3D.values()])
    assert np.allclose(np.sort(scene.points, axis=0), np.sort(ref, axis=0), atol=1e-6)


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("sub", ["sparse/0", "sparse", "."])
def test_load_layouts_and_formats(tmp_path, binary, sub):
    root = tmp_path / "s"
    rec = write_colmap_scene(root, binary=binary, sparse_sub=sub)
    scene = load_scene(root)
    _check_matches(scene, rec)
    c = scene.cameras[0]
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (64, 48, 60.0, 60.0, 32.0, 24.0)
    assert scene.colors.dtype == np.uint8 and scene.points.shape[1] == 3
    assert scene.load_image(c).shape == (48, 64, 3)
    assert scene.load_image(c, downscale=2).shape == (24, 32, 3)


def test_simple_pinhole_used_directly(tmp_path):
    rec = write_colmap_scene(tmp_path / "s", model="SIMPLE_PINHOLE")
    scene = load_scene(tmp_path / "s")
    assert not scene.undistorted and scene.cameras[0].fx == scene.cameras[0].fy == 60.0
    _check_matches(scene, rec)


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "OPENCV"])
def test_distorted_models_are_undistorted_into_cache(tmp_path, model):
    root = tmp_path / "s"
    write_colmap_scene(root, model=model)
    before = {p.name: p.read_bytes() for p in (root / "images").iterdir()}
    scene = load_scene(root)
    assert scene.undistorted
    assert scene.image_dir != root / "images" and (root / ".recgs_cache") in scene.image_dir.parents
    assert {p.name: p.read_bytes() for p in (root / "images").iterdir()} == before  # never written over
    cam = scene.cameras[0]
    img = scene.load_image(cam)
    assert img.shape == (cam.height, cam.width, 3)
    # the undistorted model's own points project where its observations are
    from recgs_addon.core.io.colmap import read_reconstruction

    rec = read_reconstruction(scene.model_dir)
    errs = []
    for c in scene.cameras:
        im = rec.image(c.image_id)
        for p2d in im.points2D:
            if p2d.has_point3D():
                uv, _ = c.project(rec.point3D(p2d.point3D_id).xyz[None])
                errs.append(np.abs(uv[0] - p2d.xy).max())
    assert len(errs) > 50 and max(errs) < 1e-3
    # second load reuses the cache
    mtime = scene.image_path(cam).stat().st_mtime_ns
    again = load_scene(root)
    assert again.image_dir == scene.image_dir and again.image_path(cam).stat().st_mtime_ns == mtime


def test_unsupported_model_refused(tmp_path):
    root = tmp_path / "s"
    write_colmap_scene(root, model="SIMPLE_PINHOLE", binary=False)
    p = root / "sparse/0/cameras.txt"
    lines = [ln if ln.startswith("#") or not ln.strip() else "1 EQUIRECTANGULAR 64 48 64 48"
             for ln in p.read_text().splitlines()]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(SceneError, match=r"cameras.txt: camera 1 uses the EQUIRECTANGULAR model"):
        load_scene(root)


@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin"])
def test_missing_model_file(colmap_scene, fname):
    root, _ = colmap_scene
    (root / "sparse/0" / fname).unlink()
    with pytest.raises(SceneError, match=f"{fname}: file is missing"):
        load_scene(root)


@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_model_file(colmap_scene, fname):
    root, _ = colmap_scene
    p = root / "sparse/0" / fname
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneError, match=f"{fname}: file is truncated"):
        load_scene(root)


@pytest.mark.parametrize("fname", ["cameras.txt", "images.txt", "points3D.txt"])
def test_garbage_text_model(tmp_path, fname):
    root = tmp_path / "s"
    write_colmap_scene(root, binary=False)
    p = root / "sparse/0" / fname
    p.write_text("# header\nthis is not a colmap line\n")
    with pytest.raises(SceneError, match=fname):
        load_scene(root)


def test_no_model_at_all(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="no COLMAP model found"):
        load_scene(tmp_path / "empty")
    with pytest.raises(SceneError, match="folder does not exist"):
        load_scene(tmp_path / "nope")


def test_image_listed_but_missing(colmap_scene):
    root, _ = colmap_scene
    (root / "images/img_002.png").unlink()
    with pytest.raises(SceneError, match="img_002.png: image file is missing"):
        load_scene(root)


def test_unreadable_image(colmap_scene):
    root, _ = colmap_scene
    (root / "images/img_001.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(SceneError, match="img_001.png: cannot read image"):
        load_scene(root)


def test_image_size_disagrees_with_camera(colmap_scene):
    from recgs_addon.core.io.images import write_image

    root, _ = colmap_scene
    write_image(root / "images/img_003.png", np.zeros((40, 50, 3), np.float32))
    with pytest.raises(SceneError, match=r"img_003.png: image is 50x40 but its COLMAP camera 1 is 64x48"):
        load_scene(root)


def test_empty_point_cloud(tmp_path):
    root = tmp_path / "s"
    write_colmap_scene(root, n_points=0)
    with pytest.raises(SceneError, match="points3D.bin: the model has no 3D points"):
        load_scene(root)


def test_image_folder_missing(colmap_scene):
    root, _ = colmap_scene
    shutil.rmtree(root / "images")
    with pytest.raises(SceneError, match="image folder does not exist"):
        load_scene(root)


def test_other_image_folder(colmap_scene):
    root, _ = colmap_scene
    shutil.copytree(root / "images", root / "clean")
    scene = load_scene(root, image_dir=root / "clean")
    assert scene.image_dir == root / "clean"
    assert read_image(scene.image_path(scene.cameras[0])).shape == (48, 64, 3)


def test_paths_with_spaces_and_non_ascii(tmp_path):
    root = tmp_path / "relevé sous-marin 1"
    rec = write_colmap_scene(root, names=["vue ñ 1.png", "vue ñ 2.png", "vue ñ 3.png"])
    _check_matches(load_scene(root), rec)


def test_param_count_table_matches_pycolmap():
    import pycolmap

    from recgs_addon.core.io.colmap import _MODEL_NUM_PARAMS

    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name != "INVALID":
            cam = pycolmap.Camera.create_from_model_name(1, name, 60.0, 64, 48)
            assert _MODEL_NUM_PARAMS[mid.value] == len(cam.params), name


def test_opencv_binary_cameras_bin_passes_structural_check(tmp_path):
    write_colmap_scene(tmp_path / "s", model="OPENCV")
    from recgs_addon.core.io.colmap import _check_cameras_bin

    _check_cameras_bin(tmp_path / "s/sparse/0/cameras.bin")


def test_all_images_missing_says_so(colmap_scene):
    root, _ = colmap_scene
    for p in (root / "images").iterdir():
        p.rename(root / p.name)
    with pytest.raises(SceneError, match=r"images: none of the 4 images the COLMAP model lists are in this folder"):
        load_scene(root)


# --- values no survey can use: each a clear error naming the file --------------------------------

def _text_scene(tmp_path):
    root = tmp_path / "survey"
    write_colmap_scene(root, binary=False, n_images=3, n_points=30)
    return root, root / "sparse" / "0"


def _edit_first_data_line(path, edit):
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    lines[i] = edit(lines[i].split())
    path.write_text("\n".join(lines) + "\n")


def _binary_scene(tmp_path, edit):
    """A binary survey whose reconstruction ``edit(rec)`` changed before it was written: the
    values pycolmap's text reader would refuse (NaN) reach us only through binary files."""
    root = tmp_path / "survey"
    rec = write_colmap_scene(root, n_images=3, n_points=30)
    edit(rec)
    rec.write_binary(str(root / "sparse" / "0"))
    return root


@pytest.mark.parametrize("params,msg", [([float("nan"), 60, 32, 24], "NaN or infinite"),
                                        ([60, float("inf"), 32, 24], "NaN or infinite"),
                                        ([-60, 60, 32, 24], "focal length <= 0")])
def test_camera_with_unusable_parameters(tmp_path, params, msg):
    def edit(rec):
        rec.cameras[1].params = params
    root = _binary_scene(tmp_path, edit)
    with pytest.raises(SceneError, match=msg) as e:
        load_scene(root)
    assert "cameras.bin" in str(e.value) and "camera 1" in str(e.value)


def test_camera_without_pixels_is_blamed_on_the_camera(tmp_path):
    root, model = _text_scene(tmp_path)
    _edit_first_data_line(model / "cameras.txt", lambda t: " ".join(t[:2] + ["0", "0"] + t[4:]))
    with pytest.raises(SceneError) as e:
        load_scene(root)
    assert "cameras.txt" in str(e.value) and "0x0" in str(e.value)


def test_pose_with_nan_is_refused(tmp_path):
    import pycolmap

    def edit(rec):
        f = rec.frames[1]
        f.rig_from_world = pycolmap.Rigid3d(f.rig_from_world.rotation, np.array([np.nan, 0.0, 3.0]))
    root = _binary_scene(tmp_path, edit)
    with pytest.raises(SceneError, match="img_000.png.*NaN") as e:
        load_scene(root)
    assert "images.bin" in str(e.value)


def test_points_with_nan_are_dropped_and_all_nan_refused(tmp_path):
    def one(rec):
        rec.points3D[next(iter(rec.points3D))].xyz = np.array([np.nan, 0.0, 0.0])
    with pytest.warns(UserWarning, match="dropped 1 of"):
        scene = load_scene(_binary_scene(tmp_path / "one", one))
    assert np.isfinite(scene.points).all() and len(scene.points) == len(scene.colors)

    def every(rec):
        for pid in rec.points3D:
            rec.points3D[pid].xyz = np.array([np.nan, np.inf, 0.0])
    with pytest.raises(SceneError, match="all .* 3D points have NaN") as e:
        load_scene(_binary_scene(tmp_path / "all", every))
    assert "points3D.bin" in str(e.value)


def test_two_images_with_one_name_are_refused(tmp_path):
    root, model = _text_scene(tmp_path)
    text = (model / "images.txt").read_text().replace("img_001.png", "img_000.png")
    (model / "images.txt").write_text(text)
    with pytest.raises(SceneError, match="same name 'img_000.png'") as e:
        load_scene(root)
    assert "images.txt" in str(e.value)
