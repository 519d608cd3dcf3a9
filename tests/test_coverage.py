"""Views and passes per seabed point (core/train/coverage.py) and the frames' times they read
(core/io/frames.py)."""
import json

import numpy as np
import pytest

from conftest import write_rendered_scene
from recgs_addon.core.errors import SceneError
from recgs_addon.core.io.frames import read_frame_times, write_frame_times
from recgs_addon.core.train.config import preset
from recgs_addon.core.train.coverage import looks_of, passes_of, sparse_coverage, surface_coverage
from recgs_addon.core.train.trainer import make_trainer


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("coverage") / "scene"
    write_rendered_scene(root, n_views=8, width=40, height=30, n_gauss=300)
    return root


def test_frames_close_in_time_count_once_a_second():
    seen = np.array([[1, 1, 1, 1, 0, 1, 1],   # 0.0-1.2 s: two a second apart; 9.0-9.3 s: one
                     [1, 0, 0, 0, 0, 0, 1],   # two frames far apart: two
                     [0, 0, 0, 0, 1, 0, 0]], bool)
    times = np.array([0.0, 0.3, 0.6, 1.2, 5.0, 9.0, 9.3])
    assert passes_of(seen, times).tolist() == [3, 2, 1]
    assert passes_of(seen, None).tolist() == [6, 2, 1]        # photos: each counts


def test_frame_times_round_trip_and_a_bad_file_is_named(tmp_path):
    assert read_frame_times(tmp_path) is None
    write_frame_times(tmp_path, {"b.png": 0.5, "a.png": 0.0}, fps=2.0)
    doc = json.loads((tmp_path / "frames.json").read_text())
    assert [f["name"] for f in doc["frames"]] == ["a.png", "b.png"] and doc["fps"] == 2.0
    assert read_frame_times(tmp_path) == {"a.png": 0.0, "b.png": 0.5}
    (tmp_path / "frames.json").write_text('{"frames": [{"name": "a.png"}]}')
    with pytest.raises(SceneError, match="frames.json: cannot read the frames' times"):
        read_frame_times(tmp_path)


def test_sparse_and_surface_coverage_count_the_views_that_see_a_point(scene, tmp_path):
    tr = make_trainer(scene, preset("default", holdout_every=0, compiled=False))
    data = tr.data
    sparse = sparse_coverage(data)
    # by hand: the sparse points inside each camera's image
    counts = np.zeros(len(data.scene.points), int)
    for cam in data.scene.cameras:
        uv, z = cam.project(data.scene.points)
        counts += (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert sparse.median_views == float(np.median(counts[counts > 0]))
    assert sparse.median_passes == sparse.median_views          # no frame times: every photo a pass
    assert sum(sparse.histogram) == sparse.points == int((counts > 0).sum())
    surface = surface_coverage(tr)                                  # the model's own surface
    assert surface.points > 0 and 1 <= surface.median_views <= len(data.train_ids)
    assert abs(surface.median_views - sparse.median_views) <= 2
    # the same views, filmed as one burst: every point is one pass
    import shutil
    burst = tmp_path / "burst"
    shutil.copytree(scene, burst)
    write_frame_times(burst, {c.name: 0.1 * k for k, c in enumerate(sorted(data.scene.cameras, key=lambda c: c.name))})
    b = sparse_coverage(make_trainer(burst, preset("default", holdout_every=0, compiled=False)).data)
    assert b.median_views == sparse.median_views and b.median_passes == 1


def test_looks_count_frames_by_how_much_light_they_share():
    rng = np.random.default_rng(0)
    seen = rng.random((40, 15)) < 0.5
    times = np.sort(rng.random(15) * 6)
    rho = np.exp(-np.abs(times[:, None] - times[None, :]) / 0.7)       # the light's correlation
    brute = [np.linalg.solve(rho[np.ix_(s, s)], np.ones(s.sum())).sum() if s.any() else 0.0 for s in seen]
    assert np.allclose(looks_of(seen, times, 0.7), brute, rtol=1e-5)
    assert np.array_equal(looks_of(seen, None), seen.sum(1))           # photos: each a look
    video = np.ones((1, 30), bool)                                     # 10 s at 3 frames a second
    assert 7 < looks_of(video, np.arange(30) / 3.0)[0] < 13            # about one look a second
