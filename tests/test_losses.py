import math

import numpy as np
import pytest
import torch

from recgs_addon.core.train.losses import l1, psnr, ssim, training_loss


def ssim_reference(a, b):
    """Plain float64 SSIM: 11x11 Gaussian window (sigma 1.5), zero padding, per channel."""
    x = np.arange(11) - 5.0
    g = np.exp(-x * x / (2 * 1.5 ** 2))
    g /= g.sum()
    win = np.outer(g, g)
    H, W, C = a.shape

    def blur(img):
        p = np.pad(img, ((5, 5), (5, 5)))
        out = np.zeros((H, W))
        for dy in range(11):
            for dx in range(11):
                out += win[dy, dx] * p[dy:dy + H, dx:dx + W]
        return out

    vals = []
    for c in range(C):
        x_, y_ = a[:, :, c], b[:, :, c]
        ma, mb = blur(x_), blur(y_)
        va = blur(x_ * x_) - ma * ma
        vb = blur(y_ * y_) - mb * mb
        cov = blur(x_ * y_) - ma * mb
        m = ((2 * ma * mb + 1e-4) * (2 * cov + 9e-4)) / ((ma * ma + mb * mb + 1e-4) * (va + vb + 9e-4))
        vals.append(m)
    return float(np.mean(vals))


def test_ssim_matches_float64_reference():
    rng = np.random.default_rng(0)
    a = rng.random((23, 31, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ref = ssim_reference(a, b)
    got = float(ssim(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)))
    assert abs(got - ref) < 1e-5
    assert abs(float(ssim(torch.tensor(a), torch.tensor(a))) - 1.0) < 1e-12


def test_ssim_and_loss_gradients_match_finite_differences():
    rng = np.random.default_rng(1)
    a = torch.tensor(rng.random((7, 8, 3)), dtype=torch.float64, requires_grad=True)
    b = torch.tensor(rng.random((7, 8, 3)), dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b), (a,), eps=1e-6, atol=1e-8)
    # both differentiable: the blur's hand-written backward (the blur itself) on either side,
    # on images smaller than the 11x11 window (zero padding everywhere)
    b2 = b.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(ssim, (a, b2), eps=1e-6, atol=1e-8)
    # L1 is not differentiable at 0; the random images keep |a - b| well away from it
    assert torch.autograd.gradcheck(lambda x: training_loss(x, b), (a,), eps=1e-6, atol=1e-8)


def test_psnr_and_l1():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert abs(psnr(a, b) - 20.0) < 1e-5  # 0.1 is not exact in float32
    assert psnr(a, a) == math.inf
    assert abs(float(l1(a, b)) - 0.1) < 1e-7


def test_tiny_images_are_finite():
    a = torch.rand(1, 1, 3, requires_grad=True)
    loss = training_loss(a, torch.rand(1, 1, 3))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(a.grad).all()


def test_weighted_loss_with_unit_weights_is_the_plain_loss():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(20, 24, 3, generator=g), torch.rand(20, 24, 3, generator=g)
    for lam in (0.0, 0.2, 1.0):
        assert torch.allclose(training_loss(a, b, lam, torch.ones(20, 24)), training_loss(a, b, lam), atol=1e-6)


def test_pixels_with_zero_weight_do_not_count():
    g = torch.Generator().manual_seed(2)
    a = torch.rand(20, 24, 3, generator=g).requires_grad_(True)
    b = torch.rand(20, 24, 3, generator=g)
    w = torch.ones(20, 24)
    w[3:7, 5:9] = 0
    loss = training_loss(a, b, 0.0, w)
    loss.backward()
    assert float(a.grad[3:7, 5:9].abs().max()) == 0.0 and float(a.grad.abs().sum()) > 0
    b2 = b.clone()
    b2[3:7, 5:9] = 1.0 - b2[3:7, 5:9]            # change what the trimmed pixels show
    assert float(training_loss(a, b2, 0.0, w)) == pytest.approx(float(loss))
    # the weighted mean: half the weight everywhere changes nothing
    assert float(training_loss(a, b, 0.2, 0.5 * w)) == pytest.approx(float(training_loss(a, b, 0.2, w)), rel=1e-6)


def test_l2_loss_is_the_mean_squared_error_and_fits_the_mean():
    """An L2 fit of one value to several views ends at their mean, an L1 fit at their median."""
    from recgs_addon.core.train.losses import training_loss

    a, b = torch.rand(6, 7, 3), torch.rand(6, 7, 3)
    assert float(training_loss(a, b, 0.0, kind="l2")) == pytest.approx(float(((a - b) ** 2).mean()), rel=1e-6)
    w = torch.ones(6, 7)
    assert float(training_loss(a, b, 0.0, w, kind="l2")) == pytest.approx(float(((a - b) ** 2).mean()), rel=1e-6)
    views = [torch.full((4, 4, 3), v) for v in (0.2, 0.3, 0.9)]
    for kind, want in (("l2", 1.4 / 3), ("l1", 0.3)):
        x = torch.full((4, 4, 3), 0.5, requires_grad=True)
        opt = torch.optim.Adam([x], lr=0.01)
        for step in range(1500):
            opt.zero_grad()
            sum(training_loss(x, v, 0.0, kind=kind) for v in views).backward()
            opt.step()
        assert float(x.mean()) == pytest.approx(want, abs=0.01), kind
    with pytest.raises(ValueError):
        training_loss(a, b, 0.0, kind="l3")


# ------------------------------------------------------------------------------ numba SSIM

def _numba_ssim():
    from recgs_addon.core.train import numba_ssim
    return numba_ssim if numba_ssim.load() is not None else None


needs_numba = pytest.mark.skipif(_numba_ssim() is None, reason="numba is not installed here")


@needs_numba
@pytest.mark.parametrize("shape", [(240, 320), (23, 31), (7, 5), (1, 1)])
@pytest.mark.parametrize("weighted", [False, True])
def test_numba_ssim_term_matches_the_eager_oracle(shape, weighted):
    """The loss with numba's SSIM against the eager definition, values and gradients, on a
    view's size, odd sizes and images smaller than the 11x11 window."""
    g = torch.Generator().manual_seed(shape[0] + weighted)
    a = torch.rand(*shape, 3, generator=g)
    b = (a + 0.1 * torch.randn(*shape, 3, generator=g)).clamp(0, 1)
    w = torch.rand(*shape, generator=g) if weighted else None
    grads = []
    for fast in (False, True):
        x = a.clone().requires_grad_(True)
        loss = training_loss(x, b, 0.2, w, fast_ssim=_numba_ssim().ssim_term if fast else None)
        loss.backward()
        grads.append((float(loss), x.grad))
    (l_eager, g_eager), (l_fast, g_fast) = grads
    assert l_fast == pytest.approx(l_eager, abs=1e-6)
    assert torch.isfinite(g_fast).all()
    assert float((g_fast - g_eager).abs().max()) <= 1e-5 * float(g_eager.abs().max())


@needs_numba
def test_numba_ssim_on_hard_cases():
    """Flat images (zero variance: C2 alone keeps the ratio finite), identical images (SSIM 1,
    gradient 0), black against white, and a render far outside [0, 1] (it is not clamped in
    training): finite, and equal to the float64 eager loss and gradient to float32 rounding."""
    z = torch.zeros(16, 16, 3)
    cases = [(z + 0.5, z + 0.5), (z + 0.5, z + 0.25), (z, z + 1.0),
             (torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(3)) * 40 - 20, z + 0.3)]
    for a, b in cases:
        ref = a.double().requires_grad_(True)
        ref_loss = training_loss(ref, b.double(), 1.0)
        ref_loss.backward()
        x = a.clone().requires_grad_(True)
        loss = training_loss(x, b, 1.0, fast_ssim=_numba_ssim().ssim_term)
        loss.backward()
        assert math.isfinite(float(loss)) and torch.isfinite(x.grad).all()
        assert float(loss) == pytest.approx(float(ref_loss), abs=1e-6)
        # float32 against float64: to 1e-5 of the largest gradient, or, where the gradient is
        # about 0 (the render is the target), to 1e-3 of one pixel's share of the loss (1 / 768):
        # its terms are of order 1 / C2 ~ 1e3 times that share and cancel, so float32 rounding
        # leaves ~1e-4 of the share (the eager float32 path leaves the same)
        tol = max(1e-5 * float(ref.grad.abs().max()), 1e-3 / 768)
        assert float((x.grad.double() - ref.grad).abs().max()) <= tol


@needs_numba
def test_a_learnt_target_keeps_its_gradient_on_the_fast_path():
    """numba's SSIM differentiates the render only: a target with a gradient of its own (the
    joint baseline's per-view fields) takes the eager SSIM, so its gradient is the eager one."""
    g = torch.Generator().manual_seed(4)
    a, b = torch.rand(12, 14, 3, generator=g), torch.rand(12, 14, 3, generator=g)
    grads = []
    for fast in (False, True):
        t = b.clone().requires_grad_(True)
        training_loss(a, t, 0.2, fast_ssim=_numba_ssim().ssim_term if fast else None).backward()
        grads.append(t.grad)
    assert torch.equal(grads[0], grads[1]) and float(grads[0].abs().sum()) > 0
