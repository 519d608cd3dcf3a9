"""What light a survey shows (core/caustics/light.py), on surveys made here: a textured flat
seabed seen from above along two overlapping rows, lit by moving caustics, by a lamp on the
camera (a cone fixed in the image and an inverse-square fall-off), by changes of exposure, or
evenly. Only the moving light is caustics."""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from recgs_addon.core.caustics import light
from recgs_addon.core.model.cameras import Camera

W, H, F = 160, 120, 140.0
ALTITUDE = 2.5


def _texture(x, y):
    """The seabed's grey level at world (x, y): sand ripples and pebbles, in (0.2, 0.8)."""
    t = (0.5 + 0.12 * np.sin(7.0 * x + 2 * np.sin(3 * y)) + 0.1 * np.sin(11.0 * y + 1.3)
         + 0.08 * np.sin(23 * x) * np.cos(19 * y))
    return np.clip(t, 0.2, 0.8)


def _caustic(x, y, phase):
    """A caustic gain at world (x, y): bright thin lines over a dimmer floor, mean about 1."""
    a = np.abs(np.sin(7.0 * x + phase[0] + 1.5 * np.sin(5.0 * y + phase[1])))
    b = np.abs(np.sin(7.0 * y + phase[2] + 1.5 * np.sin(5.0 * x + phase[3])))
    lines = np.exp(-8 * a) + np.exp(-8 * b)
    return 0.55 + 1.6 * lines


def _relief(x, y):
    """Rocks standing out of the seabed (metres): what the flat sparse points below miss."""
    return 0.35 * np.exp(-((np.sin(2.1 * x) + np.cos(1.7 * y)) ** 2)) * np.cos(3.1 * x) ** 2


def survey(kind: str, n: int = 24, seed: int = 0, noise: float = 0.0):
    """A duck-typed ``TrainData`` of ``n`` frames along two rows, with frame times 0.5 s apart.
    ``kind``: caustics | lamp | exposure | even | relief (rocks the sparse points, all on the
    flat seabed, do not show: the warps land off by the rocks' parallax). ``noise``: the
    photos' own noise, independent in every channel (sRGB levels of 1)."""
    rng = np.random.default_rng(seed)
    cams, photos, times = [], [], {}
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    for i in range(n):
        row, k = divmod(i, n // 2)
        cx = -1.2 + 2.4 * k / (n // 2 - 1) if row == 0 else 1.2 - 2.4 * k / (n // 2 - 1)
        cy = -0.45 + 0.9 * row
        z = ALTITUDE + 0.1 * np.sin(i)
        R = np.diag([1.0, -1.0, -1.0])        # looking straight down, image x along world x
        centre = np.array([cx, cy, z])
        t = -R @ centre
        name = f"f{i:03d}.png"
        cams.append(Camera(name, W, H, F, F, W / 2, H / 2, R, t))
        times[name] = 0.5 * i
        # the seabed point under each pixel (z = 0, or on the rocks)
        wx = cx + (u - W / 2) / F * z
        wy = cy - (v - H / 2) / F * z
        if kind == "relief":
            for _ in range(4):   # where the ray meets the rocks
                h = _relief(wx, wy)
                wx, wy = cx + (u - W / 2) / F * (z - h), cy - (v - H / 2) / F * (z - h)
        lin = _texture(wx, wy) ** 2.2
        if kind == "caustics":
            lin = lin * _caustic(wx, wy, rng.uniform(0, 2 * np.pi, 4))
        elif kind == "lamp":
            xn, yn = (u - W / 2) / (W / 2), (v - H / 2) / (W / 2)
            r = np.sqrt((u - W / 2) ** 2 + (v - H / 2) ** 2 + F ** 2) / F * z
            lin = lin * np.exp(-1.2 * ((xn - 0.2) ** 2 + (yn + 0.1) ** 2)) * (ALTITUDE / r) ** 2 * 1.4
        elif kind == "exposure":
            lin = lin * math.exp(rng.normal(0, 0.25))
        srgb = np.repeat((np.clip(lin, 0, 1) ** (1 / 2.2))[..., None], 3, -1)
        if noise:
            srgb = np.clip(srgb + rng.normal(0, noise, srgb.shape), 0, 1)
        photos.append(torch.tensor(srgb, dtype=torch.float32))
    gx, gy = np.meshgrid(np.linspace(-1.9, 1.9, 70), np.linspace(-1.3, 1.3, 50))
    points = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1).astype(np.float32)
    scene = SimpleNamespace(cameras=cams, points=points)
    return SimpleNamespace(scene=scene, train_ids=list(range(n)), photo=lambda i: photos[i],
                           camera=lambda i: cams[i]), times


@pytest.mark.parametrize("kind", ["caustics", "lamp", "exposure", "even"])
def test_only_light_that_moves_over_the_seabed_is_caustics(kind):
    data, times = survey(kind)
    f = light.survey_light(data, times=times)
    assert f.pairs >= 8
    assert f.caustics == (kind == "caustics"), f.reason
    if kind == "caustics":
        assert f.moving > 5 * light.MOVING_FLOOR and f.reason.startswith("caustics found")
    else:
        assert f.moving < light.MOVING_FLOOR and f.reason.startswith("no caustics found")
    if kind == "lamp":   # the camera's light is found and named; most of the difference is its
        assert f.camera > 0.2 and f.explained > 0.9 and "fixed to the camera" in f.reason
        assert f.range_slope < -1.0       # it falls with range
    if kind == "exposure":
        assert f.exposure > 0.1 and "exposure" in f.reason and f.camera < light.CAMERA_FLOOR
    if kind == "even":
        assert f.total < light.MOVING_FLOOR and f.camera < light.CAMERA_FLOOR


def test_misregistration_that_grows_with_the_baseline_is_not_caustics():
    """Rocks the sparse points miss: the warps land off by their parallax, so what differs
    between frames grows with the distance between the cameras; between frames taken from
    nearly the same place it is small, and no caustics are found, for that reason."""
    data, times = survey("relief")
    f = light.survey_light(data, times=times)
    assert not f.caustics, f.reason
    assert f.moving_far > light.GROWTH * f.moving and f.moving < f.floor
    assert "grows with the distance between the cameras" in f.decided_by and f.decided_by in f.reason


def test_the_noise_floor_is_measured_on_the_survey():
    """Noisy photos raise the floor (what the colour channels do not share, which sunlight does
    not make) above the fixed one: noise alone is not caustics, caustics under it still are."""
    noisy, times = survey("even", noise=0.06)
    f = light.survey_light(noisy, times=times)
    assert f.floor > 2 * light.MOVING_FLOOR and f.colour_noise > 0
    assert not f.caustics and f.moving < f.floor, f.reason
    lit, times = survey("caustics", noise=0.06)
    g = light.survey_light(lit, times=times)
    assert g.caustics and g.moving > g.floor, g.reason
    assert "above the noise measured on the survey's photos" in g.decided_by
    quiet, times = survey("even")
    assert light.survey_light(quiet, times=times).floor == light.MOVING_FLOOR   # grey, noise-free: the fixed floor


def test_the_fit_recovers_a_pattern_fixed_in_the_image():
    """Pairs made from a known pattern F: log(j / i) = F(x_j) - F(x_i) + an exposure; the fit
    gives F back (up to its constant) and leaves no residual. (Frames that only translate cannot
    tell a pattern's linear part from an exposure change: the pattern has none.)"""
    rng = np.random.default_rng(2)
    true = np.zeros(light.pattern_terms(np.zeros(1), np.zeros(1)).shape[-1])
    true[[2, 3, 4]] = [-0.5, 0.2, -0.4]           # x^2, xy, y^2
    samples = []
    for p in range(6):
        xi = rng.uniform(-1, 1, (2, 3000)) * [[1], [0.75]]
        xj = xi + rng.uniform(-0.4, 0.4, (2, 1))
        ri, rj = np.full(3000, 2.5), np.full(3000, 2.5)
        d = light.pattern_terms(*xj) @ true - light.pattern_terms(*xi) @ true + 0.1 * p
        samples.append(light.PairSamples(d, xi, xj, ri, rj, np.zeros(3000), np.arange(3000), (60, 50)))
    fit = light.fit_light(samples)
    grid = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 9), np.linspace(-0.4, 0.4, 7))).reshape(2, -1)
    got, want = light.pattern_terms(*grid) @ fit["pattern"], light.pattern_terms(*grid) @ true
    assert np.abs((got - got.mean()) - (want - want.mean())).max() < 0.02
    assert max(np.abs(r).max() for r in fit["residual"]) < 0.02
    assert np.allclose(np.diff(fit["exposure"]), 0.1, atol=0.01)


def test_too_few_overlapping_frames_is_said_not_guessed():
    data, times = survey("caustics", n=24)
    data.train_ids = [0]
    f = light.survey_light(data, times=times)
    assert not f.caustics and f.pairs == 0 and "too few overlapping frames" in f.reason
