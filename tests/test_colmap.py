"""Scene loading: formats, folder layouts, undistortion, and one clear error per bad input."""
import shutil

import numpy as np
import pytest

from conftest import write_colmap_scene
from recgs_addon.core.io.colmap import find_model_dir, load_scene
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


def test_two_jobs_undistorting_one_survey_at_once_keep_the_first_cache(tmp_path, monkeypatch):
    """Two runs started side by side on a survey both undistort it: the one that finishes
    second keeps the first one's cache, which that run is reading, instead of deleting it under
    it; a leftover cache without its ``done`` mark is replaced."""
    import pycolmap

    from recgs_addon.core.io import colmap

    root = tmp_path / "s"
    write_colmap_scene(root, model="OPENCV")
    real = pycolmap.undistort_images
    first = {}

    def beside(out_dir, *a, **kw):   # the other job finishes while this one undistorts
        real(out_dir, *a, **kw)
        if not first:
            first["busy"] = True   # the other job's own undistortion runs as it is
            first["dir"] = load_scene(root).image_dir.parent
            (first["dir"] / "reading").write_text("the other job's")
    monkeypatch.setattr(pycolmap, "undistort_images", beside)
    key = colmap._cache_key(find_model_dir(root), root / "images", sorted(p.name for p in (root / "images").iterdir()))
    (root / ".recgs_cache").mkdir()
    mine = colmap._undistort(find_model_dir(root), root / "images",
                             sorted(p.name for p in (root / "images").iterdir()), root / ".recgs_cache")
    assert mine == first["dir"] == root / ".recgs_cache" / f"undistorted-{key}"
    assert (mine / "reading").read_text() == "the other job's" and (mine / "sparse" / "points3D.bin").is_file()
    assert [p.name for p in (root / ".recgs_cache").iterdir()] == [mine.name]   # nothing left behind
    # a broken leftover (no done mark) is replaced
    (mine / "done").unlink()
    monkeypatch.setattr(pycolmap, "undistort_images", real)
    again = load_scene(root)
    assert (again.image_dir.parent / "done").is_file() and not (again.image_dir.parent / "reading").exists()


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

    from recgs_addon.core.io.colmap_checks import _MODEL_NUM_PARAMS

    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name != "INVALID":
            cam = pycolmap.Camera.create_from_model_name(1, name, 60.0, 64, 48)
            assert _MODEL_NUM_PARAMS[mid.value] == len(cam.params), name


def test_opencv_binary_cameras_bin_passes_structural_check(tmp_path):
    write_colmap_scene(tmp_path / "s", model="OPENCV")
    from recgs_addon.core.io.colmap_checks import ModelIndex, _cameras_bin

    _cameras_bin(tmp_path / "s/sparse/0/cameras.bin", ModelIndex(".bin"))


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
    assert "frames.bin: frame 1" in str(e.value)   # where pycolmap takes the pose from
    for name in ("frames.bin", "rigs.bin"):         # a model from before COLMAP 3.12: images.bin holds it
        (root / "sparse" / "0" / name).unlink()
    with pytest.raises(SceneError, match=r"images.bin: image 1 \('img_000.png'\) has a pose with NaN"):
        load_scene(root)


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


# --- what the outside trial found: each a clear error naming the file and record at fault ---------
# (pycolmap reads some of these silently, and refuses the others with its internal check
# messages, naming no file: "Check failed: frame->HasDataId(DataId())", "unordered_map::at")

import struct  # noqa: E402


def _patch(path, offset, fmt, *values):
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


def _first_2d_point_id_offset(images_bin):
    data = images_bin.read_bytes()
    return data.index(b"img_000.png\0") + len(b"img_000.png\0") + 8 + 16   # n2d, then x y of the first


BINARY_BREAKS = {  # case -> (how to break sparse/0, the error)
    "image names a missing camera": (lambda m: _patch(m / "images.bin", 8 + 60, "<I", 7),
                                     r"images.bin: image 1 \('img_000.png'\) names camera 7, which cameras.bin does not have"),
    "legacy: image names a missing camera": (
        lambda m: ((m / "rigs.bin").unlink(), (m / "frames.bin").unlink(), _patch(m / "images.bin", 8 + 60, "<I", 7)),
        r"images.bin: image 1 \('img_000.png'\) names camera 7, which cameras.bin does not have"),
    "frame names a missing rig": (lambda m: _patch(m / "frames.bin", 8 + 4, "<I", 9),
                                  "frames.bin: frame 1 names rig 9, which rigs.bin does not have"),
    "frame names a missing image": (lambda m: _patch(m / "frames.bin", 8 + 68 + 8, "<Q", 99),
                                    "frames.bin: frame 1 names image 99, which images.bin does not have"),
    "rig names a missing camera": (lambda m: _patch(m / "rigs.bin", 8 + 12, "<I", 5),
                                   "rigs.bin: rig 1 names camera 5, which cameras.bin does not have"),
    "zero rotation in frames.bin": (lambda m: _patch(m / "frames.bin", 8 + 8, "<4d", 0, 0, 0, 0),
                                    r"frames.bin: frame 1 \('img_000.png'\) has a rotation quaternion of length 0"),
    "legacy: zero rotation in images.bin": (
        lambda m: ((m / "rigs.bin").unlink(), (m / "frames.bin").unlink(), _patch(m / "images.bin", 8 + 4, "<4d", 0, 0, 0, 0)),
        r"images.bin: image 1 \('img_000.png'\) has a rotation quaternion of length 0"),
    "two frames name one image": (lambda m: _patch(m / "frames.bin", 8 + 68 + 8, "<Q", 2),
                                  r"frames.bin: frame 2 names image 2 \('img_001.png'\), which frame 1 names too"),
    "track names a missing image": (lambda m: _patch(m / "points3D.bin", 8 + 51, "<I", 999),
                                    "points3D.bin: 3D point 1's track names image 999, which images.bin does not have"),
    "observation names a missing point": (
        lambda m: _patch(m / "images.bin", _first_2d_point_id_offset(m / "images.bin"), "<q", 10 ** 9),
        r"images.bin: image 1 \('img_000.png'\) observes 3D point 1000000000, which points3D.bin does not have"),
    "track and observation disagree": (
        lambda m: _patch(m / "images.bin", _first_2d_point_id_offset(m / "images.bin"), "<q", 2),
        r"points3D.bin: 3D point 1's track says image 1 \('img_000.png'\) saw it as 2D point 0, but images.bin "
        "gives that 2D point to 3D point 2"),
}


@pytest.mark.parametrize("case", sorted(BINARY_BREAKS))
def test_binary_model_references_and_rotations(tmp_path, case):
    root = tmp_path / "survey"
    write_colmap_scene(root, n_images=3, n_points=30)
    breaker, message = BINARY_BREAKS[case]
    breaker(root / "sparse" / "0")
    with pytest.raises(SceneError, match=message) as e:
        load_scene(root)
    assert str(root / "sparse" / "0") in str(e.value) and "Check failed" not in str(e.value)


def _edit_line(path, first_token, edit):
    """Replace the data line of ``path`` whose first token is ``first_token`` by ``edit(tokens)``."""
    lines = path.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln and not ln.startswith("#") and ln.split()[0] == first_token)
    lines[i] = " ".join(edit(lines[i].split()))
    path.write_text("\n".join(lines) + "\n")


def _set(i, value):
    def edit(tok):
        tok[i] = value
        return tok
    return edit


TEXT_BREAKS = {
    "image names a missing camera": (lambda m: _edit_line(m / "images.txt", "1", _set(8, "7")),
                                     r"images.txt: line 5: image 1 \('img_000.png'\) names camera 7, which cameras.txt"),
    "unknown camera model": (lambda m: _edit_line(m / "cameras.txt", "1", _set(1, "FANCY_LENS")),
                             "cameras.txt: line 4: camera 1 uses the unknown camera model 'FANCY_LENS'"),
    "NaN focal length": (lambda m: _edit_line(m / "cameras.txt", "1", _set(4, "nan")),
                         "cameras.txt: line 4: camera 1 has parameters that are NaN or infinite"),
    "wrong parameter count": (lambda m: _edit_line(m / "cameras.txt", "1", lambda t: t + ["0.1"]),
                              "cameras.txt: line 4: camera 1 has 5 parameters; the PINHOLE model has 4"),
    "NaN pose in images.txt": (lambda m: _edit_line(m / "images.txt", "1", _set(5, "nan")),
                               r"images.txt: line 5: image 1 \('img_000.png'\) has a pose with NaN or infinite"),
    "NaN pose in frames.txt": (lambda m: _edit_line(m / "frames.txt", "1", _set(7, "inf")),
                               r"frames.txt: line 4: frame 1 \('img_000.png'\) has a pose with NaN or infinite"),
    "zero rotation in frames.txt": (lambda m: _edit_line(m / "frames.txt", "1", lambda t: t[:2] + ["0"] * 4 + t[6:]),
                                    r"frames.txt: line 4: frame 1 \('img_000.png'\) has a rotation quaternion of length 0"),
    "NaN 3D point": (lambda m: _edit_line(m / "points3D.txt", "1", _set(2, "nan")),
                     "points3D.txt: line 4: 3D point 1 has NaN or infinite coordinates"),
    "points3D.txt cut short": (
        lambda m: (m / "points3D.txt").write_text("\n".join((m / "points3D.txt").read_text().splitlines()[:14]) + "\n"),
        "points3D.txt: its points' tracks hold 33 observations but images.txt lists 90: points are missing"),
    "points3D.txt cut inside a line": (
        lambda m: (m / "points3D.txt").write_text((m / "points3D.txt").read_text()[:1200]),
        "points3D.txt: line 15 is not a 3D point"),
    "images.txt without its last points line": (
        lambda m: (m / "images.txt").write_text("\n".join((m / "images.txt").read_text().splitlines()[:-1]) + "\n"),
        r"images.txt: line 9: image 3 \('img_002.png'\) has no line of 2D points after it"),
    "frame names a missing image": (lambda m: _edit_line(m / "frames.txt", "1", _set(12, "99")),
                                    "frames.txt: line 4: frame 1 names image 99, which images.txt does not have"),
    "a frame's line lost": (lambda m: _edit_line(m / "frames.txt", "1", lambda t: ["#"] + t),
                            r"images.txt: line 5: image 1 \('img_000.png'\) is in no frame of frames.txt"),
    "a rig without its camera": (lambda m: _edit_line(m / "rigs.txt", "1", lambda t: ["1", "0"]),
                                 "frames.txt: line 4: frame 1 names camera 1, which its rig 1 in rigs.txt does not have"),
    "an unknown sensor type": (lambda m: _edit_line(m / "rigs.txt", "1", _set(2, "LIDAR")),
                               "rigs.txt: line 4 is not a rig .*sensor 1 is not SENSOR_TYPE"),
    "a frame's data id not a number": (lambda m: _edit_line(m / "frames.txt", "1", _set(12, "x")),
                                       "frames.txt: line 4 is not a frame .*data id 1 is not SENSOR_TYPE"),
    "a colour that is not a number": (lambda m: _edit_line(m / "points3D.txt", "1", _set(5, "x")),
                                      "points3D.txt: line 4 is not a 3D point"),
    "a NaN 2D point": (lambda m: (m / "images.txt").write_text(
        (m / "images.txt").read_text().replace("\n3", "\nnan", 1)),
                       "images.txt: line 6 is not a line of 2D points .* for image 1"),
}


@pytest.mark.parametrize("case", sorted(TEXT_BREAKS))
def test_text_model_values_and_references(tmp_path, case):
    root = tmp_path / "survey"
    write_colmap_scene(root, n_images=3, n_points=30, binary=False)
    breaker, message = TEXT_BREAKS[case]
    breaker(root / "sparse" / "0")
    with pytest.raises(SceneError, match=message) as e:
        load_scene(root)
    assert "Check failed" not in str(e.value)


def test_a_file_or_a_folder_where_the_other_belongs(tmp_path, colmap_scene):
    root, _ = colmap_scene
    (tmp_path / "survey.txt").write_text("not a folder")
    with pytest.raises(SceneError, match="survey.txt: is a file, not a folder"):
        load_scene(tmp_path / "survey.txt")
    image = root / "images" / "img_001.png"
    image.unlink()
    image.mkdir()
    with pytest.raises(SceneError, match="img_001.png: is a folder, not an image file"):
        load_scene(root)
