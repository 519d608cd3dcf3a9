"""Per-pair compositing maths of one chunk of tiles, for :class:`.composite._Composite`:
forward (falloff, alpha, front-to-back transmittance, accumulated values) and its hand-written
backward, plus the compositing constants (alpha clamp, transmittance stop). Written once, run
eagerly or through ``torch.compile`` (:mod:`.kernels`)."""
from __future__ import annotations

import torch

from .projection import ALPHA_MIN

#: Alpha is clamped here (INRIA): one Gaussian never makes a pixel fully opaque, which also
#: keeps 1 / (1 - alpha) <= 100 in the backward pass.
ALPHA_MAX = 0.99
#: A pixel stops compositing when the transmittance would fall below this (INRIA); the
#: Gaussian that would cross it is not added.
T_MIN = 1e-4


# ----------------------------------------------------------------------------------------
# Per-pair maths (one chunk of tiles). Written once, run eagerly or through torch.compile.
# Layout: [Tc tiles, G Gaussian slots (depth order), P pixels of the tile]; the geometry is
# planar, geo[k] = (mean x, mean y relative to the tile centre, l11, l21, l22, opacity)[k] of
# shape (Tc, G); padded slots have opacity 0.
# ----------------------------------------------------------------------------------------

def _offsets(pxl, pyl, geo):
    npix = pxl.shape[0]
    dx = pxl.view(1, 1, npix) - geo[0].unsqueeze(2)
    dy = pyl.view(1, 1, npix) - geo[1].unsqueeze(2)
    p1 = geo[2].unsqueeze(2) * dx + geo[3].unsqueeze(2) * dy   # (Tc, G, P)
    p2 = geo[4].unsqueeze(2) * dy
    return dx, dy, p1, p2


def _contract_out(w, vals, fused: bool):
    """out[c, t, p] = sum_g w[t, g, p] vals[c, t, g]."""
    if fused:   # a reduction inductor fuses into the surrounding loop
        return (w.unsqueeze(0) * vals.unsqueeze(3)).sum(2)
    return torch.bmm(w.transpose(1, 2), vals.permute(1, 2, 0)).permute(2, 0, 1)


def _chunk_forward(pxl, pyl, geo, vals, fused: bool = False):
    """Composite one chunk.

    Args:
        pxl, pyl: (P,) pixel-centre coordinates relative to the tile centre.
        geo: (6, Tc, G) geometry (see above). vals: (C, Tc, G) per-slot values, planar.
        fused: contractions as broadcast-reductions (for torch.compile) instead of bmm
            (eager); same numbers up to summation order.
    Returns:
        out (C, Tc, P) = sum_i w_i vals_i, and the state the backward pass needs:
        g (Tc, G, P) Gaussian falloff exp(-q/2) and t_excl (Tc, G, P) transmittance in front.
    """
    _, _, p1, p2 = _offsets(pxl, pyl, geo)
    g = torch.exp(-0.5 * (p1 * p1 + p2 * p2))
    alpha = torch.clamp_max(geo[5].unsqueeze(2) * g, ALPHA_MAX)
    keep = alpha >= ALPHA_MIN
    om = torch.where(keep, 1.0 - alpha, torch.ones_like(alpha))
    # Inclusive product = INRIA's running T * (1 - alpha), same float operations in the same
    # order; it is non-increasing, so ">= T_MIN" marks exactly the samples before the stop.
    t_incl = torch.cumprod(om, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    w = torch.where(keep & (t_incl >= T_MIN), alpha * t_excl, torch.zeros_like(alpha))
    return _contract_out(w, vals, fused), g, t_excl


def _chunk_backward(pxl, pyl, geo, vals, g, t_excl, g_out, fused: bool = False):
    """Gradients of one chunk from the forward state (g, t_excl).

    Args:
        g_out: (C, Tc, P) gradient of the loss wrt the chunk's accumulated values.
    Returns:
        d_geo (6, Tc, G) gradients wrt the geometry, d_vals (C, Tc, G) wrt the values.
    """
    dx, dy, p1, p2 = _offsets(pxl, pyl, geo)
    oa = geo[5].unsqueeze(2) * g
    alpha = torch.clamp_max(oa, ALPHA_MAX)
    om = 1.0 - alpha                                   # >= 0.01
    # t_excl * om is bit-identical to the forward's inclusive product.
    valid = (alpha >= ALPHA_MIN) & (t_excl * om >= T_MIN)
    w = torch.where(valid, alpha * t_excl, torch.zeros_like(alpha))
    if fused:                                          # <dL/dout_p, v_i>
        gv = (vals.unsqueeze(3) * g_out.unsqueeze(2)).sum(0)
    else:
        gv = torch.bmm(vals.permute(1, 2, 0), g_out.permute(1, 0, 2))
    wg = w * gv
    behind = wg.sum(dim=1, keepdim=True) - torch.cumsum(wg, dim=1)   # sum over k > i
    # d out / d alpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) / (1 - alpha_i)
    d_alpha = torch.where(valid, gv * t_excl - behind / om, torch.zeros_like(gv))
    # alpha = min(0.99, o g): no gradient to o or g where the clamp is active.
    d_oa = torch.where(oa <= ALPHA_MAX, d_alpha, torch.zeros_like(d_alpha))
    d_q = -0.5 * oa * d_oa                              # q = p1^2 + p2^2, g = exp(-q/2)
    e1 = d_q * p1
    e2 = d_q * p2
    s1 = e1.sum(dim=2)
    s2 = e2.sum(dim=2)
    d_geo = torch.stack([
        -2.0 * geo[2] * s1,                            # mean x (dx = px - mx)
        -2.0 * (geo[3] * s1 + geo[4] * s2),            # mean y
        2.0 * (e1 * dx).sum(dim=2),                    # l11
        2.0 * (e1 * dy).sum(dim=2),                    # l21
        2.0 * (e2 * dy).sum(dim=2),                    # l22
        (g * d_oa).sum(dim=2),                         # opacity
    ], dim=0)
    if fused:
        d_vals = (w.unsqueeze(0) * g_out.unsqueeze(2)).sum(3)
    else:
        d_vals = torch.bmm(w, g_out.permute(1, 2, 0)).permute(2, 0, 1)
    return d_geo, d_vals


def _chunk_weights(geo, g, t_excl, inside):
    """(Tc, G) blending weight of each slot of one chunk: its ``alpha T`` summed over the tile's
    pixels inside the image (``inside`` (Tc, P), 1 or 0), with the forward's own alphas and
    stop, from the forward state (g, t_excl)."""
    alpha = torch.clamp_max(geo[5].unsqueeze(2) * g, ALPHA_MAX)
    valid = (alpha >= ALPHA_MIN) & (t_excl * (1.0 - alpha) >= T_MIN)
    return (torch.where(valid, alpha * t_excl, torch.zeros_like(alpha)) * inside.unsqueeze(1)).sum(2)
