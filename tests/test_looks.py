"""Look frames (core/io/looks.py): reading looks.json, placing each frame between the
keyframes, and the pose interpolation it uses (core/model/cameras.py)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from recgs_addon.core.errors import SceneError
from recgs_addon.core.io.images import write_image
from recgs_addon.core.io.looks import place_looks, read_looks
from recgs_addon.core.model.cameras import (Camera, interpolate_pose, quat_to_rotmat, rotmat_to_quat, slerp)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def angle_between(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1)))


def test_slerp_halves_a_rotation_and_takes_the_shorter_arc():
    q0, q1 = rotmat_to_quat(np.eye(3)), rotmat_to_quat(rot_z(1.2))
    assert angle_between(quat_to_rotmat(slerp(q0, q1, 0.5)), rot_z(0.6)) < 1e-9
    assert angle_between(quat_to_rotmat(slerp(q0, -q1, 0.25)), rot_z(0.3)) < 1e-9   # -q is the same rotation
    assert angle_between(quat_to_rotmat(slerp(q0, q1, 0.0)), np.eye(3)) < 1e-6
    tiny = rotmat_to_quat(rot_z(1e-5))   # nearly equal: the chord, still a unit quaternion
    assert abs(np.linalg.norm(slerp(q0, tiny, 0.5)) - 1) < 1e-12


def test_interpolated_pose_moves_the_centre_on_a_line_and_turns_steadily():
    R0, R1 = rot_z(0.0), rot_z(0.8)
    c0, c1 = np.array([0.0, 0.0, 2.0]), np.array([1.0, 0.5, 2.2])
    R, t = interpolate_pose(R0, -R0 @ c0, R1, -R1 @ c1, 0.25)
    assert np.allclose(-R.T @ t, 0.75 * c0 + 0.25 * c1)
    assert angle_between(R, rot_z(0.2)) < 1e-9


def keyframe(name: str, R: np.ndarray, centre) -> Camera:
    return Camera(name, 64, 48, 60.0, 60.0, 32.0, 24.0, R, -R @ np.asarray(centre, float), 1, 1)


def write_looks(scene, entries, images=None):
    (scene / "looks").mkdir(parents=True, exist_ok=True)
    for e in entries if images is None else images:
        write_image(scene / "looks" / e["name"], np.zeros((48, 64, 3), np.float32))
    (scene / "looks.json").write_text(json.dumps({"fps": 12.0, "looks": entries}))


def test_looks_are_read_in_time_order_with_their_poses_and_missing_images_counted(tmp_path):
    q = rotmat_to_quat(rot_z(0.3)).tolist()
    entries = [{"name": "b.png", "time_s": 2.0}, {"name": "a.png", "time_s": 1.0, "qvec": q, "tvec": [1, 2, 3]},
               {"name": "gone.png", "time_s": 1.5}]
    write_looks(tmp_path, entries, images=entries[:2])
    found = read_looks(tmp_path)
    assert [lk.name for lk in found.looks] == ["a.png", "b.png"]
    assert found.listed == 3 and found.missing == ["gone.png"] and found.fps == 12.0
    assert found.looks[0].posed and angle_between(found.looks[0].R, rot_z(0.3)) < 1e-9
    assert np.allclose(found.looks[0].t, [1, 2, 3]) and not found.looks[1].posed
    assert read_looks(tmp_path / "nothing") is None


@pytest.mark.parametrize("bad, says", [
    ("{not json", "cannot read the look frames"),
    (json.dumps({"frames": []}), "cannot read the look frames"),
    (json.dumps({"looks": [{"name": "a.png"}]}), "needs a name and a time_s"),
    (json.dumps({"looks": [{"name": "a.png", "time_s": "NaN"}]}), "no finite time_s"),
    (json.dumps({"looks": [{"name": "a.png", "time_s": 1, "qvec": [1, 0, 0, 0]}]}), "both qvec and tvec"),
    (json.dumps({"looks": [{"name": "a.png", "time_s": 1, "qvec": [2, 0, 0, 0], "tvec": [0, 0, 0]}]}),
     "no unit quaternion"),
])
def test_a_bad_looks_file_is_an_error_naming_it(tmp_path, bad, says):
    (tmp_path / "looks.json").write_text(bad)
    with pytest.raises(SceneError) as e:
        read_looks(tmp_path)
    assert "looks.json" in str(e.value) and says in str(e.value)


def test_looks_are_placed_between_the_keyframes_around_them(tmp_path):
    keys = [keyframe("k0.png", rot_z(0.0), [0, 0, 2]), keyframe("k1.png", rot_z(0.4), [1, 0, 2]),
            keyframe("k2.png", rot_z(0.4), [9, 0, 2])]
    times = [0.0, 0.5, 4.0]   # k1 to k2: too far apart in time to place a frame between them
    R_given = rot_z(1.0)
    entries = [{"name": "l1.png", "time_s": 0.125}, {"name": "l2.png", "time_s": 2.0},
               {"name": "l3.png", "time_s": 3.0, "qvec": rotmat_to_quat(R_given).tolist(), "tvec": [0, 0, 1]},
               {"name": "l0.png", "time_s": -1.0}]
    write_looks(tmp_path, entries)
    placed, counts = place_looks(read_looks(tmp_path).looks, keys, times)
    assert counts == {"given": 1, "interpolated": 1, "unplaced": 2}
    by = {lk.name: (cam, k) for lk, cam, k in placed}
    cam, k = by["l1.png"]
    assert k == 0 and np.allclose(cam.center, [0.25, 0, 2]) and angle_between(cam.R, rot_z(0.1)) < 1e-9
    assert (cam.width, cam.fx) == (64, 60.0)
    cam, k = by["l3.png"]
    assert k == 2 and angle_between(cam.R, R_given) < 1e-9 and np.allclose(cam.t, [0, 0, 1])


@pytest.mark.parametrize("model", ["PINHOLE", "OPENCV"])
def test_a_look_frame_is_read_as_the_keyframes_are_undistorted(tmp_path, model):
    """A look frame that is a copy of a keyframe's photo (at twice its size) comes back as that
    keyframe's image in the job: undistorted by pycolmap as the keyframes' cache was, at the
    keyframe camera's size."""
    import shutil

    from conftest import write_colmap_scene
    from recgs_addon.core.io.colmap import load_scene
    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.io.looks import look_reader

    root = tmp_path / "s"
    write_colmap_scene(root, model=model, width=96, height=72)
    scene = load_scene(root)
    cam = scene.cameras[1]
    (root / "looks").mkdir()
    big = read_image(root / "images" / cam.name, size=(192, 144))
    write_image(root / "looks" / "l.png", big)
    shutil.copy(root / "images" / cam.name, root / "looks" / "same.png")
    (root / "looks.json").write_text(json.dumps({"looks": [{"name": "l.png", "time_s": 1.0},
                                                           {"name": "same.png", "time_s": 2.0}]}))
    looks = {lk.name: lk for lk in read_looks(root).looks}
    read = look_reader(root, scene.undistorted)
    want = scene.load_image(cam)
    same = read(looks["same.png"], cam)
    assert same.shape == want.shape
    assert np.abs(same - want).mean() < 0.01
    got = read(looks["l.png"], cam)

    def coarse(a):   # 4 x 4 block means: the photos are noise-like texture, resampled twice here
        h, w = a.shape[0] // 4 * 4, a.shape[1] // 4 * 4
        return a[:h, :w].reshape(h // 4, 4, w // 4, 4, 3).mean((1, 3))
    assert np.abs(coarse(got) - coarse(want))[1:-1, 1:-1].mean() < 0.03, np.abs(coarse(got) - coarse(want)).mean()
    shifted = np.roll(want, 3, axis=1)   # what the check tells from: a frame 3 pixels off
    assert np.abs(coarse(shifted) - coarse(want))[1:-1, 1:-1].mean() > 0.03


def test_posed_looks_of_a_survey_without_times_take_the_nearest_keyframe(tmp_path):
    keys = [keyframe("k0.png", rot_z(0.0), [0, 0, 2]), keyframe("k1.png", rot_z(0.0), [3, 0, 2])]
    R = rot_z(0.1)
    entries = [{"name": "p.png", "time_s": 0.0, "qvec": rotmat_to_quat(R).tolist(), "tvec": (-R @ [2.5, 0, 2]).tolist()},
               {"name": "q.png", "time_s": 0.0}]
    write_looks(tmp_path, entries)
    placed, counts = place_looks(read_looks(tmp_path).looks, keys, [None, None])
    assert counts == {"given": 1, "interpolated": 0, "unplaced": 1}
    assert placed[0][2] == 1 and np.allclose(placed[0][1].center, [2.5, 0, 2])
