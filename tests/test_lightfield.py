"""The light-field estimator's pieces: TV denoising (against a float64 reference solve), the
one-sided light field, and the linear-light gain."""
import numpy as np
import pytest
import torch

from benchmarks.caustic_estimators import lightfield
from recgs_addon.core.caustics.tv import div, grad, tv_denoise, tv_energy
from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
from recgs_addon.core.model.gaussians import SH_C0


def test_div_is_the_negative_adjoint_of_grad():
    g = torch.Generator().manual_seed(0)
    u = torch.randn(2, 7, 9, generator=g, dtype=torch.float64)
    p = torch.randn(2, 2, 7, 9, generator=g, dtype=torch.float64)
    assert abs(float((grad(u) * p).sum() + (u * div(p)).sum())) < 1e-10


def _reference_rof(f: np.ndarray, lam: float, w: np.ndarray, iters: int = 20000) -> np.ndarray:
    """float64 ROF by plain (unaccelerated) Chambolle-Pock run far past convergence."""
    u = torch.tensor(f, dtype=torch.float64).unsqueeze(0)
    f64, w64 = u.clone(), torch.tensor(w, dtype=torch.float64).unsqueeze(0)
    p = torch.zeros(1, 2, *f.shape, dtype=torch.float64)
    ubar = u.clone()
    s = 1 / np.sqrt(8)
    for _ in range(iters):
        p = p + s * grad(ubar)
        p = p / torch.clamp(torch.sqrt((p * p).sum(1, keepdim=True)) / lam, min=1.0)
        un = (u + s * div(p) + s * w64 * f64) / (1 + s * w64)
        ubar = 2 * un - u
        u = un
    return u[0].numpy()


@pytest.mark.parametrize("lam,weighted,iters", [(0.05, False, 100), (0.3, False, 200), (0.3, True, 2000)])
def test_tv_denoise_reaches_the_float64_minimum(lam, weighted, iters):
    """Uniform data weights make the problem strongly convex (the accelerated steps: 100-200
    iterations); pixels without data leave only plain steps, which need many more."""
    g = torch.Generator().manual_seed(1)
    f = torch.zeros(1, 24, 32)
    f[:, 6:14, 8:20] = 1.0
    f[:, 18, :] = 0.7       # a one-pixel line
    f += 0.1 * torch.randn(f.shape, generator=g)
    w = torch.ones_like(f)
    if weighted:
        w[:, :, :4] = 0.0   # no data there: filled from the neighbours
    u = tv_denoise(f, lam, w, iters=iters)
    ref = _reference_rof(f[0].numpy(), lam, w[0].numpy())
    e_u = float(tv_energy(u.double(), f.double(), lam, w.double()))
    e_ref = float(tv_energy(torch.tensor(ref).unsqueeze(0), f.double(), lam, w.double()))
    assert e_u <= e_ref * (1 + 1e-3)
    assert np.abs(u[0].numpy() - ref).max() < 0.02


def test_tv_keeps_a_wide_bright_line_and_flattens_noise():
    g = torch.Generator().manual_seed(2)
    f = 0.05 * torch.randn(1, 40, 60, generator=g)
    f[:, 18:23, :] += 1.0   # a 5-pixel-wide line across the image
    u = tv_denoise(f, 0.05, iters=200)
    assert float(u[:, 19:22].mean()) > 0.85                    # the line stays
    assert float(u[:, :12].std()) < 0.3 * float(f[:, :12].std())  # the noise goes


def test_tv_denoise_refuses_bad_shapes_and_passes_tiny_images():
    with pytest.raises(ValueError):
        tv_denoise(torch.zeros(4, 4), 0.1)
    x = torch.rand(2, 1, 5)
    assert torch.equal(tv_denoise(x, 0.1), x)
    assert torch.equal(tv_denoise(x, 0.0), x)


def test_light_field_is_one_sided_above_its_low_band():
    """Light above the model counts, darkness below it does not (only the mean-free low band
    may be negative); a field made of broad light is taken by the low band alone."""
    h, w = 48, 64
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    q = torch.zeros(1, h, w)
    q[:, 20:25, :] = 0.8     # a bright line
    q[:, 35:40, :] = -0.8    # a dark band: the model is too bright there, not light
    L = lightfield.light_fields(q, 0, 0.02, tau=0.0)
    assert float(L[:, 21:24].mean()) > 0.6
    assert float(L[:, 36:39].abs().max()) < 1e-6
    broad = 0.3 * torch.cos(2 * np.pi * x / w).float().unsqueeze(0)
    Lb = lightfield.light_fields(broad, 5, 0.02, tau=0.05)
    assert torch.allclose(Lb, broad - broad.mean(), atol=1e-4)


def test_remove_light_undoes_a_grey_multiplicative_light():
    g = torch.Generator().manual_seed(3)
    base = 0.1 + 0.6 * torch.rand(20, 30, 3, generator=g)
    field = 0.5 * torch.rand(20, 30, generator=g)
    lit = (base + lightfield.LOG_EPS) * torch.exp(field).unsqueeze(-1) - lightfield.LOG_EPS
    assert torch.allclose(lightfield.remove_light(lit, field), base, atol=1e-6)
    q = lightfield.grey_log_ratio(lit, base)
    assert torch.allclose(q, field, atol=1e-5)


def test_srgb_round_trip_and_linear_gain():
    x = torch.linspace(0, 1, 101)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-5)
    g = torch.Generator().manual_seed(4)
    photo = torch.rand(10, 12, 3, generator=g)
    darker = lightfield.scale_linear(photo, torch.tensor([0.5, 0.6, 0.7]))
    gain = lightfield.linear_gain([(photo, darker)])
    assert torch.allclose(gain, torch.tensor([2.0, 1 / 0.6, 1 / 0.7]), rtol=1e-3)


def test_apply_linear_gain_scales_the_rendered_colour_in_linear_light():
    c = torch.tensor([[0.2, 0.5, 0.8]])
    params = {"sh_dc": ((c - 0.5) / SH_C0).unsqueeze(1).clone(), "sh_rest": torch.ones(1, 3, 3)}
    gain = torch.tensor([1.5, 1.2, 0.9])
    lightfield.apply_linear_gain(params, gain)
    c_new = 0.5 + SH_C0 * params["sh_dc"][:, 0]
    want = linear_to_srgb(srgb_to_linear(c) * gain)
    assert torch.allclose(c_new, want, atol=1e-6)
    assert torch.allclose(params["sh_rest"][0, 0], (want / c)[0], atol=1e-6)
