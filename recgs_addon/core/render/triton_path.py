"""The autograd Functions of the GPU path, each one launch of Triton's kernels
(:mod:`.triton_kernels`) forward and one backward: projection + SH colour of the visible
Gaussians (:class:`_ProjectTriton`) and compositing over every tile (:class:`_CompositeTriton`).
Culling and binning before them are Triton kernels too, without autograd;
:func:`.rasterizer._render_triton` runs a view through them."""
from __future__ import annotations

import torch

from .tiles import _N_GEOM


class _ProjectTriton(torch.autograd.Function):
    """Projection and colour of the visible Gaussians through Triton's kernels (float32 rows,
    float64 maths, hand-written backward): the twin of numba's :class:`.numba_path._ProjectNumba`.
    Inputs: the visible rows of means, log_scales, quats, logit_opacities, sh (V, K, 3), and
    ``setup`` = (kernels, SH degree, :meth:`.triton_kernels.TritonKernels.view_arrays`, width,
    height, antialiased). Outputs: means2d (V, 2) float32, geo (V, 4) (l11, l21, l22,
    opacity), depth (V,), colour (V, 3), and pos (V, 2) float64 (the centres compositing uses;
    no gradient)."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, logits, sh, setup):
        rows = tuple(x.detach().to(torch.float32).contiguous() for x in (means, log_scales, quats, logits, sh))
        tk, deg, view, width, height, aa = setup
        pos, geo, depth, colour = tk.project_forward(rows, deg, view, width, height, aa)
        ctx.rows, ctx.setup = rows, setup
        ctx.mark_non_differentiable(pos)
        return pos.to(torch.float32), geo, depth, colour, pos

    @staticmethod
    def backward(ctx, g_m2d, g_geo, g_depth, g_colour, _g_pos):
        tk, deg, view, width, height, aa = ctx.setup
        rows = ctx.rows
        v, dev = rows[0].shape[0], rows[0].device

        def arr(g, *shape):
            if g is None:
                return torch.zeros(*shape, dtype=torch.float32, device=dev)
            return g.detach().to(torch.float32).contiguous()

        grads = tk.project_backward(rows, deg, view, width, height, aa, arr(g_m2d, v, 2), arr(g_geo, v, 4),
                                    arr(g_depth, v), arr(g_colour, v, 3))
        ctx.rows = None
        return tuple(grads) + (None,)


class _CompositeTriton(torch.autograd.Function):
    """:class:`.composite._Composite` through Triton's kernels (float32 compositing, whatever
    the inputs' dtype; gradients come back in it). Inputs: means2d_full (N, 2) [gradient
    only], chol (V, 3), opacity (V,), values (V, C), pos64 (V, 2) detached centres, ids (V,),
    plan (``tile_start`` and ``isect_rows``: :meth:`.triton_kernels.TritonKernels.bin`), kernels. Output: (H, W, C) accumulated values."""

    @staticmethod
    def forward(ctx, means2d_full, chol, opacity, values, pos64, ids, plan, tk):
        ts = plan.tile_size
        geo = torch.cat([chol.detach(), opacity.detach().unsqueeze(1)], 1).to(torch.float32).contiguous()
        vals = values.detach().to(torch.float32).contiguous()
        pos = pos64.detach().to(torch.float64).contiguous()
        out, last = tk.forward(plan.tile_start, plan.isect_rows, pos, geo, vals, ts, plan.tiles_x, plan.tiles_y)
        ctx.arrays = (pos, geo, vals, out, last)
        ctx.plan, ctx.tk = plan, tk
        ctx.n = means2d_full.shape[0]
        ctx.dtypes = (means2d_full.dtype, chol.dtype, opacity.dtype, values.dtype)
        ctx.save_for_backward(ids)
        return out[:, :plan.height, :plan.width].permute(1, 2, 0).to(values.dtype).contiguous()

    @staticmethod
    def backward(ctx, g_img):
        (ids,) = ctx.saved_tensors
        pos, geo, vals, out, last = ctx.arrays
        plan, tk = ctx.plan, ctx.tk
        ts = plan.tile_size
        g_out = torch.zeros_like(out)
        g_out[:, :plan.height, :plan.width] = g_img.detach().permute(2, 0, 1).to(torch.float32)
        # the padding beyond the image has no gradient: its pixels' passes are not replayed
        # (the same gradients, and no blending weight counted outside the image)
        last[plan.height:] = 0
        last[:, plan.width:] = 0
        d = tk.backward(plan.tile_start, plan.isect_rows, pos, geo, vals, ts, plan.tiles_x, plan.tiles_y,
                        out, last, g_out, weights=plan.weights is not None)
        ctx.arrays = None
        if plan.weights is not None:
            plan.weights.index_add_(0, ids, d[-1].to(plan.weights.dtype))
            d = d[:-1]
        t_m, t_c, t_o, t_v = ctx.dtypes
        d_means2d = torch.zeros(ctx.n, 2, dtype=t_m, device=d.device)
        d_means2d.index_copy_(0, ids, d[0:2].t().to(t_m))
        return (d_means2d, d[2:5].t().to(t_c), d[5].to(t_o), d[_N_GEOM:].t().to(t_v),
                None, None, None, None)
