"""The water model (core/model/medium.py, core/train/water.py) and the survey generator's water
(tools/survey_water.py): the formula against float64 numpy, gradients against finite
differences, the inverse, the coefficients recovered from views at several ranges, and the
trainer's decisions and state."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
from recgs_addon.core.model.medium import Medium, out_of_water, ray_lengths, through_water

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import survey_water  # noqa: E402

COASTAL = {"attenuation": [0.5, 0.22, 0.34], "backscatter": [0.3, 0.34, 0.3], "veil": [0.012, 0.085, 0.065]}


def _srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _lin(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _medium(values: dict, length: float = 3.0) -> Medium:
    return Medium.from_values({**values, "length": length})


def test_see_matches_the_formula_in_float64():
    rng = np.random.default_rng(0)
    h, w = 6, 8
    surface = rng.uniform(0, 1, (h, w, 3))
    alpha = rng.uniform(0.3, 1.0, (h, w))
    depth_z = rng.uniform(1.0, 5.0, (h, w))
    m = _medium(COASTAL)
    rl = ray_lengths(w, h, 5.0, 5.0, w / 2, h / 2)
    got = m.see(torch.tensor(surface, dtype=torch.float32), torch.tensor(alpha, dtype=torch.float32),
                torch.tensor(depth_z * alpha, dtype=torch.float32), rl).detach().numpy()
    r = (depth_z * rl.double().numpy())[..., None]
    vals = m.values()
    att, back, veil = (np.array(vals[k]) for k in ("attenuation", "backscatter", "veil"))
    want = _srgb(_lin(surface) * np.exp(-att * r) + veil * (1 - np.exp(-back * r)))
    assert np.allclose(vals["attenuation"], COASTAL["attenuation"], rtol=1e-5)
    assert np.abs(got - want).max() < 2e-5
    # full cover: the numpy output model and the generator's agree with the torch one
    full = m.see(torch.tensor(surface, dtype=torch.float32), torch.ones(h, w), torch.tensor(depth_z, dtype=torch.float32), rl)
    lin_np = through_water(_lin(surface), r[..., 0], vals)
    gen = survey_water.apply_water(_lin(surface), r[..., 0], {"attenuation_per_m": vals["attenuation"],
                                                               "backscatter_per_m": vals["backscatter"],
                                                               "veiling_light": vals["veil"]})
    assert np.abs(_srgb(lin_np) - full.detach().numpy()).max() < 2e-5
    assert np.abs(gen - lin_np).max() < 1e-12


def test_srgb_curves_invert_each_other():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    assert np.allclose(srgb_to_linear(x).numpy(), _lin(x.numpy()), atol=1e-12)


def test_gradients_match_finite_differences():
    torch.manual_seed(0)
    h, w = 4, 5
    surface = (torch.rand(h, w, 3, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    alpha = (torch.rand(h, w, dtype=torch.float64) * 0.5 + 0.5).requires_grad_()
    depth = torch.rand(h, w, dtype=torch.float64) * 3 + 1
    rl = ray_lengths(w, h, 4.0, 4.0, 2.5, 2.0).double()
    m = _medium(COASTAL)
    m.raw = torch.nn.Parameter(m.raw.detach().double())
    weights = torch.rand(h, w, 3, dtype=torch.float64)

    z = depth.clone()

    def f():   # depth follows alpha (a fixed surface): the range, which is not differentiated, stays put
        return (m.see(surface, alpha, z * alpha, rl) * weights).sum()

    f().backward()
    assert alpha.grad is None   # the water does not move the geometry
    for t in (m.raw, surface):
        flat, grad = t.data.view(-1), t.grad.view(-1)
        for k in range(0, flat.numel(), max(1, flat.numel() // 9)):
            old = float(flat[k])
            eps = 1e-6
            flat[k] = old + eps
            up = float(f().detach())
            flat[k] = old - eps
            down = float(f().detach())
            flat[k] = old
            fd = (up - down) / (2 * eps)
            assert abs(fd - float(grad[k])) <= 1e-6 * max(1.0, abs(fd)), (t.shape, k, fd, float(grad[k]))


def test_out_of_water_inverts_through_water_where_the_gain_allows():
    rng = np.random.default_rng(1)
    true = rng.uniform(0.05, 0.8, (10, 10, 3))
    r = rng.uniform(0.5, 4.0, (10, 10))
    seen = through_water(true, r, COASTAL)
    back = out_of_water(seen, r, COASTAL, max_gain=1e9)
    assert np.abs(back - true).max() < 1e-10
    capped = out_of_water(seen, np.full_like(r, 30.0), COASTAL, max_gain=20.0)
    assert np.isfinite(capped).all()


def test_coefficients_recovered_from_views_at_several_ranges():
    """A patch of seabed seen at six ranges (1.5-5 m): the water and the true colour together
    are what the photos tell, so the fit finds both (the trainer's setting: Adam on the
    medium's raw parameters and the colours)."""
    gen = torch.Generator().manual_seed(3)
    n = 400
    true = torch.rand(n, 3, generator=gen) * 0.7 + 0.1               # sRGB true colours
    ranges = torch.tensor([1.5, 2.2, 2.9, 3.6, 4.3, 5.0])
    truth = _medium(COASTAL)
    with torch.no_grad():
        photos = [truth.see(true[None], torch.ones(1, n), torch.full((1, n), float(r)), torch.ones(1, n)) for r in ranges]
        photos = [torch.round(p * 255) / 255 for p in photos]        # 8-bit photos
    fit = Medium(3.0, veil=(0.05, 0.1, 0.1))
    colours = torch.nn.Parameter(torch.full((1, n, 3), 0.5))
    opt = torch.optim.Adam([{"params": [fit.raw], "lr": 0.02}, {"params": [colours], "lr": 0.02}])
    for _ in range(4000):
        loss = sum((fit.see(colours, torch.ones(1, n), torch.full((1, n), float(r)), torch.ones(1, n)) - p).abs().mean()
                   for r, p in zip(ranges, photos))
        opt.zero_grad()
        loss.backward()
        opt.step()
    got = fit.values()
    for key in ("attenuation", "backscatter", "veil"):
        assert np.allclose(got[key], COASTAL[key], rtol=0.15, atol=0.01), (key, got[key], COASTAL[key])
    assert float((colours.detach()[0] - true).abs().mean()) < 0.02


def test_medium_state_round_trip():
    m = _medium(COASTAL, length=2.5)
    m2 = Medium.from_state(m.state_dict())
    assert m2.length == 2.5
    assert torch.equal(m2.raw, m.raw)


def test_generator_water_types_and_overrides():
    w = survey_water.water_coefficients("coastal")
    assert w["attenuation_per_m"][0] > w["attenuation_per_m"][1]     # red goes first
    assert survey_water.water_coefficients("none") is None
    o = survey_water.water_coefficients("clear", attenuation="0.1,0.2,0.3")
    assert o["attenuation_per_m"] == [0.1, 0.2, 0.3]
    with pytest.raises(ValueError):
        survey_water.water_coefficients("clear", backscatter="1,2")
    # no surface hit: the veil alone
    img = survey_water.apply_water(np.ones((1, 2, 3)), np.array([[np.inf, 1e10]]), w)
    assert np.allclose(img, w["veiling_light"])


# --- the trainer with water -------------------------------------------------------------------

HEIGHTS = [1.4, 2.6, 3.8, 1.8, 3.2, 4.2, 1.6, 2.9, 3.6, 2.1, 4.0, 2.4]


@pytest.fixture(scope="module")
def water_scenes(tmp_path_factory):
    """The same seabed seen from 1.4-4.2 m, through coastal water and through none."""
    from conftest import write_rendered_scene

    root = tmp_path_factory.mktemp("water")
    write_rendered_scene(root / "water", n_views=12, width=48, height=36, n_gauss=300, heights=HEIGHTS,
                         water=COASTAL)
    write_rendered_scene(root / "dry", n_views=12, width=48, height=36, n_gauss=300, heights=HEIGHTS)
    return root


def _cfg(**kw):
    from recgs_addon.core.train.config import preset

    base = dict(iterations=400, eval_every=100, log_every=100, holdout_every=4, compiled=False,
                densify_from=60, densify_every=60, densify_until=300, pyramid=((40, 2),))
    return preset("default", **{**base, **kw})


def test_auto_models_the_water_only_where_there_is_some(water_scenes):
    from recgs_addon.core.train.trainer import make_trainer

    wet = make_trainer(water_scenes / "water", _cfg())
    dry = make_trainer(water_scenes / "dry", _cfg())
    assert wet.medium is not None, wet.medium_info["reason"]
    assert dry.medium is None and "no measurable water" in dry.medium_info["reason"]
    assert wet.medium_info["range_spread"] > 1.5
    # before training, from the sparse points alone: red is taken first
    att = wet.medium.values()["attenuation"]
    assert att[0] > att[1] and att[0] > att[2]
    # the Gaussians start from the points' true colours as the photos show them through the
    # water (this survey's sparse colours are the true ones: the fit comes close to them)
    assert np.abs(wet.true_point_colours().astype(float) - wet.data.scene.colors).mean() < 25


def test_a_survey_with_caustics_fits_its_water_under_the_light(water_scenes, monkeypatch):
    """Where the light finding saw caustics, the points' fit is asked to measure the moving
    light (this scene's light is still: it says the light is too weak and keeps the plain fit)."""
    from recgs_addon.core.train import water
    from recgs_addon.core.train.trainer import Trainer, load_data

    asked = []
    real = water.fit_from_points
    monkeypatch.setattr(water, "fit_from_points", lambda *a, **k: asked.append(k.get("moving_light")) or real(*a, **k))
    cfg = _cfg()
    still = Trainer(load_data(water_scenes / "water", cfg), cfg)
    caustics = Trainer(load_data(water_scenes / "water", cfg), cfg, light={"caustics": True, "moving": 0.2})
    assert asked == [False, True]
    assert still.medium_info["prefit_under_light"] is None
    under = caustics.medium_info["prefit_under_light"]
    assert under["under_light"] is False and under["light_noise"][0] < 3 * under["light_noise"][1]
    assert caustics.medium is not None


def test_true_colour_is_learned_through_the_water_and_resumes_exactly(water_scenes):
    """Trained through the water, the true-colour renders come close to the true colour (far
    closer than a run that takes the water in); a checkpoint taken mid-run resumes to the same
    model and water."""
    from recgs_addon.core.train.trainer import make_trainer

    wet = make_trainer(water_scenes / "water", _cfg(), gt_images="clean")
    wet.run()
    plain = make_trainer(water_scenes / "water", _cfg(medium="off"), gt_images="clean")
    plain.run()
    got, base = wet.evaluate()["psnr_gt"], plain.evaluate()["psnr_gt"]
    assert got > base + 2.0, (got, base)
    fitted = wet.medium.values()
    # the survey pins the attenuation here: it is kept from the points, and the veil of each
    # channel where the points pin it too; the rest is trained
    assert wet.medium_info["attenuation_from_points"]
    assert np.allclose(fitted["attenuation"], wet.medium_info["prefit_coefficients"]["attenuation"], rtol=1e-6)
    for c, held in enumerate(wet.medium_info["veil_kept"]):
        same = np.isclose(fitted["veil"][c], wet.medium_info["prefit_coefficients"]["veil"][c], rtol=1e-6)
        assert same == held, (c, wet.medium_info["veil_kept"], fitted["veil"])
    att = fitted["attenuation"]   # red, which the water takes most, is measured best
    assert abs(att[0] - COASTAL["attenuation"][0]) < 0.3 * COASTAL["attenuation"][0] and att[0] > max(att[1:]), fitted
    part = make_trainer(water_scenes / "water", _cfg(), gt_images="clean")
    assert part.run(should_stop=lambda: part.step >= 150) == "stopped"
    resumed = make_trainer(water_scenes / "water", _cfg(), gt_images="clean")
    resumed.load_state_dict(part.state_dict())
    resumed.run()
    assert torch.equal(resumed.medium.raw, wet.medium.raw)
    for k in wet.params:
        assert torch.equal(resumed.params[k], wet.params[k]), k


def _trained_through(water_scenes, attenuation_factor: float = 1.0):
    """A trainer on the water survey, trained through the points' water with its attenuation
    scaled by ``attenuation_factor`` and held there."""
    from recgs_addon.core.train.trainer import make_trainer

    tr = make_trainer(water_scenes / "water", _cfg())
    v = tr.medium.values()
    v["attenuation"] = [a * attenuation_factor for a in v["attenuation"]]
    with torch.no_grad():
        tr.medium.raw.copy_(Medium.from_values(v).raw)
    tr.medium_info["attenuation_kept"] = [True] * 3
    tr._hold_points_water()
    tr.run()
    return tr


def test_the_water_never_leaves_a_true_colour_above_white_or_tinted(water_scenes):
    """At the end the true colour the water leaves is checked: trained through the points' water
    it is kept (the seabed within white, no cast); held at four times the attenuation, training
    pushes the true colour above white on more of the seabed than the limit, and with a seabed
    tinted beyond the photos' own cast the same: the water is left out, the report says why,
    and the Gaussians keep the colour the photos show (the water put into their colours at the
    range the views see them from), so the held-out photos are matched at least as well."""
    from recgs_addon.core.train import water

    good = _trained_through(water_scenes)
    good.decide_medium()
    info = good.medium_info
    assert good.medium is not None and info["kept"], info["reason"]
    assert info["true_over_white"] <= water.MAX_OVER_WHITE and info["true_cast"] <= water.GREY_WORLD, info
    # each Gaussian's range: its distance from the views whose frame holds it, in float64
    ids = good.data.train_ids[:: max(1, len(good.data.train_ids) // 4)][:4]
    rng = good.gaussian_ranges(ids).numpy()
    for g in range(0, len(rng), max(1, len(rng) // 40)):
        x, d = good.params["means"][g].detach().double().numpy(), []
        for i in ids:
            cam = good.data.scene.cameras[i]
            pc = cam.R @ x + cam.t
            u, v = cam.fx * pc[0] / pc[2] + cam.cx, cam.fy * pc[1] / pc[2] + cam.cy
            if pc[2] > 0 and 0 <= u < cam.width and 0 <= v < cam.height:
                d.append(np.linalg.norm(pc))
        assert rng[g] == pytest.approx(np.mean(d) if d else good.medium.length, rel=1e-5), g

    strong = _trained_through(water_scenes, 4.0)
    before = strong.evaluate()["psnr"]
    strong.decide_medium()
    info = strong.medium_info
    assert strong.medium is None and not info["kept"] and info["as_seen"], info
    assert info["true_over_white"] > water.MAX_OVER_WHITE and "above white" in info["reason"]
    assert "keep the colour the photos show" in info["reason"] and info["coefficients_left_out"]["attenuation"]
    assert strong.evaluate()["psnr"] > before - 0.5
    from recgs_addon.core.outputs.report import _water_section
    section = "\n".join(_water_section(strong.medium_summary()))
    assert "Trained, then left out" in section and "above white" in section, section

    tinted = _trained_through(water_scenes)
    seen_before = [tinted.render_output(i).rgb.clamp(0, 1) for i in tinted.data.train_ids[:3]]
    with torch.no_grad():   # a seabed far redder than any water would leave it
        from recgs_addon.core.model.gaussians import SH_C0
        colour = tinted.params["sh_dc"][:, 0] * SH_C0 + 0.5
        colour[:, 1:] *= 0.15
        tinted.params["sh_dc"][:, 0] = (colour - 0.5) / SH_C0
    seen = [tinted.render_output(i).rgb.clamp(0, 1) for i in tinted.data.train_ids[:3]]
    tinted.decide_medium()
    info = tinted.medium_info
    assert tinted.medium is None and info["as_seen"] and "tinted" in info["reason"], info
    assert info["true_cast"] > max(water.GREY_WORLD, info["seen_cast"])
    # the colour kept is the one seen through the water (to within the per-Gaussian range)
    after = [tinted.render_output(i).rgb.clamp(0, 1) for i in tinted.data.train_ids[:3]]
    err = np.mean([float((a - b).abs().mean()) for a, b in zip(after, seen)])
    assert err < 0.5 * np.mean([float((b - s).abs().mean()) for b, s in zip(seen_before, seen)]) + 0.02, err


def test_numba_path_matches_torch_values_and_gradients():
    """The water through numba's kernels (core/train/numba_water.py) against the torch oracle,
    clamps included (surface values beyond [0, 1], a seen value above 1)."""
    from recgs_addon.core.train import numba_water

    if numba_water.load() is None:
        pytest.skip(f"numba unavailable: {numba_water.error()!r}")
    gen = torch.Generator().manual_seed(5)
    h, w = 7, 9
    surface = torch.rand(h, w, 3, generator=gen) * 1.2 - 0.1
    surface[0, 0] = torch.tensor([0.02, 0.5, 1.0])
    rng = torch.rand(h, w, generator=gen) * 4 + 0.5
    rng[1, 1] = 0.0
    m = _medium({**COASTAL, "veil": [0.012, 0.085, 0.9]})
    weights = torch.rand(h, w, 3, generator=gen)
    outs = []
    for fast in (False, True):
        s = surface.clone().requires_grad_()
        m.raw.grad = None
        y = numba_water.see(s, rng, *m.coefficients()) if fast else m.see_at(s, rng)
        (y * weights).sum().backward()
        outs.append((y.detach(), s.grad.clone(), m.raw.grad.clone()))
    (y0, gs0, gr0), (y1, gs1, gr1) = outs
    assert torch.allclose(y0, y1, atol=2e-6)
    assert torch.allclose(gs0, gs1, atol=1e-4, rtol=1e-4)
    assert torch.allclose(gr0, gr1, atol=1e-3, rtol=1e-4)


def test_train_command_writes_the_true_colour_outputs(water_scenes, tmp_path):
    """``train`` on a survey behind water: the plan says the water is modelled, and the job
    leaves medium.json, truecolour/ photos closer to the true colour than the photos, true-colour
    held-out renders, and a report with the water's section and example."""
    import json
    import subprocess

    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "recgs_addon", "train", str(water_scenes / "water"), "--out", str(out),
                           "--iterations", "150", "--holdout-every", "4", "--eager", "--gt-images", "clean"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "water: modelled" in proc.stderr
    medium = json.loads((out / "medium.json").read_text())
    assert medium["kept"] and len(medium["coefficients"]["attenuation"]) == 3
    m = json.loads((out / "metrics.json").read_text())
    assert m["medium"]["kept"] and m["psnr_truecolour_gt"] > m["psnr_captured_gt"] + 3
    assert len(list((out / "truecolour").glob("*.png"))) == 9
    report = (out / "report.md").read_text()
    assert "## The water" in report and "report/water_" in report
