"""The water measured from points seen at several ranges (core/model/medium_fit.py) and the
decision and pinning built on it (core/train/water.py)."""
from __future__ import annotations

import numpy as np
import pytest

from recgs_addon.core.model import medium_fit
from recgs_addon.core.train import water

TRUE = {"attenuation": [0.5, 0.12, 0.18], "backscatter": [0.4, 0.18, 0.22], "veil": [0.02, 0.09, 0.07]}


def _observations(n=600, per=8, spread=1.3, near=(2.6, 4.5), noise=0.0, outliers=0.0, water=TRUE, seed=0,
                  light=0.0):
    """``n`` points of random colour, each seen ``per`` times from ranges within x``spread`` of
    its nearest (which varies from point to point: one altitude over relief). ``light``: the
    seabed's colour in each view times a grey gain of mean 1 (caustics: mostly a dim cell's
    ``1 - light``, now and then a bright line; a gamma distribution, skewed), else 1."""
    rs = np.random.default_rng(seed)
    J = rs.uniform(0.02, 0.6, (n, 3))
    point = np.repeat(np.arange(n), per)
    r0 = rs.uniform(*near, n)[point]
    rng = r0 * rs.uniform(1.0, spread, point.size)
    gain = (1 - light) + light * rs.gamma(0.5, 2.0, point.size) if light else np.ones(point.size)
    y = J[point] * gain[:, None]
    if water is not None:
        att, back, veil = (np.asarray(water[k]) for k in ("attenuation", "backscatter", "veil"))
        y = y * np.exp(-att * rng[:, None]) + veil * (1 - np.exp(-back * rng[:, None]))
    y = y + noise * rs.standard_normal(y.shape)
    bad = np.flatnonzero(rs.random(point.size) < outliers)   # another point's colour (occlusion)
    y[bad] = rs.uniform(0, 1, (bad.size, 3))
    return point, rng, y, J


def test_noise_free_observations_give_the_water_back_exactly():
    point, rng, y, J = _observations()
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)))
    assert np.allclose(f["attenuation"], TRUE["attenuation"], rtol=2e-3), f["attenuation"]
    veil_at = [v * (1 - np.exp(-b * np.median(rng))) for v, b in zip(TRUE["veil"], TRUE["backscatter"])]
    assert np.allclose(f["veil_at_length"], veil_at, rtol=5e-3), f["veil_at_length"]
    assert np.allclose(f["J"], J, atol=2e-3)
    assert f["gain"] > 0.9


def test_a_lamps_known_light_on_the_seabed_leaves_the_water_and_veil_right():
    """Under a lamp the seabed is lit by a known gain (5-100 % of the beam's centre here) and the
    veil lies in front of it: fitted with the gain, the water comes back; the colours divided by
    the gain instead (the veil divided with them) read it far off."""
    point, rng, _, J = _observations(water=None, seed=3)
    lit = np.exp(np.random.default_rng(4).uniform(np.log(0.05), 0.0, point.size))
    att, back, veil = (np.asarray(TRUE[k]) for k in ("attenuation", "backscatter", "veil"))
    y = lit[:, None] * J[point] * np.exp(-att * rng[:, None]) + 3 * veil * (1 - np.exp(-back * rng[:, None]))
    n, length = int(point.max()) + 1, float(np.median(rng))
    f = medium_fit.fit_water(point, n, rng, y, length, lit=lit)
    assert np.allclose(f["attenuation"], att, rtol=5e-3), f["attenuation"]
    assert np.allclose(f["J"][np.unique(point)], J[np.unique(point)], atol=5e-3)
    divided = medium_fit.fit_water(point, n, rng, np.clip(y / lit[:, None], 0, 1), length)
    assert np.abs(np.asarray(divided["attenuation"]) / att - 1).max() > 0.2, divided["attenuation"]
    with pytest.raises(ValueError):
        medium_fit.fit_water(point, n, rng, y, length, lit=lit, moving_light=True)


def test_heavy_tailed_errors_and_noise_leave_the_attenuation_within_a_few_percent():
    """Texture and occlusion: 15 % of the observations replaced by any colour, the rest noisy."""
    point, rng, y, _ = _observations(n=800, noise=0.01, outliers=0.15, seed=1)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4)
    att = np.asarray(f["attenuation"])
    assert np.all(np.abs(att / TRUE["attenuation"] - 1) < 0.1), att
    # the refits' spread is an honest error bar: the truth lies within a few of them
    sd = np.asarray(f["spread"]["attenuation"])
    assert np.all(sd > 0) and np.all(np.abs(att - TRUE["attenuation"]) < 5 * sd + 0.01), (att, sd)


def test_no_water_shows_no_attenuation_beyond_its_spread():
    point, rng, y, _ = _observations(n=800, noise=0.02, outliers=0.1, water=None, seed=2)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4)
    fit = {"fit": {k: f[k] for k in ("attenuation", "backscatter", "veil", "veil_at_length")}, "spread": f["spread"]}
    pins = water.pinning(fit)
    assert max(pins["z"]) < water.MIN_Z, pins["z"]
    assert pins["attenuation"] == ["free"] * 3


def test_one_range_per_point_pins_nothing_of_the_attenuation():
    """Seen from one range (x1.0), the colour and the water are one number per point."""
    point, rng, y, _ = _observations(n=400, spread=1.0 + 1e-9, noise=0.005, seed=3)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4)
    fit = {"fit": {k: f[k] for k in ("attenuation", "backscatter", "veil", "veil_at_length")}, "spread": f["spread"]}
    assert "pinned" not in water.pinning(fit)["attenuation"][1:]


@pytest.mark.parametrize("spread", [1.1, 1.3])
def test_the_least_squares_fit_is_the_minimum_of_its_loss(spread, monkeypatch):
    """Without the robust reweighting, the fitted water is a minimum of the squared error with
    each point's colour projected out: moving any of its numbers raises the loss computed
    directly in float64 (beyond the optimiser's tolerance, a part in 10^4: a fit stuck at a bound
    of its search was 0.6 % above the minimum)."""
    import torch

    monkeypatch.setattr(medium_fit, "IRLS_ROUNDS", 1)
    monkeypatch.setattr(medium_fit, "HUBER_K", 1e9)
    point, rng, y, _ = _observations(n=300, spread=spread, noise=0.01, seed=4)
    n, length = int(point.max()) + 1, float(np.median(rng))
    f = medium_fit.fit_channel(torch.from_numpy(point), n, torch.from_numpy(rng), torch.from_numpy(y[:, 0]), length)

    def loss(att, back, v_len):
        a = np.exp(-att * rng)
        z = y[:, 0] - v_len * np.expm1(-back * rng) / np.expm1(-back * length)
        j = np.bincount(point, a * z, n) / np.bincount(point, a * a, n)
        return float(np.mean((z - j[point] * a) ** 2))
    best = loss(f["attenuation"], f["backscatter"], f["veil_at_length"])
    for d in ([0.01, 1, 1], [0.99, 1, 1], [1, 1.05, 1], [1, 0.95, 1], [1, 1, 1.02], [1, 1, 0.98]):
        moved = loss(f["attenuation"] * d[0], f["backscatter"] * d[1], f["veil_at_length"] * d[2])
        assert moved > best * (1 - 1e-4), (d, moved, best)


def test_the_tied_fit_is_the_minimum_of_its_loss_and_its_error_bars_match_central_differences(monkeypatch):
    """With the backscatter rate tied to the attenuation (a multiple of it), the fit is a minimum
    of the squared error over the two numbers left (attenuation, veil at the median range), and
    its Gauss-Newton variances are those of the loss's curvature: the information of the
    residuals' Jacobian by central differences in float64."""
    import torch

    monkeypatch.setattr(medium_fit, "IRLS_ROUNDS", 1)
    monkeypatch.setattr(medium_fit, "HUBER_K", 1e9)
    monkeypatch.setattr(medium_fit, "TUKEY_C", 1e9)
    point, rng, y, _ = _observations(n=300, spread=1.25, noise=0.01, seed=5)
    n, length = int(point.max()) + 1, float(np.median(rng))
    for tied in (1.0, 2.0):
        f = medium_fit.fit_channel(torch.from_numpy(point), n, torch.from_numpy(rng), torch.from_numpy(y[:, 1]), length,
                                   tied=tied)
        assert f["backscatter"] == pytest.approx(tied * f["attenuation"])

        def residuals(att, v_len):
            a = np.exp(-att * rng)
            z = y[:, 1] - v_len * np.expm1(-tied * att * rng) / np.expm1(-tied * att * length)
            j = np.bincount(point, a * z, n) / np.bincount(point, a * a, n)
            return z - j[point] * a
        best = float(np.mean(residuals(f["attenuation"], f["veil_at_length"]) ** 2))
        for d in ([0.99, 1], [1.01, 1], [1, 1.02], [1, 0.98]):
            moved = float(np.mean(residuals(f["attenuation"] * d[0], f["veil_at_length"] * d[1]) ** 2))
            assert moved > best * (1 - 1e-4), (tied, d, moved, best)
        x = np.array([f["attenuation"], f["veil_at_length"]])
        h = 1e-6 * np.abs(x)
        jac = np.stack([(residuals(*(x + h * e)) - residuals(*(x - h * e))) / (2 * h[k])
                        for k, e in enumerate(np.eye(2))], 1)
        res = residuals(*x)
        var = float(res @ res) / (len(res) - len(np.unique(point)) - 3)
        cov = var * np.linalg.inv(jac.T @ jac)
        assert f["variance"][0] == pytest.approx(cov[0, 0], rel=1e-3)
        assert f["variance"][2] == pytest.approx(cov[1, 1], rel=1e-3)
        assert f["variance"][1] == pytest.approx(tied * tied * cov[0, 0], rel=1e-3)


def test_a_rate_one_altitude_leaves_free_is_tied_to_the_attenuation():
    """Flown at one altitude (each point's ranges within x1.2) the veil's value and its growth
    with range trade against each other; the refits leave the rate free, and the water's fit
    ties it to the attenuation: the veil at the median range comes out nearer the truth than the
    free rate left it, within its error bars, which cover the tie's own doubt. Seen from ranges
    x3 apart the survey pins the rate of green and blue, whose veils are bright, and they are not
    tied (red's veil is a twentieth of theirs: nothing pins its rate)."""
    truth = {"attenuation": [0.5, 0.22, 0.34], "backscatter": [0.4, 0.3, 0.3], "veil": [0.012, 0.085, 0.065]}
    point, rng, y, _ = _observations(n=800, spread=1.2, near=(2.3, 2.7), noise=0.004, outliers=0.05, water=truth,
                                     seed=6)
    n, length = int(point.max()) + 1, float(np.median(rng))
    free = medium_fit.fit_water(point, n, rng, y, length, rounds=4)
    tied = medium_fit.fit_water(point, n, rng, y, length, rounds=4, tie_free_rates=water.PINNED)
    want = np.asarray(truth["veil"]) * -np.expm1(-np.asarray(truth["backscatter"]) * length)
    assert tied["rate_tied"][1:] == [True, True], tied["rate_tied"]
    for c in range(3):
        if not tied["rate_tied"][c]:
            continue
        assert tied["backscatter"][c] == pytest.approx(tied["attenuation"][c])
        err_tied, err_free = abs(tied["veil_at_length"][c] - want[c]), abs(free["veil_at_length"][c] - want[c])
        assert err_tied < err_free, (c, tied["veil_at_length"], free["veil_at_length"], want)
        assert err_tied < 2 * tied["spread"]["veil_at_length"][c], (c, tied["veil_at_length"], tied["spread"])
        assert abs(tied["attenuation"][c] / truth["attenuation"][c] - 1) < 0.1
    # the survey pins the rate where the ranges are x3 apart
    point, rng, y, _ = _observations(n=600, spread=3.0, near=(1.5, 2.0), noise=0.004, water=truth, seed=7)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4,
                             tie_free_rates=water.PINNED)
    assert f["rate_tied"][1:] == [False, False], (f["backscatter"], f["spread"]["backscatter"])
    assert np.allclose(f["backscatter"][1:], truth["backscatter"][1:], rtol=0.1), f["backscatter"]


def test_the_attenuation_error_bar_matches_its_spread_over_surveys():
    """The Gauss-Newton standard error of the attenuation is the spread of the fits over
    independent draws of the same survey (within the spread's own sampling error)."""
    import torch

    fits, sds = [], []
    for seed in range(10):
        point, rng, y, _ = _observations(n=250, per=6, spread=1.25, noise=0.01, seed=10 + seed)
        f = medium_fit.fit_channel(torch.from_numpy(point), int(point.max()) + 1, torch.from_numpy(rng),
                                   torch.from_numpy(y[:, 1]), float(np.median(rng)))
        fits.append(f["attenuation"])
        sds.append(np.sqrt(f["variance"][0]))
    spread = np.std(fits, ddof=1)
    assert 0.5 < np.median(sds) / spread < 2.0, (np.median(sds), spread, fits)
    assert abs(np.mean(fits) - TRUE["attenuation"][1]) < 3 * spread


def _fit_dict(att, sd, effect=20.0):
    return {"fit": {"attenuation": att, "backscatter": [0.3] * 3, "veil": [0.02, 0.08, 0.07],
                    "veil_at_length": [0.01, 0.05, 0.04]},
            "spread": {"attenuation": sd, "backscatter": [1.0] * 3, "veil": [0.1] * 3, "veil_at_length": [0.001] * 3},
            "effect_levels": effect}


def test_water_is_modelled_where_the_attenuation_is_coloured_clear_of_its_error_and_matters():
    f = _fit_dict([0.5, 0.12, 0.18], [0.01, 0.01, 0.01])
    shown, why = water.decide(f, water.pinning(f))
    assert shown and "show water" in why
    # a fall-off alike in every channel: the light's (a lamp, the exposure), not water
    f = _fit_dict([0.030, 0.028, 0.027], [0.004, 0.004, 0.004])
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "alike in every channel" in why
    # attenuation within its noise of 0
    f = _fit_dict([0.02, -0.01, 0.01], [0.05, 0.05, 0.05])
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "no attenuation beyond their noise" in why
    # measured, but changes the photos by less than the threshold
    f = _fit_dict([0.05, 0.01, 0.01], [0.002, 0.002, 0.002], effect=1.0)
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "too weak to matter" in why


def test_the_channels_apart_are_judged_by_the_spread_of_their_difference_where_the_refits_give_it():
    """Under moving light the channels share the light's noise: each channel's attenuation is
    loose while their differences are sure. The decision takes the refits' spread of the
    difference where the fit gives it (0.146 apart at 0.013 is water), the channels' own spreads
    together where not (the same values 2.6 of them apart are not)."""
    f = _fit_dict([0.357, 0.211, 0.316], [0.044, 0.034, 0.044])
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "alike in every channel" in why
    f["spread"]["difference"] = [0.013, 0.002, 0.011]   # red - green, red - blue, green - blue
    shown, why = water.decide(f, water.pinning(f))
    assert shown and "show water" in why
    f["spread"]["difference"] = [0.05, 0.002, 0.011]    # the pair that decides is red and green
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "alike in every channel" in why


def test_water_that_would_leave_the_seabed_brighter_than_white_is_no_water():
    """A lamp's fall-off with range taken for water: the fit's attenuation is coloured, pinned
    and like a natural water's, but it leaves most points brighter than white once taken out of
    it (the true colour above 1), which no seabed is: no water model."""
    f = _fit_dict([2.1, 1.2, 1.6], [0.01, 0.01, 0.01])
    assert water.decide(f, water.pinning(f))[0]             # nothing else tells it
    f["over_white"] = 0.81
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "81 % of them brighter than white" in why and "no water model" in why
    f["over_white"] = 0.02                                   # a few bright or noisy points: still water
    assert water.decide(f, water.pinning(f))[0]


def test_the_points_fit_says_how_many_it_leaves_brighter_than_white():
    """``fit_from_points`` counts the points whose fitted true colour exceeds white: none for
    water that truly acts on a seabed of reflectance below 1; most where the photos' colours
    fall off with range far faster than any water's (a lamp's inverse square, 30 times over)."""
    import torch

    from recgs_addon.core.model.colour import linear_to_srgb

    def srgb(lin):
        return linear_to_srgb(torch.from_numpy(np.clip(lin, 0, 1)).float()).numpy()

    point, rng, y, _ = _observations(n=200, per=6, spread=1.5, noise=0.005, seed=3)
    obs = {"point": point, "range": rng, "colour": srgb(y), "points": np.arange(int(point.max()) + 1)}
    fit = water.fit_from_points(obs, float(np.median(rng)), rounds=0)
    assert fit["over_white"] < water.MAX_OVER_WHITE
    dim = dict(obs, colour=srgb(y * np.exp(-3.0 * (rng - rng.min()))[:, None]))
    assert water.fit_from_points(dim, float(np.median(rng)), rounds=0)["over_white"] > water.MAX_OVER_WHITE


def test_attenuation_unlike_any_natural_water_is_no_water():
    """Attenuation below 0 beyond its error bar, or red's below green's, is no natural water:
    the run models none, whatever the error bars say of its size."""
    # green and blue below 0 (the reef clip's fit), red clear of its noise
    f = _fit_dict([0.30, -0.08, -0.05], [0.01, 0.01, 0.01])
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "unlike any natural water" in why and "green, blue" in why
    f = _fit_dict([0.10, 0.30, 0.20], [0.01, 0.01, 0.01])
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "below green's" in why
    # within the error bars: still water
    f = _fit_dict([0.5, 0.12, -0.005], [0.01, 0.01, 0.01])
    assert water.decide(f, water.pinning(f))[0]
    assert medium_fit.unnatural([0.5, 0.12, 0.18]) is None
    assert "not above 0" in medium_fit.unnatural([-0.01, -0.002, -0.006])
    assert "below green's" in medium_fit.unnatural([0.1, 0.2, 0.1])
    # a fit that stopped before its refits (no natural water) has no spread
    f = _fit_dict([-0.01, -0.002, -0.006], [0.0] * 3)
    f["spread"] = None
    shown, why = water.decide(f, water.pinning(f))
    assert not shown and "not above 0" in why


def test_a_fit_unlike_natural_water_makes_no_refits():
    odd = {k: [v[1], v[0], v[2]] for k, v in TRUE.items()}   # red's water and green's swapped
    point, rng, y, _ = _observations(n=150, per=5, spread=1.3, noise=0.01, seed=3, water=odd)
    n = int(point.max()) + 1
    length = float(np.median(rng))
    f = medium_fit.fit_water(point, n, rng, y, length, rounds=4, natural_only=True)
    assert "spread" not in f and medium_fit.unnatural(f["attenuation"]) is not None
    assert "spread" in medium_fit.fit_water(point, n, rng, y, length, rounds=4)


def test_cues_say_where_the_fit_is_unlike_natural_water():
    f = _fit_dict([0.1, 0.3, 0.2], [0.01] * 3)
    f["J_mean"] = [0.3, 0.3, 0.3]
    assert any("takes red less than green" in c for c in water.cues(f))
    f = _fit_dict([0.5, 0.12, 0.18], [0.01] * 3)
    f["J_mean"] = [0.6, 0.15, 0.1]
    said = water.cues(f)
    assert len(said) == 1 and "6.0 times as bright in red" in said[0]
    f["J_mean"] = [0.3, 0.25, 0.2]
    assert water.cues(f) == []
    f = _fit_dict([0.5, 0.2, 0.1], [0.01] * 3)   # blue travels furthest, but the veil is greenest
    f["J_mean"] = [0.3, 0.25, 0.2]
    assert [c for c in water.cues(f) if "brightest in green but the water takes blue least" in c]


def _relative_error(att) -> np.ndarray:
    return np.abs(np.asarray(att) / TRUE["attenuation"] - 1)


def test_under_moving_light_the_fit_measures_the_light_where_the_plain_fit_is_biased():
    """Sharp caustics at one altitude: every view's seabed colour times a skewed grey gain of
    mean 1. The plain fit (each point's colour projected out, robust) reads the attenuation
    tens of per cent off; the fit under light is within a few per cent in every channel, and
    its points' colours are the light's mean."""
    point, rng, y, J = _observations(n=1500, per=10, light=0.9, noise=0.002, seed=20)
    n, length = int(point.max()) + 1, float(np.median(rng))
    plain = medium_fit.fit_water(point, n, rng, y, length)
    light = medium_fit.fit_water(point, n, rng, y, length, moving_light=True)
    assert light["under_light"] and "under_light" not in plain
    assert _relative_error(plain["attenuation"]).max() > 0.15, plain["attenuation"]
    assert _relative_error(light["attenuation"]).max() < 0.06, light["attenuation"]
    veil_at = [v * (1 - np.exp(-b * length)) for v, b in zip(TRUE["veil"], TRUE["backscatter"])]
    assert np.allclose(light["veil_at_length"], veil_at, rtol=0.15, atol=2e-3), light["veil_at_length"]
    # each point's colour holds its few views' light, but not its geometric mean: unbiased
    assert np.allclose(light["J"].mean(0) / J.mean(0), 1, atol=0.05), light["J"].mean(0) / J.mean(0)


def test_the_fit_under_light_gives_still_light_its_water_too():
    """Where the light finding was wrong (no light moves), the fit under light still measures
    the water: the log ratios then hold only the photos' noise."""
    point, rng, y, _ = _observations(n=800, noise=0.003, seed=21)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), moving_light=True)
    assert _relative_error(f["attenuation"]).max() < 0.05, f["attenuation"]


def test_under_moving_light_a_rate_one_altitude_leaves_free_is_tied_to_the_attenuation():
    """Under caustics at one altitude (ranges within x1.2) the fit under light, with the rate
    searched, slides along the line the survey leaves free (the veil at the median range right,
    its growth with range and the seabed's fall-off traded: green and blue read far too low).
    Where the refits leave a rate loose, every channel's rate is tied to its attenuation: each
    attenuation comes out nearer the truth, its error bars cover the truth, and the tied rates
    equal the attenuation. Seen from ranges x3 apart the survey pins the rates: no tie."""
    truth = {"attenuation": [0.5, 0.12, 0.18], "backscatter": [0.4, 0.18, 0.22], "veil": [0.03, 0.2, 0.22]}
    point, rng, y, _ = _observations(n=1500, per=10, spread=1.2, near=(2.3, 2.7), light=0.9, noise=0.002,
                                     water=truth, seed=31)
    n, length = int(point.max()) + 1, float(np.median(rng))
    free = medium_fit.fit_water(point, n, rng, y, length, rounds=4, moving_light=True)
    tied = medium_fit.fit_water(point, n, rng, y, length, rounds=4, moving_light=True,
                                tie_free_rates=water.PINNED)
    assert free["under_light"] and tied["under_light"]
    assert tied["rate_tied"] == [True, True, True], (free["backscatter"], free["spread"]["backscatter"])
    assert np.allclose(tied["backscatter"], tied["attenuation"], rtol=0.01)   # to the round before it settled
    err_free = np.abs(np.asarray(free["attenuation"]) - truth["attenuation"])
    err_tied = np.abs(np.asarray(tied["attenuation"]) - truth["attenuation"])
    assert (err_tied < err_free).all(), (tied["attenuation"], free["attenuation"])
    assert (err_tied < 2.5 * np.asarray(tied["spread"]["attenuation"])).all(), (tied["attenuation"], tied["spread"])
    # the channels share the light's noise: their differences are surer than each channel
    sd = np.asarray(tied["spread"]["attenuation"])
    for (a, b), sd_pair in zip(medium_fit.PAIRS, tied["spread"]["difference"]):
        assert sd_pair < np.hypot(sd[a], sd[b]), (tied["spread"]["difference"], sd)
    # the survey pins the rates where the ranges are x3 apart
    point, rng, y, _ = _observations(n=1500, per=10, spread=3.0, near=(1.5, 2.0), light=0.9, noise=0.002,
                                     water=truth, seed=32)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4,
                             moving_light=True, tie_free_rates=water.PINNED)
    assert f["under_light"] and f["rate_tied"] == [False, False, False], (f["backscatter"], f["spread"])
    assert np.allclose(f["backscatter"], truth["backscatter"], rtol=0.1), f["backscatter"]


def test_caustics_without_water_read_no_water():
    """Under caustics in clear air (no water at all), whichever fit is kept reads no attenuation
    beyond its error bars: the light is not taken for water."""
    point, rng, y, _ = _observations(n=1500, per=10, light=0.9, noise=0.002, water=None, seed=23)
    f = medium_fit.fit_water(point, int(point.max()) + 1, rng, y, float(np.median(rng)), rounds=4,
                             moving_light=True, tie_free_rates=water.PINNED)   # as the job fits
    fit = {"fit": {k: f[k] for k in ("attenuation", "backscatter", "veil", "veil_at_length")}, "spread": f["spread"],
           "effect_levels": 10.0}
    shown, why = water.decide(fit, water.pinning(fit))
    assert not shown, (why, f["attenuation"], f.get("under_light"))


def test_the_log_ratio_of_two_channels_holds_no_light():
    """With the true water, each point's log ratio of a channel's seabed part to green's is one
    number whatever the light's gain in each view: the residuals vanish (float64)."""
    import torch

    point, rng, y, _ = _observations(n=200, per=6, light=0.9, seed=22)
    lf = medium_fit._LightFit(torch.from_numpy(point), int(point.max()) + 1, torch.from_numpy(rng),
                              torch.from_numpy(y), float(np.median(rng)), torch.ones(point.size, dtype=torch.float64))
    length = float(np.median(rng))
    att = torch.tensor(TRUE["attenuation"], dtype=torch.float64)
    rate = torch.tensor(TRUE["backscatter"], dtype=torch.float64)
    v_len = torch.tensor(TRUE["veil"], dtype=torch.float64) * -torch.expm1(-rate * length)
    lf.eps = torch.full((3,), 1e-12, dtype=torch.float64)   # every colour is above its veil here
    h = torch.ones(point.size, 2, dtype=torch.float64)
    res = lf.chroma(v_len, att[[0, 2]] - att[1], rate, h)
    assert float(res.abs().max()) < 1e-9
    wrong = lf.chroma(v_len * 1.5, att[[0, 2]] - att[1], rate, h)
    assert float(wrong.abs().max()) > 1e-3


def test_levenberg_marquardt_finds_a_least_squares_minimum():
    """A curve with parameters of very different scales: the damped steps reach the minimum
    (the gradient of the squared error vanishes, checked by central differences in float64)."""
    import torch

    x = torch.linspace(0, 4, 50, dtype=torch.float64)
    y = 2.5 * torch.exp(-0.7 * x) + 0.004 + 0.01 * torch.sin(7 * x)

    def residuals(t):
        return t[0] * torch.exp(-t[1] * x) + t[2] - y
    theta = medium_fit._levenberg_marquardt(residuals, torch.tensor([1.0, 0.2, 0.5], dtype=torch.float64), 60)
    assert abs(float(theta[1]) - 0.7) < 0.02

    def loss(t):
        r = residuals(t)
        return float(r @ r)
    for k in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[k] = 1e-6 * max(abs(float(theta[k])), 1e-3)
        grad = (loss(theta + step) - loss(theta - step)) / (2 * float(step[k]))
        assert abs(grad) * max(abs(float(theta[k])), 1e-3) < 1e-6 * max(loss(theta), 1e-12) + 1e-12, (k, grad)


def test_the_report_says_whether_the_points_fit_measured_the_moving_light():
    from recgs_addon.core.outputs.report import _water_section

    medium = {"coefficients": {"attenuation": [0.47, 0.2, 0.31], "backscatter": [0.3] * 3, "veil": [0.02, 0.08, 0.06]},
              "reason": "the sparse points show water",
              "prefit_under_light": {"under_light": True, "light_noise": [0.42, 0.012],
                                     "plain_attenuation": [0.63, 0.326, 0.44]}}
    text = "\n".join(_water_section(medium))
    assert "measured it" in text and "35 times the photos' own noise" in text and "0.630 / 0.326 / 0.440" in text
    medium["prefit_under_light"] = {"under_light": False, "light_noise": [0.05, 0.04], "plain_attenuation": [0.5] * 3}
    text = "\n".join(_water_section(medium))
    assert "too little to measure the water by" in text and "1.2 times" in text
    medium["prefit_under_light"] = None   # no moving light found: nothing said
    assert "moving light" not in "\n".join(_water_section(medium))
