"""The autograd Functions of numba's path (float32): projection + SH colour of the visible
Gaussians (:class:`_ProjectNumba`) and compositing over every tile (:class:`_CompositeNumba`),
each a call into :mod:`.numba_kernels` forward and one backward.
:func:`.rasterizer._render_numba` runs a view through them."""
from __future__ import annotations

import numpy as np
import torch

from .tiles import _N_GEOM


class _ProjectNumba(torch.autograd.Function):
    """Projection and colour of the visible Gaussians through numba's kernels (float32 rows,
    float64 maths, hand-written backward): the twin of projection._project_rows plus the SH
    colour. Inputs: the visible rows of means, log_scales, quats, logit_opacities, sh
    (V, K, 3), and ``setup`` = (kernels, SH degree, viewmat (4, 4) float64, K float64, camera
    centre, width, height, near, antialiased). Outputs: means2d (V, 2) float32, geo (V, 4)
    (l11, l21, l22, opacity), depth (V,), colour (V, 3), and pos (V, 2) float64 (the centres
    binning and compositing use; no gradient)."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, logits, sh, setup):
        rows = tuple(x.detach().contiguous().numpy() for x in (means, log_scales, quats, logits, sh))
        nk, deg, *view = setup
        pos, geo, depth, colour = nk.project_forward(rows, deg, *view)
        ctx.rows, ctx.setup = rows, setup
        pos = torch.from_numpy(pos)
        ctx.mark_non_differentiable(pos)
        return (pos.to(torch.float32), torch.from_numpy(geo), torch.from_numpy(depth),
                torch.from_numpy(colour), pos)

    @staticmethod
    def backward(ctx, g_m2d, g_geo, g_depth, g_colour, _g_pos):
        nk, deg, *view = ctx.setup
        v = ctx.rows[0].shape[0]

        def arr(g, shape):
            if g is None:
                return np.zeros(shape, np.float32)
            return g.detach().to(torch.float32).contiguous().numpy()

        grads = nk.project_backward(ctx.rows, deg, *view, arr(g_m2d, (v, 2)), arr(g_geo, (v, 4)),
                                    arr(g_depth, (v,)), arr(g_colour, (v, 3)))
        ctx.rows = None
        return tuple(torch.from_numpy(g) for g in grads) + (None,)


class _CompositeNumba(torch.autograd.Function):
    """:class:`.composite._Composite` through numba's kernels (float32): one kernel call over every tile
    forward, one backward, nothing kept per pair (the backward replays each pixel's pass up to
    where the forward stopped it: ``last``). Inputs: means2d_full (N, 2) [gradient only],
    geo (V, 4) (l11, l21, l22, opacity), values (V, C), pos64 (V, 2) float64 detached centres,
    ids (V,), plan (unchunked), kernels. Output: (H, W, C) accumulated values."""

    @staticmethod
    def forward(ctx, means2d_full, geo, values, pos64, ids, plan, nk):
        ts = plan.tile_size
        geo_np = geo.detach().contiguous().numpy()
        vals = values.detach().contiguous().numpy()
        pos = pos64.detach().contiguous().numpy()
        tile_start, rows = plan.tile_start.numpy(), plan.isect_rows.numpy()
        out, last = nk.forward(tile_start, rows, pos, geo_np, vals, ts, plan.tiles_x, plan.tiles_y)
        ctx.arrays = (tile_start, rows, pos, geo_np, vals, out, last)
        ctx.plan = plan
        ctx.nk = nk
        ctx.n = means2d_full.shape[0]
        ctx.save_for_backward(ids)
        img = torch.from_numpy(out)[:, :plan.height, :plan.width].permute(1, 2, 0)
        return img.contiguous()

    @staticmethod
    def backward(ctx, g_img):
        (ids,) = ctx.saved_tensors
        tile_start, rows, pos, geo, vals, out, last = ctx.arrays
        plan = ctx.plan
        ts = plan.tile_size
        g_out = np.zeros(out.shape, np.float32)
        g_out[:, :plan.height, :plan.width] = g_img.detach().permute(2, 0, 1).numpy()
        # the padding beyond the image has no gradient: its pixels' passes are not replayed
        # (the same gradients, and no blending weight counted outside the image)
        last[plan.height:] = 0
        last[:, plan.width:] = 0
        d = torch.from_numpy(ctx.nk.backward(tile_start, rows, pos, geo, vals, ts, plan.tiles_x,
                                             out, last, g_out, weights=plan.weights is not None))
        ctx.arrays = None
        if plan.weights is not None:
            plan.weights.index_add_(0, ids, d[-1].to(plan.weights.dtype))
            d = d[:-1]
        d_means2d = torch.zeros(ctx.n, 2, dtype=torch.float32)
        d_means2d.index_copy_(0, ids, d[0:2].t())
        return d_means2d, d[2:_N_GEOM].t(), d[_N_GEOM:].t(), None, None, None, None
