"""numba kernels of the training loss's SSIM term (imported by :mod:`.numba_ssim` only, after
numba's cache has been pointed at RecGS's folder).

The same sums as :func:`.losses.ssim_map` (INRIA's SSIM: 11-tap Gaussian window, zero
padding), in the same order: each separable pass starts from the first tap and adds the
others in turn (a horizontal pass reads a zero-padded copy of the row, as the eager path's
shifted adds do; a vertical pass skips the taps outside the image, where the eager path adds
exact zeros). What the eager path does in ~60 tensor operations a step (five blurred maps
forward, three backward, each pass a full read and write of every plane) is four passes here,
each a loop per map and tap over a contiguous row, which LLVM turns into SIMD code.

Layout: the images are (H, W, C) float32 as the rasterizer gives them, the intermediate maps
planar (k, C, H, W); every kernel works on a range ``[lo, hi)`` of the C * H planar rows
(channel-major), serial and without the GIL, so
:func:`..render.numba_kernels.run_ranges` can run ranges on threads.

* :func:`forward_rows`: the horizontal pass of the five maps a, b, a², b², ab;
* :func:`forward_cols`: the vertical pass, the SSIM of every pixel, and the loss's gradient
  with respect to the three maps that depend on the render (mu_a, E[a²], E[ab]), scaled by
  each pixel's loss coefficient;
* :func:`backward_rows` / :func:`backward_cols`: the blur of those three gradients (the blur
  is its own adjoint) and the chain rule through a, a² and ab.
"""
from __future__ import annotations

import numba
import numpy as np

F32 = np.float32


@numba.njit(inline="always", error_model="numpy")
def _hblur(src, taps, acc):
    """acc (W,) <- the horizontal blur of the zero-padded row ``src`` (W + 2r,): the first
    tap's product, then the others added in turn (as the eager path's shifted adds)."""
    w = acc.shape[0]
    wt = taps[0]
    for x in range(w):
        acc[x] = wt * src[x]
    for t in range(1, taps.shape[0]):
        wt = taps[t]
        for x in range(w):
            acc[x] += wt * src[x + t]


@numba.njit(inline="always", error_model="numpy")
def _vblur(src, c, y, taps, acc):
    """acc (K, W) <- the vertical blur at row ``y`` of the planes ``src[k, c]``, k < K (zero
    padding: the first tap sets each sum, those outside the image add nothing)."""
    h = src.shape[2]
    w = acc.shape[1]
    r = taps.shape[0] // 2
    for k in range(acc.shape[0]):
        first = True
        for t in range(taps.shape[0]):
            yy = y + t - r
            if yy < 0 or yy >= h:
                if first:   # the eager path's first product is with the zero padding
                    for x in range(w):
                        acc[k, x] = F32(0.0)
                    first = False
                continue
            wt = taps[t]
            if first:
                for x in range(w):
                    acc[k, x] = wt * src[k, c, yy, x]
                first = False
            else:
                for x in range(w):
                    acc[k, x] += wt * src[k, c, yy, x]


@numba.njit(error_model="numpy", nogil=True, cache=True)
def forward_rows(lo, hi, a, b, taps, tmp):
    """tmp (5, C, H, W) <- horizontal blur of a, b, a*a, b*b, a*b ((H, W, C) each), rows
    lo..hi of C * H."""
    h, w, n_c = a.shape
    r = taps.shape[0] // 2
    src = np.zeros((5, w + 2 * r), np.float32)
    acc = np.empty(w, np.float32)
    for row in range(lo, hi):
        c = row // h
        y = row - c * h
        for x in range(w):
            av = a[y, x, c]
            bv = b[y, x, c]
            src[0, x + r] = av
            src[1, x + r] = bv
            src[2, x + r] = av * av
            src[3, x + r] = bv * bv
            src[4, x + r] = av * bv
        for k in range(5):
            _hblur(src[k], taps, acc)
            for x in range(w):
                tmp[k, c, y, x] = acc[x]


@numba.njit(error_model="numpy", nogil=True, cache=True)
def forward_cols(lo, hi, tmp, taps, c1, c2, weight, norm, row_sums, grads):
    """Vertical pass of ``tmp`` and the SSIM S of each pixel, rows lo..hi of C * H.

    The loss is sum over pixels and channels of k (1 - S), k = ``norm`` * ``weight`` (H, W)
    (``norm`` alone where ``weight`` is empty). Writes ``row_sums`` (C * H,) float64, each
    row's share of the loss, and ``grads`` (3, C, H, W): the loss's gradient with respect to
    mu_a, E[a²] and E[ab] at each pixel."""
    weighted = weight.shape[0] > 0
    _, n_c, h, w = tmp.shape
    m = np.empty((5, w), np.float32)
    for row in range(lo, hi):
        c = row // h
        y = row - c * h
        _vblur(tmp, c, y, taps, m)
        total = 0.0
        for x in range(w):
            mu_a = m[0, x]
            mu_b = m[1, x]
            mu_aa = mu_a * mu_a
            mu_bb = mu_b * mu_b
            mu_ab = mu_a * mu_b
            a1 = F32(2.0) * mu_ab + c1
            a2 = F32(2.0) * (m[4, x] - mu_ab) + c2
            b1 = mu_aa + mu_bb + c1
            b2 = (m[2, x] - mu_aa) + (m[3, x] - mu_bb) + c2
            den = b1 * b2
            s = (a1 * a2) / den
            k = norm * weight[y, x] if weighted else norm
            total += k * (F32(1.0) - s)
            # d(coef (1 - S)) = -coef dS; dS/dmu_a = 2 (mu_b (a2 - a1) - mu_a S (b2 - b1)) / den,
            # written so that both differences are of the maps' size (the form with 1/b1 - 1/b2
            # cancels two terms of order 1/C2 ~ 1e3 where the render matches the target)
            grads[0, c, y, x] = -k * F32(2.0) * (mu_b * (a2 - a1) - mu_a * s * (b2 - b1)) / den
            grads[1, c, y, x] = k * s / b2
            grads[2, c, y, x] = -k * F32(2.0) * a1 / den
        row_sums[row] = total


@numba.njit(error_model="numpy", nogil=True, cache=True)
def backward_rows(lo, hi, grads, taps, tmp):
    """tmp (3, C, H, W) <- horizontal blur of ``grads``, rows lo..hi of C * H."""
    _, n_c, h, w = grads.shape
    r = taps.shape[0] // 2
    src = np.zeros(w + 2 * r, np.float32)
    acc = np.empty(w, np.float32)
    for row in range(lo, hi):
        c = row // h
        y = row - c * h
        for k in range(3):
            for x in range(w):
                src[x + r] = grads[k, c, y, x]
            _hblur(src, taps, acc)
            for x in range(w):
                tmp[k, c, y, x] = acc[x]


@numba.njit(error_model="numpy", nogil=True, cache=True)
def backward_cols(lo, hi, tmp, taps, a, b, scale, grad_a):
    """grad_a (H, W, C) <- scale * (B g_mu + 2 a B g_aa + b B g_ab), with B the vertical pass
    of ``tmp``, rows lo..hi of C * H."""
    _, n_c, h, w = tmp.shape
    m = np.empty((3, w), np.float32)
    for row in range(lo, hi):
        c = row // h
        y = row - c * h
        _vblur(tmp, c, y, taps, m)
        for x in range(w):
            grad_a[y, x, c] = scale * (m[0, x] + F32(2.0) * a[y, x, c] * m[1, x] + b[y, x, c] * m[2, x])
