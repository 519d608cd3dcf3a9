"""The caustic likelihood (benchmarks/caustic_estimators/likelihood.py): its table, its fit, and what fitting a
point to it recovers, against the median (L1) and the mean, for light shaped like the survey
generator's."""
import math

import numpy as np
import pytest
import torch

from benchmarks.caustic_estimators import likelihood
from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear


def _network_gains(rng, n):
    """Gains shaped like light networks: a dim floor most of the time, bright lines sometimes
    (mean 1, as the generator's)."""
    floor = 0.66 + 0.05 * rng.random(n)
    line = rng.random(n) < 0.12
    g = np.where(line, 1.0 + 6.0 * rng.random(n), floor)
    return g / g.mean()


def test_fit_is_unimodal_zero_at_the_mode_and_shifted_to_the_mean_light():
    rng = np.random.default_rng(0)
    g = _network_gains(rng, 200_000)
    r = torch.tensor(np.log(g) - 0.3)                 # a model 0.3 log units too bright
    lik = likelihood.GainLikelihood.fit(r)
    assert lik.shift == pytest.approx(-0.3, abs=0.01)
    rho = lik.rho
    m = int(torch.argmin(rho))
    assert float(rho.min()) == 0.0
    assert bool((rho[:m].diff() <= 1e-6).all()) and bool((rho[m:].diff() >= -1e-6).all())
    assert lik.mode() == pytest.approx(math.log(0.68 / g.mean() * 1.0), abs=0.08)   # the floor's log gain
    assert lik.slope_lo < -10 and lik.slope_hi > 0           # steep below the floor, gentle above


def test_table_is_continuous_and_its_gradient_is_the_slope():
    lik = likelihood.GainLikelihood.fit(torch.randn(100_000, dtype=torch.float64) * 0.3)
    r = torch.linspace(-5, 5, 2001, dtype=torch.float64, requires_grad=True)
    v = lik(r)
    assert float((v[1:] - v[:-1]).abs().max()) < 0.2                # no jumps, also where the table ends
    v.sum().backward()
    h = 1e-5
    r0 = torch.tensor([-4.0, -0.4137, 0.0123, 0.3711, 4.0], dtype=torch.float64)
    fd = (lik(r0 + h) - lik(r0 - h)) / (2 * h)
    r0.requires_grad_(True)
    lik(r0).sum().backward()
    assert torch.allclose(r0.grad, fd, atol=1e-4)
    assert float(lik(torch.tensor(-10.0))) > float(lik(torch.tensor(-3.0))) > 0    # the tails keep rising
    assert float(lik(torch.tensor(10.0))) > float(lik(torch.tensor(3.0))) > 0


@pytest.mark.parametrize("shape", ["network", "broad"])
def test_fitting_points_to_the_likelihood_beats_the_median(shape):
    """Points seen by 12 views each: the maximum-likelihood colour (what training on rho does)
    against the median (what an L1 loss fits) and the mean (L2), as relative error."""
    rng = np.random.default_rng(1)
    pool = _network_gains(rng, 100_000) if shape == "network" else np.exp(0.35 * rng.standard_normal(100_000) - 0.06)
    pool = pool / pool.mean()
    lik = likelihood.GainLikelihood.fit(torch.tensor(np.log(pool)))
    s = torch.tensor(np.log(pool[rng.integers(0, len(pool), (2000, 12))]))
    m = torch.zeros(2000, requires_grad=True)
    opt = torch.optim.Adam([m], lr=0.05)
    for _ in range(300):
        opt.zero_grad()
        lik(s - m[:, None]).sum().backward()
        opt.step()
    err = lambda e: float(np.sqrt(np.mean((np.asarray(e) - 1) ** 2)))  # noqa: E731
    ml, median, mean = err(torch.exp(m.detach())), err(np.exp(np.median(s.numpy(), 1))), err(np.exp(s.numpy()).mean(1))
    if shape == "network":
        assert ml < 0.25 * median and ml < 0.5 * mean, (ml, median, mean)
    else:                                                             # symmetric light: about the mean
        assert ml < median and ml < 1.15 * mean, (ml, median, mean)


def test_light_map_and_remove_light_undo_a_grey_gain():
    rng = np.random.default_rng(2)
    clean = torch.tensor(rng.uniform(0.3, 0.8, (24, 32, 3)), dtype=torch.float32)
    gain = torch.tensor(np.exp(0.4 * rng.standard_normal((24, 32))), dtype=torch.float32)
    photo = linear_to_srgb(srgb_to_linear(clean) * gain.unsqueeze(-1))
    light = likelihood.light_map(photo, clean, sigma=0)
    back = likelihood.remove_light(photo, light)
    assert torch.allclose(back, clean, atol=0.01)      # to the grey offset's share of dark pixels
    blurred = likelihood.light_map(photo, clean, sigma=1.0)
    assert torch.allclose(blurred.mean(), light.mean(), atol=0.02) and blurred.std() < light.std()
