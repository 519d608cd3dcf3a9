"""Tests for tools/make_survey.py (synthetic seafloor survey generator) and its caustic model
(tools/survey_light.py).

The caustic maths test is fast (numpy only). The end-to-end test renders a tiny survey with
Blender (bpy) and is marked ``slow``.
"""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "make_survey.py"


def _load_module():
    spec = importlib.util.spec_from_file_location("make_survey", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses need the module registered
    spec.loader.exec_module(mod)  # does not import bpy (imported lazily by the Blender parts)
    return mod


ms = _load_module()
import survey_light as light  # noqa: E402  (make_survey puts tools/ on sys.path)


@pytest.mark.parametrize("kind", light.CAUSTIC_PATTERNS)
def test_caustic_gain_maths(kind):
    res, seed = 64, 4
    shots = light.caustic_shots(3, seed=seed, dt=1.0)
    gains = [light.caustic_gain(kind, res, s["time_s"], s["offset"], seed=seed, strength=0.6) for s in shots]
    for g in gains:
        assert g.dtype == np.float32 and g.shape == (res, res)
        assert abs(g.astype(np.float64).mean() - 1.0) < 1e-6      # redistributes light, adds none
        assert g.min() >= 0.0
        assert g.max() > 1.5                                      # has bright caustic ridges
    # every shot sees a different pattern
    assert not np.allclose(gains[0], gains[1], atol=1e-3)
    assert not np.allclose(gains[1], gains[2], atol=1e-3)
    # deterministic
    again = light.caustic_gain(kind, res, shots[1]["time_s"], shots[1]["offset"], seed=seed, strength=0.6)
    assert np.array_equal(again, gains[1])
    # full strength still non-negative with mean 1
    full = light.caustic_gain(kind, res, 0.5, (0.1, 0.7), seed=seed, strength=1.0)
    assert full.min() >= 0.0 and abs(full.astype(np.float64).mean() - 1.0) < 1e-6
    # strength 0: no caustics at all
    assert np.array_equal(light.caustic_gain(kind, res, 0.5, (0.1, 0.7), seed=seed, strength=0.0),
                          np.ones((res, res), np.float32))
    with pytest.raises(ValueError):
        light.caustic_gain(kind, res, 0.0, strength=1.5)
    # the texture tiles: an offset of whole tiles gives the same pattern
    a = light.caustic_pattern(kind, res, 0.3, (0.25, 0.5), seed)
    b = light.caustic_pattern(kind, res, 0.3, (1.25, -0.5), seed)
    assert np.allclose(a, b, atol=1e-6)
    assert abs(a.mean() - 1.0) < 1e-9 and a.min() >= 0.0


def test_linear_to_srgb8():
    v = ms.linear_to_srgb8(np.array([0.0, 0.0031308, 0.18, 1.0, 2.0, -1.0]))
    assert v.dtype == np.uint8
    assert list(v) == [0, 10, 118, 255, 255, 0]


def test_the_burned_in_time_stamp_is_steady_but_for_its_seconds():
    """The overlay the generator burns in: the same pixels every shot but the seconds' digits,
    in the top-left corner, and the found overlay (core/train/overlay.py) covers it whole."""
    import torch
    from recgs_addon.core.train.overlay import find_overlay

    rng = np.random.default_rng(0)
    base = rng.integers(30, 220, (240, 960, 3), dtype=np.uint8)
    frames, stamps = [], []
    for t in range(12):
        img = base[:, 12 * t:12 * t + 320].copy()
        ms.burn_time_stamp(img, 0.5 * t)
        stamps.append(img[:16, :100].copy())
        frames.append(torch.tensor(img.mean(-1) / 255.0, dtype=torch.float32))
    assert all(np.array_equal(stamps[0][1:8, 1:70], s[1:8, 1:70]) for s in stamps)   # the date, hours, minutes
    assert not np.array_equal(stamps[0], stamps[2])                              # the seconds change
    found = find_overlay(frames)
    assert found.mask is not None and bool(found.mask[1:12, 1:80].all()) and found.share < 0.05, found.reason


@pytest.mark.slow
@pytest.mark.blender
def test_a_tiled_glossy_floor_seen_forward(tmp_path):
    """The hard cases' options render: tiles, gloss, a forward pitch, the stamp in images/ only."""
    pytest.importorskip("bpy")
    oiio = pytest.importorskip("OpenImageIO")
    out = tmp_path / "tiles"
    cmd = [sys.executable, str(SCRIPT), "--out", str(out), "--views", "4", "--width", "96", "--height", "72",
           "--seed", "3", "--samples", "2", "--points", "600", "--floor", "tiles", "--gloss", "0.7", "--pitch", "45",
           "--overlay"]
    subprocess.run(cmd, check=True, cwd=ROOT, timeout=600)
    a = oiio.ImageBuf(str(out / "images" / "view_000.png")).get_pixels(oiio.UINT8)
    b = oiio.ImageBuf(str(out / "clean" / "view_000.png")).get_pixels(oiio.UINT8)
    assert (a[2:12, 2:40] == 235).any() and not (b[2:12, 2:40] == 235).all()
    assert json.loads((out / "survey.json").read_text())["parameters"]["floor"] == "tiles"


@pytest.mark.slow
@pytest.mark.blender
def test_tiny_survey_end_to_end(tmp_path):
    pytest.importorskip("bpy")
    pycolmap = pytest.importorskip("pycolmap")
    oiio = pytest.importorskip("OpenImageIO")
    out = tmp_path / "survey"
    cmd = [sys.executable, str(SCRIPT), "--out", str(out), "--views", "4", "--width", "64", "--height", "48",
           "--seed", "3", "--samples", "4", "--points", "600", "--point-noise", "0"]
    subprocess.run(cmd, check=True, cwd=ROOT, timeout=600)

    names = [f"view_{i:03d}.png" for i in range(4)]
    for sub in ("images", "clean"):
        for n in names:
            assert (out / sub / n).is_file()
    for f in ("sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin", "survey.json", "README.md"):
        assert (out / f).is_file(), f

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == 4 and rec.num_points3D() > 50
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (64, 48)
    fx, fy, cx, cy = cam.params
    assert fx == pytest.approx(fy) and (cx, cy) == (32.0, 24.0)
    assert sorted(im.name for im in rec.images.values()) == names

    # every observation is the exact projection of its (noise-free) point
    n_obs = 0
    for im in rec.images.values():
        for p2 in im.points2D:
            if not p2.has_point3D():
                continue
            uv = im.project_point(rec.points3D[p2.point3D_id].xyz)
            assert uv is not None
            assert np.linalg.norm(np.asarray(uv) - p2.xy) < 0.05
            n_obs += 1
    assert n_obs >= 2 * rec.num_points3D()
    assert all(p.track.length() >= 2 for p in rec.points3D.values())

    # caustics visible: images/ differ from clean/
    diffs = []
    for n in names:
        a = oiio.ImageBuf(str(out / "images" / n)).get_pixels(oiio.UINT8).astype(float)
        b = oiio.ImageBuf(str(out / "clean" / n)).get_pixels(oiio.UINT8).astype(float)
        assert a.shape == b.shape == (48, 64, 3)
        diffs.append(np.abs(a - b).mean())
    assert min(diffs) > 2.0

    meta = json.loads((out / "survey.json").read_text())
    shots = meta["caustics"]["shots"]
    assert len(shots) == 4
    for s in shots:
        assert abs(s["mean_gain"] - 1.0) < 1e-3
        assert s["min_gain"] >= 0.0
    assert len({tuple(s["offset"]) for s in shots}) == 4
    assert meta["intrinsics"]["cx"] == 32.0 and meta["intrinsics"]["cy"] == 24.0


def test_run_sfm_uses_core_sfm(tmp_path):
    """--sfm goes through recgs_addon.core.capture.sfm: six sample views register, poses match the truth."""
    pycolmap = pytest.importorskip("pycolmap")
    sample = ROOT / "data" / "sample"
    (tmp_path / "images").mkdir()
    for i in range(6):
        (tmp_path / "images" / f"view_{i:03d}.png").write_bytes((sample / "images" / f"view_{i:03d}.png").read_bytes())
    res = ms.run_sfm(tmp_path, pycolmap.Reconstruction(str(sample / "sparse" / "0")), threads=2)
    assert res["images"] == 6 and res["registered"] >= 3
    assert res["mean_reprojection_error_px"] < 1.0
    assert res["median_position_error_m"] < 0.05  # after the similarity alignment
    assert (tmp_path / "sfm" / "0" / "images.bin").is_file()
    assert not [p for p in (tmp_path / "sfm").iterdir() if p.name != "0"]
