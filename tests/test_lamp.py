"""Light fixed to the camera (core/model/lamp.py, core/train/lamp.py): the gain's convention and
gradients, the water's fit with a lamp taken out, and training that models a lamp a survey shows."""
import math

import numpy as np
import pytest
import torch

from conftest import write_rendered_scene
from recgs_addon.core.caustics.build import make_method
from recgs_addon.core.caustics.config import CausticConfig
from recgs_addon.core.model.lamp import POWERS, TERMS, Lamp, image_positions
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


def test_the_lamp_is_checkpointed_and_kept_in_snapshots(lamp_scene):
    m = _run(lamp_scene, "on", steps=60)
    tr = m.trainer
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
