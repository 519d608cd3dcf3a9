"""Front-to-back compositing of the binned Gaussians with a hand-written backward
(:class:`_Composite`): builds the slot tables of a :class:`.tiles._Plan` and runs a kernel set
(:mod:`.kernels`) over its chunks."""
from __future__ import annotations

import torch

from .chunks import _chunk_weights
from .tiles import _N_GEOM, _pixel_offsets, _slot_tables, _slot_tables_compiled


# ----------------------------------------------------------------------------------------
# Compositing with a hand-written backward
# ----------------------------------------------------------------------------------------

class _Composite(torch.autograd.Function):
    """Front-to-back compositing of the binned Gaussians.

    Inputs: means2d_full (N, 2) [gradient only; positions come from pos64], chol (V, 3),
    opacity (V,), values (V, C), pos64 (V, 2) float64 detached centres, ids (V,), plan,
    kernels, low_memory. Output: (H, W, C) accumulated ``sum_i v_i alpha_i T_i``.

    The forward keeps, per chunk, the Gaussian falloff g and the transmittance in front of
    every (pixel, Gaussian) pair (8 bytes a pair) so the backward needs neither exp nor the
    product scan; with ``low_memory`` it keeps nothing and replays the forward chunk by chunk.
    Either way the backward sees exactly the forward's alphas, skips and stops.
    """

    @staticmethod
    def forward(ctx, means2d_full, chol, opacity, values, pos64, ids, plan, kern, low_memory):
        dtype = values.dtype
        n_c = values.shape[1]
        ts = plan.tile_size
        n_vis = chol.shape[0]
        sr, st = plan.slot_rows, plan.slot_tiles
        # Slot tables, planar: geometry (6, S), values (C, S). Row n_vis of the per-Gaussian
        # tables is all zeros (opacity 0): padding slots point there.
        per_row = torch.cat([chol.t(), opacity.unsqueeze(0), values.t()], dim=0)
        per_row = torch.cat([per_row, per_row.new_zeros(per_row.shape[0], 1)], dim=1)
        pos = torch.cat([pos64.t(), pos64.new_zeros(2, 1)], dim=1)
        slot_fn = _slot_tables_compiled if kern.compiled else _slot_tables
        tab = slot_fn(sr, st, pos, per_row, plan.tiles_x, ts)
        geo, vals = tab[:_N_GEOM], tab[_N_GEOM:]
        pxl, pyl = _pixel_offsets(ts, dtype, values.device)
        n_tiles = plan.tiles_x * plan.tiles_y
        acc = torch.zeros(n_c, n_tiles, ts * ts, dtype=dtype, device=values.device)
        state = []
        for tiles, tc, g, off in plan.chunks:
            geo_c = geo[:, off:off + tc * g].view(_N_GEOM, tc, g)
            vals_c = vals[:, off:off + tc * g].view(n_c, tc, g)
            out, fall, t_excl = kern.forward(pxl, pyl, geo_c, vals_c)
            acc.index_copy_(1, tiles, out)
            if not low_memory:
                state.append((fall, t_excl))
        ctx.save_for_backward(geo, vals, ids)
        ctx.state = state
        ctx.plan = plan
        ctx.kern = kern
        ctx.n = means2d_full.shape[0]
        ctx.n_vis = n_vis
        img = acc.view(n_c, plan.tiles_y, plan.tiles_x, ts, ts).permute(1, 3, 2, 4, 0)
        img = img.reshape(plan.tiles_y * ts, plan.tiles_x * ts, n_c)
        return img[:plan.height, :plan.width].contiguous()

    @staticmethod
    def backward(ctx, g_img):
        geo, vals, ids = ctx.saved_tensors
        plan, kern, state = ctx.plan, ctx.kern, ctx.state
        dtype = geo.dtype
        n_c = vals.shape[0]
        ts = plan.tile_size
        hp, wp = plan.tiles_y * ts, plan.tiles_x * ts
        dev = g_img.device

        def tiled(img):
            """(H, W, C) image -> (C, tiles, P), padded to whole tiles with zeros."""
            pad = torch.zeros(hp, wp, img.shape[-1], dtype=dtype, device=dev)
            pad[:plan.height, :plan.width] = img
            pad = pad.view(plan.tiles_y, ts, plan.tiles_x, ts, img.shape[-1]).permute(4, 0, 2, 1, 3)
            return pad.reshape(img.shape[-1], plan.tiles_y * plan.tiles_x, ts * ts)

        g_tiles = tiled(g_img)
        if plan.weights is not None:   # (tiles, P): pixels inside the image, not its padding
            inside = tiled(torch.ones(plan.height, plan.width, 1, dtype=dtype, device=dev))[0]
        pxl, pyl = _pixel_offsets(ts, dtype, dev)
        n_vis = ctx.n_vis
        n_slots = geo.shape[1]
        # Per-slot gradients, planar: rows 0..5 geometry, 6.. values.
        d_slot = torch.empty(_N_GEOM + n_c + int(plan.weights is not None), n_slots, dtype=dtype, device=dev)
        for k, (tiles, tc, g, off) in enumerate(plan.chunks):
            geo_c = geo[:, off:off + tc * g].view(_N_GEOM, tc, g)
            vals_c = vals[:, off:off + tc * g].view(n_c, tc, g)
            if state:
                fall, t_excl = state[k]
            else:
                _, fall, t_excl = kern.forward(pxl, pyl, geo_c, vals_c)
            dg, dv = kern.backward(pxl, pyl, geo_c, vals_c, fall, t_excl,
                                   g_tiles.index_select(1, tiles))
            d_slot[:_N_GEOM, off:off + tc * g] = dg.reshape(_N_GEOM, -1)
            d_slot[_N_GEOM:_N_GEOM + n_c, off:off + tc * g] = dv.reshape(n_c, -1)
            if plan.weights is not None:
                w_c = _chunk_weights(geo_c, fall, t_excl, inside.index_select(0, tiles))
                d_slot[-1, off:off + tc * g] = w_c.reshape(-1)
        ctx.state = None
        d_rows = torch.zeros(d_slot.shape[0], n_vis + 1, dtype=dtype, device=dev)
        d_rows.index_add_(1, plan.slot_rows, d_slot)
        d_rows = d_rows[:, :n_vis]
        if plan.weights is not None:
            plan.weights.index_add_(0, ids, d_rows[-1].to(plan.weights.dtype))
        d_means2d = torch.zeros(ctx.n, 2, dtype=dtype, device=dev)
        d_means2d.index_copy_(0, ids, d_rows[0:2].t())
        return (d_means2d, d_rows[2:5].t(), d_rows[5], d_rows[_N_GEOM:_N_GEOM + n_c].t(),
                None, None, None, None, None)
