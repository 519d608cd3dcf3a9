"""Light fixed to the camera (core/model/lamp.py, core/train/lamp.py): the gain's convention and
gradients, the lamp fitted to the sparse points, and training that models a lamp a survey shows."""
import math

import numpy as np
import pytest
import torch

from conftest import write_rendered_scene
from recgs_addon.core.caustics.build import make_method
from recgs_addon.core.caustics.config import CausticConfig
from recgs_addon.core.model.lamp import POWERS, TERMS, Lamp, fit_to_points, image_positions
from recgs_addon.core.train.config import TrainConfig, preset
from recgs_addon.core.train.losses import psnr

#: A lamp below the camera: brighter at the bottom of the frame, dark in the corners, inverse square.
PATTERN = [0.0, 0.5, -0.6, 0.0, -0.5] + [0.0] * (TERMS - 5)


def test_the_gain_is_one_at_the_centre_at_r0_and_follows_its_terms():
    lamp = Lamp(2.5, PATTERN, fall=-2.0, attenuation=0.1)
    x = torch.tensor([0.0, 0.5, -0.3, 0.0])
    y = torch.tensor([0.0, 0.2, 0.4, 0.0])
    r = torch.tensor([2.5, 3.0, 2.0, 5.0])
    got = lamp.log_gain_at(x, y, r)
    want = [sum(c * xi ** i * yi ** j for c, (i, j) in zip(PATTERN, POWERS)) - 2.0 * math.log(ri / 2.5) + 0.1 * (ri - 2.5)
            for xi, yi, ri in zip(x.tolist(), y.tolist(), r.tolist())]
    assert torch.allclose(got, torch.tensor(want, dtype=torch.float32), atol=1e-5)
    assert float(got[0]) == pytest.approx(0.0, abs=1e-7)
    # the image grid: centred on the principal point, in half-widths
    gx, gy = image_positions(40, 30, 20.0, 15.0)
    assert float(gx[15, 20]) == pytest.approx(0.5 / 20) and float(gx[0, -1]) == pytest.approx(39.5 / 20 - 1)
    assert float(gy[-1, 0]) == pytest.approx((29.5 - 15) / 20)
    assert Lamp.from_state(lamp.state_dict()).values() == lamp.values()


def test_the_gain_is_differentiable_in_its_terms():
    """Its gradient against central differences, in float64."""
    lamp = Lamp(2.0, PATTERN, fall=-1.5, attenuation=0.2)
    lamp.raw = torch.nn.Parameter(lamp.raw.detach().double())
    x, y = torch.rand(50, dtype=torch.float64) - 0.5, torch.rand(50, dtype=torch.float64) - 0.5
    r = 1.5 + torch.rand(50, dtype=torch.float64)
    w = torch.rand(50, dtype=torch.float64)

    def f():
        return (w * torch.exp(lamp.log_gain_at(x, y, r))).sum()
    f().backward()
    grad = lamp.raw.grad.clone()
    for k in range(len(grad)):
        with torch.no_grad():
            lamp.raw[k] += 1e-6
            up = float(f())
            lamp.raw[k] -= 2e-6
            down = float(f())
            lamp.raw[k] += 1e-6
        assert float(grad[k]) == pytest.approx((up - down) / 2e-6, rel=1e-5, abs=1e-8)


def _beam_observations(seed: int = 0, points: int = 800, views: int = 6, outliers: float = 0.05):
    """Sparse points' observations of a seabed under a narrow beam (the log gain falling by up
    to 6 at the frame's corners), its inverse square and a little attenuation, with noise and
    outliers (occlusions, misplaced points): ``(point, x, y, r, grey), lamp``."""
    rng = np.random.default_rng(seed)
    pattern = [0.0, 1.2, -3.5, 0.0, -3.2, 0.0, -0.4, 0.0, -0.3, 0.6, 0.0, 1.0, 0.0, 0.2]
    lamp = Lamp(2.5, pattern, fall=-2.0, attenuation=0.15)
    n = points * views
    point = np.repeat(np.arange(points), views)
    x, y = rng.uniform(-1, 1, n), rng.uniform(-0.75, 0.75, n)
    r = 2.5 * (1 + 0.25 * rng.uniform(-1, 1, n) + 0.2 * (x * x + y * y))   # relief, and longer rays at the edges
    with torch.no_grad():
        log_gain = lamp.log_gain_at(*(torch.from_numpy(a).float() for a in (x, y, r))).double().numpy()
    j = rng.uniform(0.05, 0.6, points)[point]
    grey = j * np.exp(log_gain + rng.normal(0, 0.02, n))
    bad = rng.random(n) < outliers
    grey[bad] *= rng.uniform(0.2, 3.0, int(bad.sum()))
    return (point, x, y, r, grey), lamp


def test_the_points_fit_recovers_a_narrow_beam():
    """The lamp fitted to the points' colours matches the true gain over the frame (within 0.03
    in log, where its darkest observations are 400 times darker than the centre's), through 5 %
    outliers; with too few observations there is no fit."""
    (point, x, y, r, grey), lamp = _beam_observations()
    fit = fit_to_points(point, x, y, r, grey, lamp.r0)
    assert fit is not None and fit["observations"] > 4000
    got = Lamp(lamp.r0, fit["pattern"], fit["fall"], fit["attenuation"])
    gx, gy = np.meshgrid(np.linspace(-0.95, 0.95, 9), np.linspace(-0.7, 0.7, 7))
    gx, gy = gx.ravel(), gy.ravel()
    for scale in (0.9, 1.0, 1.15):
        rr = 2.5 * scale * (1 + 0.2 * (gx * gx + gy * gy))
        args = [torch.from_numpy(a).float() for a in (gx, gy, rr)]
        with torch.no_grad():
            err = (got.log_gain_at(*args) - lamp.log_gain_at(*args)).abs().max()
        assert float(err) < 0.03, (scale, float(err))
    assert 0.015 < fit["spread"] < 0.04   # the points' noise, 0.02
    assert fit_to_points(point[:400], x[:400], y[:400], r[:400], grey[:400], lamp.r0) is None
    # the same points each seen once carry no ratio: no fit
    assert fit_to_points(np.arange(len(point)), x, y, r, grey, lamp.r0) is None


@pytest.fixture(scope="module")
def lamp_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("lamp") / "scene"
    # the camera rises and sinks: the fall-off with range is told from the pattern over the image
    heights = [2.0 + 1.0 * ((i * 5) % 12) / 11 for i in range(12)]
    write_rendered_scene(root, n_views=12, width=64, height=48, n_gauss=400, lamp=Lamp(2.5, PATTERN, fall=-2.0),
                         downward=True, heights=heights)
    return root


def _run(scene, lamp: str, steps: int = 400):
    cfg = preset("default", iterations=steps, eval_every=100, log_every=100, holdout_every=4, compiled=False,
                 densify_from=50, densify_every=50, densify_until=300, pyramid=(), lamp=lamp, medium="off")
    m = make_method(scene, cfg, CausticConfig(mode="3dgs"), gt_images="clean")
    m.run()
    return m


def test_training_models_a_lamp_the_survey_shows(lamp_scene):
    """auto finds the light fixed to the camera, models it, and the Gaussians come out evenly
    lit: held-out true-colour renders closer to the truth than a run that leaves the lamp in
    the colours, and the lamp's fall-off near the inverse square."""
    with_lamp = _run(lamp_scene, "auto")
    tr = with_lamp.trainer
    assert tr.lamp is not None and tr.lamp_info["kept"], tr.lamp_info
    assert tr.lamp_info["start_from"] == "points", tr.lamp_info   # the sparse points' fit started it
    start, end = tr.lamp_info["start"], tr.lamp.values()   # and training refined it
    assert abs(end["fall"] - start["fall"]) + abs(end["attenuation"] - start["attenuation"]) > 1e-3, (start, end)
    assert tr.light["camera"] > 0.15 and not tr.light["caustics"]
    without = _run(lamp_scene, "off")
    assert without.trainer.lamp is None
    score = lambda m: np.mean([psnr(m.trainer.render_view(i, seen=False).clamp(0, 1), m.data.gt_view(i))  # noqa: E731
                               for i in m.data.test_ids])
    assert score(with_lamp) > score(without) + 2.0, (score(with_lamp), score(without))
    assert -2.6 < tr.lamp.values()["fall"] + tr.lamp.values()["attenuation"] * tr.lamp.r0 < -1.4
    # the photos as the lamp lit them: the seen render matches them as well as the plain run's does
    seen = np.mean([psnr(tr.render_view(i).clamp(0, 1), tr.data.view(i)[1]) for i in tr.data.test_ids])
    assert seen > 20.0


def test_the_gaussians_start_evenly_lit_under_a_lamp(lamp_scene):
    """The Gaussians start from the sparse points' colours as the lamp's model holds the seabed
    (each point's pixels in the photos over the lamp's light there), not as the photos show it:
    under the lamp's dark corners those are a fraction of the centre's light, and Gaussians
    started from them leave the lamp to make up the difference at first."""
    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.model.colour import srgb_to_linear
    from recgs_addon.core.model.gaussians import sh_dc_to_rgb
    cfg = preset("default", iterations=1, compiled=False, pyramid=(), lamp="auto", medium="off")
    tr = make_method(lamp_scene, cfg, CausticConfig(mode="3dgs"), gt_images="clean").trainer
    assert tr.lamp is not None
    pts = np.asarray(tr.data.scene.points, np.float64)
    clean, lit, n = np.zeros((len(pts), 3)), np.zeros((len(pts), 3)), np.zeros(len(pts))
    for i in tr.data.train_ids:   # each point's colour in clean/ and in the photos, in linear light
        cam = tr.data.camera(i, 1)
        pc = pts @ cam.R.T + cam.t
        u, v = cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy
        seen = np.flatnonzero((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))
        at = (v[seen].astype(int), u[seen].astype(int))
        for acc, folder in ((clean, "clean"), (lit, "images")):
            img = read_image(lamp_scene / folder / cam.name, size=(cam.width, cam.height))
            acc[seen] += srgb_to_linear(torch.from_numpy(img[at])).numpy()
        n[seen] += 1
    # the Gaussians started from the points' true colours
    dc = sh_dc_to_rgb(tr.params["sh_dc"].detach()[:, 0].double().numpy())
    assert np.allclose(dc, tr.true_point_colours() / 255.0, atol=1e-6)
    seen = n > 0
    truth, as_lit = clean[seen] / n[seen, None], lit[seen] / n[seen, None]
    # the sparse model's colours as SfM gives them: the photos' (this scene's are the truth)
    from recgs_addon.core.model.colour import linear_to_srgb
    sfm = np.asarray(tr.data.scene.colors).copy()
    sfm[seen] = np.round(linear_to_srgb(torch.from_numpy(as_lit)).numpy() * 255)
    tr.data.scene.colors = sfm
    start = srgb_to_linear(torch.from_numpy(tr.true_point_colours() / 255.0)).numpy()[seen]
    err_start, err_lit = np.abs(start - truth).mean(), np.abs(as_lit - truth).mean()
    assert err_lit > 0.04, (err_start, err_lit)   # the lamp darkens the photos' corners
    assert err_start < 0.3 * err_lit and err_start < 0.02, (err_start, err_lit)
    # the photos decide the colour of a point they see, not the sparse model's colour
    again = tr.evened_point_colours(np.zeros((len(pts), 3), np.uint8))
    assert np.array_equal(again[seen], tr.evened_point_colours(sfm)[seen])
    # ... and without a lamp the colours are the sparse model's
    lamp, tr.lamp = tr.lamp, None
    assert np.array_equal(tr.true_point_colours(), sfm)
    tr.lamp = lamp


def test_the_oracle_colours_its_points_from_the_clean_photos(lamp_scene):
    """``oracle`` is 3DGS on the clean photos as if the survey had been solved from them: its
    sparse points take their colours from those photos, not from the photos as filmed (this
    scene's are lit by a lamp). Each point's colour is its pixels' mean in linear light."""
    from recgs_addon.core.io.colmap import load_scene
    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
    cfg = preset("default", iterations=1, compiled=False, pyramid=(), lamp="off", medium="off")
    data = make_method(lamp_scene, cfg, CausticConfig(mode="oracle"), gt_images="clean").trainer.data
    filed = np.asarray(load_scene(lamp_scene, check_images=False).colors)
    pts = np.asarray(data.scene.points, np.float64)
    acc, n = np.zeros((len(pts), 3)), np.zeros(len(pts))
    for i in data.train_ids:
        cam = data.camera(i, 1)
        pc = pts @ cam.R.T + cam.t
        u, v = cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy
        seen = np.flatnonzero((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))
        img = read_image(lamp_scene / "clean" / cam.name, size=(cam.width, cam.height))
        acc[seen] += srgb_to_linear(torch.from_numpy(img[v[seen].astype(int), u[seen].astype(int)])).numpy()
        n[seen] += 1
    seen = n > 0
    want = np.round(linear_to_srgb(torch.from_numpy(acc[seen] / n[seen, None])).numpy() * 255)
    assert seen.mean() > 0.5 and np.abs(data.scene.colors[seen].astype(float) - want).max() <= 1
    assert not np.array_equal(data.scene.colors, filed)   # not the sparse model's own colours
    assert np.array_equal(data.scene.colors[~seen], filed[~seen])


def test_the_lamp_is_checkpointed_and_kept_in_snapshots(lamp_scene):
    m = _run(lamp_scene, "on", steps=60)
    tr = m.trainer
    # the loss weighs each pixel as if evenly lit: more where the lamp gives less, within the
    # cap, nothing where it gives under 1 %
    from types import SimpleNamespace
    from recgs_addon.core.train.lamp import LAMP_DARKEST, LAMP_WEIGHT_CAP
    cam = tr.data.view(tr.data.train_ids[0], 1)[0]
    out = SimpleNamespace(alpha=torch.ones(cam.height, cam.width), depth=torch.full((cam.height, cam.width), 2.5),
                          rgb=torch.full((cam.height, cam.width, 3), 0.5))
    seen, shared = tr.seen_and_lamp(out, cam)   # the step's weight from the lamp its render was lit by
    log_l = tr.lamp_log_gain_of(cam, 2.5 * tr.ray_len(cam)).detach()
    assert torch.allclose(shared, log_l) and torch.equal(seen, tr.as_seen(out, cam))
    from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
    expect = linear_to_srgb((srgb_to_linear(torch.tensor(0.5)) * torch.exp(log_l)).clamp(0, 1))
    assert torch.allclose(seen, expect.unsqueeze(-1).expand_as(seen), atol=1e-6)
    w = tr.lamp_weight(shared)
    lit = log_l >= math.log(LAMP_DARKEST)
    assert float(w.max()) <= LAMP_WEIGHT_CAP and bool((w[~lit] == 0).all())
    assert torch.allclose(w[lit], torch.exp(-log_l[lit] / 2.4).clamp(max=LAMP_WEIGHT_CAP), rtol=1e-5)
    snap = tr.snapshot()
    before = tr.lamp.raw.detach().clone()
    with torch.no_grad():
        tr.lamp.raw.add_(0.5)
    with tr.using(snap):
        assert torch.equal(tr.lamp.raw.detach(), before)
    assert not torch.equal(tr.lamp.raw.detach(), before)
    state = m.state_dict()
    again = _run(lamp_scene, "on", steps=1)
    again.load_state_dict(state)
    assert torch.equal(again.trainer.lamp.raw.detach(), tr.lamp.raw.detach())


def test_an_evenly_lit_survey_models_no_lamp(tmp_path):
    root = tmp_path / "even"
    write_rendered_scene(root, n_views=12, width=64, height=48, n_gauss=400, downward=True)
    cfg = preset("default", iterations=1, compiled=False, pyramid=(), medium="off")
    m = make_method(root, cfg, CausticConfig(mode="3dgs"))
    assert m.trainer.lamp is None and "not modelled" in m.trainer.lamp_info["reason"]
    assert TrainConfig.from_dict({**__import__("dataclasses").asdict(cfg), "lamp": "auto"}).lamp == "auto"
