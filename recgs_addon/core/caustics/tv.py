"""Total-variation denoising (Rudin, Osher & Fatemi 1992), batched, plain torch.

    u = argmin_u  sum_p w_p (u_p - f_p)^2 / 2  +  lam * sum_p |grad u|_p

with the isotropic TV (forward differences, Neumann boundary), solved with the primal-dual
algorithm of Chambolle & Pock (2011) at step sizes tau = sigma = 1 / sqrt(8) (the bound
``tau sigma ||grad||^2 <= 1`` with ``||grad||^2 <= 8``). TV keeps large, coherent structures
(edges, long lines of high contrast) and flattens small, low-contrast ones (noise, fine
texture): what a caustic light network is, against what a model's leftover texture error is.

Shapes: ``f`` and ``w`` are (B, H, W) float tensors; ``w`` >= 0 (0: the pixel carries no
data, its value comes from its neighbours). Float32 throughout (tested against a float64
reference).
"""
from __future__ import annotations

import math
from typing import Optional

import torch

#: Primal and dual step sizes: tau * sigma * 8 = 1 (8 bounds the squared norm of the 2D gradient).
STEP = 1.0 / math.sqrt(8.0)


def grad(u: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) forward differences of ``u`` (B, H, W); zero on the last row / column."""
    g = torch.zeros(u.shape[0], 2, *u.shape[1:], dtype=u.dtype, device=u.device)
    g[:, 0, :, :-1] = u[:, :, 1:] - u[:, :, :-1]
    g[:, 1, :-1, :] = u[:, 1:, :] - u[:, :-1, :]
    return g


def div(p: torch.Tensor) -> torch.Tensor:
    """(B, H, W) divergence, the negative adjoint of :func:`grad`: ``<grad u, p> = -<u, div p>``."""
    px, py = p[:, 0], p[:, 1]
    d = torch.zeros_like(px)
    d[:, :, 0] = px[:, :, 0]
    d[:, :, 1:-1] = px[:, :, 1:-1] - px[:, :, :-2]
    d[:, :, -1] = -px[:, :, -2]
    d[:, 0, :] += py[:, 0, :]
    d[:, 1:-1, :] += py[:, 1:-1, :] - py[:, :-2, :]
    d[:, -1, :] += -py[:, -2, :]
    return d


def tv_energy(u: torch.Tensor, f: torch.Tensor, lam: float, w: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(B,) the ROF objective of ``u`` for data ``f`` (what :func:`tv_denoise` minimises)."""
    w = torch.ones_like(f) if w is None else w
    g = grad(u)
    return (0.5 * w * (u - f) ** 2).sum((1, 2)) + lam * torch.sqrt((g * g).sum(1)).sum((1, 2))


@torch.no_grad()
def tv_denoise(f: torch.Tensor, lam: float, w: Optional[torch.Tensor] = None, iters: int = 200) -> torch.Tensor:
    """ROF denoising of each image of ``f`` (B, H, W) with weight ``lam`` (in the units of
    ``f`` per pixel of edge: a feature survives where its contrast times its area beats
    ``lam`` times its perimeter) and per-pixel data weights ``w`` (B, H, W) or None."""
    if f.dim() != 3:
        raise ValueError(f"expected (B, H, W) images, got shape {tuple(f.shape)}")
    if lam <= 0:
        return f.clone()
    w = torch.ones_like(f) if w is None else w.to(f.dtype)
    if f.shape[1] < 2 or f.shape[2] < 2:
        return f.clone()
    u = f.clone()
    u_bar = u.clone()
    p = torch.zeros(f.shape[0], 2, *f.shape[1:], dtype=f.dtype, device=f.device)
    # the data term is uniformly convex with modulus min(w): Chambolle & Pock's accelerated
    # variant (their algorithm 2) shrinks tau and grows sigma as it goes
    gamma = float(w.min())
    tau = sigma = STEP
    for _ in range(iters):
        p.add_(grad(u_bar), alpha=sigma)
        p.div_(torch.sqrt((p * p).sum(1, keepdim=True)).div_(lam).clamp_min_(1.0))
        tw = tau * w
        u_new = (u + tau * div(p) + tw * f) / (1.0 + tw)
        theta = 1.0 / math.sqrt(1.0 + 2.0 * gamma * tau)
        u_bar = u_new + theta * (u_new - u)
        u = u_new
        tau, sigma = theta * tau, sigma / theta
    return u
