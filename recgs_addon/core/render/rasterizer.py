"""Differentiable Gaussian rasterizer for the CPU, in pure torch (INRIA 3DGS maths).

Entry point: :func:`render`. Design and measured speed: ``docs/dev/rasterizer.md``.

Pipeline
--------
1. :func:`recgs_addon.core.render.projection.project_gaussians` (per Gaussian, float64, autograd):
   a cheap conservative candidate test, then the exact cull on the candidates, EWA-project,
   0.3 px dilation, opacity-aware radius, stable depth sort.
2. Colours from spherical harmonics (:mod:`recgs_addon.core.model.sh`, autograd).
3. Binning (no gradient): every visible Gaussian is listed in each tile that its opacity-aware
   ellipse reaches (exact per tile row, not the bounding square); the list is stably sorted by
   tile, so inside a tile it stays in depth order (ties by index).
4. Compositing (:class:`_Composite`, hand-written backward): tiles are grouped into chunks of
   similar list length; each chunk is a padded batch ``[tiles, Gaussians, pixels per tile]``.
   Front-to-back transmittance is an inclusive ``cumprod`` over the depth axis, which is the
   same sequence of float multiplications as INRIA's loop, and makes its early stop exact:
   the running product is non-increasing, so "stop at the first Gaussian whose
   ``T (1 - alpha)`` would drop below 1e-4, without adding it" selects exactly the samples
   whose inclusive product is >= 1e-4. The backward uses the forward's falloff and
   transmittance (or, with ``low_memory``, replays the forward chunk by chunk) and
   ``dC/dalpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) / (1 - alpha_i)`` with a reverse
   cumulative sum; ``1 - alpha >= 0.01`` because alpha is clamped at 0.99.

The per-pair maths of step 4 runs either eagerly or through ``torch.compile`` (which fuses
it into a few C++ loops, about 10-30x faster here); both give the same numbers to ~1e-7.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np
import torch

from .projection import ALPHA_MIN, _index_rows, allow_variants, camera_centre, project_gaussians
from ..model.sh import eval_sh_colour

#: Alpha is clamped here (INRIA): one Gaussian never makes a pixel fully opaque, which also
#: keeps 1 / (1 - alpha) <= 100 in the backward pass.
ALPHA_MAX = 0.99
#: A pixel stops compositing when the transmittance would fall below this (INRIA); the
#: Gaussian that would cross it is not added.
T_MIN = 1e-4
#: Default near plane (scene units), INRIA.
DEFAULT_NEAR = 0.2
#: Default tile size in pixels (fastest measured on the CPU, benchmarks/RESULTS.md#rasterizer-design-trials).
DEFAULT_TILE_SIZE = 4
#: Default number of (pixel, Gaussian) pairs per chunk: bounds the temporaries of a pass to
#: roughly 60 bytes x this and keeps the working set in cache (2^16..2^20 measured).
DEFAULT_CHUNK_PAIRS = 1 << 18
#: Number of per-Gaussian attributes in the intersection table before the values:
#: (mean x, mean y relative to the tile centre, l11, l21, l22, opacity).
_N_GEOM = 6


class RenderOutput(NamedTuple):
    """Result of :func:`render`.

    Attributes:
        rgb: (H, W, 3) colour, ``sum_i c_i alpha_i T_i + T_final * background``.
        alpha: (H, W) accumulated opacity ``1 - T_final``.
        depth: (H, W) expected depth ``sum_i z_i alpha_i T_i`` (camera-space z, scene units),
            NOT normalised by alpha (divide by ``alpha`` for the depth of the visible surface).
        means2d: (N, 2) projected centres in pixels (0 for culled Gaussians). When the
            parameters require grad its ``.grad`` is filled by ``backward()`` (retain_grad),
            in pixels: multiply x by W/2 and y by H/2 for INRIA's NDC-space gradient to which
            its 2e-4 densification threshold refers.
        radii: (N,) int32 opacity-aware screen radius in pixels, 0 = culled.
        stats: dict with ``visible`` (Gaussians), ``intersections`` (tile, Gaussian) pairs,
            ``pairs`` (pixel, Gaussian) pairs evaluated per pass incl. padding, ``chunks``,
            ``compiled`` (bool).
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    stats: dict


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


class _Kernels(NamedTuple):
    forward: object
    backward: object
    compiled: bool
    #: numba's whole-view kernels (:class:`.numba_kernels.NumbaKernels`): they replace the
    #: per-chunk ones above for float32 renders (float64 ones take the eager kernels)
    numba: object = None


_KERNEL_CACHE: dict = {}


def _mark_dynamic(*tensors_dims):
    """Tell torch.compile which dims vary (Tc, G) so it compiles once, keeping P static."""
    mark = torch._dynamo.maybe_mark_dynamic
    for t, dims in tensors_dims:
        for d in dims:
            mark(t, d)


def _compiled_kernels() -> _Kernels:
    allow_variants()
    fwd_c = torch.compile(_chunk_forward, fullgraph=True, dynamic=False)
    bwd_c = torch.compile(_chunk_backward, fullgraph=True, dynamic=False)

    # Always without autograd (also inside autograd.Function), so one graph per kernel.
    def fwd(pxl, pyl, geo, vals):
        _mark_dynamic((geo, (1, 2)), (vals, (1, 2)))
        with torch.no_grad():
            return fwd_c(pxl, pyl, geo, vals, True)

    def bwd(pxl, pyl, geo, vals, g, t_excl, g_out):
        _mark_dynamic((geo, (1, 2)), (vals, (1, 2)), (g, (0, 1)), (t_excl, (0, 1)),
                      (g_out, (1,)))
        with torch.no_grad():
            return bwd_c(pxl, pyl, geo, vals, g, t_excl, g_out, True)

    return _Kernels(fwd, bwd, True)


def _smoke_test(kern: _Kernels) -> None:
    """Run the kernels once on a small input (forces compilation, surfaces failures)."""
    gen = torch.Generator().manual_seed(0)
    pxl = torch.arange(4, dtype=torch.float32) - 1.5
    geo = torch.rand(6, 3, 5, generator=gen)
    vals = torch.rand(5, 3, 5, generator=gen)
    out, g, te = kern.forward(pxl, pxl, geo, vals)
    kern.backward(pxl, pxl, geo, vals, g, te, torch.ones_like(out))


def _smoke_render() -> None:
    """A tiny compiled render + backward (compiles projection, SH, binning, slot tables)."""
    gen = torch.Generator().manual_seed(0)
    n = 3
    params = [torch.rand(n, 3, generator=gen) * 0.2 + torch.tensor([0.0, 0.0, 2.0]),
              torch.full((n, 3), -2.0), torch.rand(n, 4, generator=gen),
              torch.zeros(n), torch.rand(n, 4, 3, generator=gen)]
    params = [p.requires_grad_() for p in params]
    K = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    out = render(*params, torch.eye(4), K, 8, 8, compiled=True)
    out.rgb.sum().backward()


def get_kernels(compiled: Optional[bool]) -> _Kernels:
    """The per-pair kernels: eager (``compiled=False``), ``torch.compile``d (``True``, raises
    if compilation fails), compiled-if-possible (``None``, warns once and falls back) or
    numba's (``"numba"``: no C++ compiler needed; the rest of the render runs eagerly)."""
    if compiled is False:
        return _Kernels(_chunk_forward, _chunk_backward, False)
    if compiled == "numba":   # compiled without a C++ compiler; eager if numba is missing
        from . import numba_kernels
        nk = numba_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN)
        if nk is None:
            if "warned_numba" not in _KERNEL_CACHE:
                warnings.warn(f"numba kernels unavailable ({numba_kernels.error()!r}); using the eager rasterizer")
                _KERNEL_CACHE["warned_numba"] = True
            return _Kernels(_chunk_forward, _chunk_backward, False)
        return _Kernels(_chunk_forward, _chunk_backward, False, numba=nk)
    if "compiled" not in _KERNEL_CACHE:
        try:
            kern = _compiled_kernels()
            # the first render may come from inside torch.no_grad() (an evaluation); the
            # smoke tests need autograd, or a working compiler is taken for a broken one
            with torch.enable_grad():
                _smoke_test(kern)
                _KERNEL_CACHE["compiled"] = kern
                _smoke_render()      # the per-Gaussian compiled functions too
        except Exception as exc:  # no compiler, unsupported platform, ...
            _KERNEL_CACHE["compiled"] = exc
    kern = _KERNEL_CACHE["compiled"]
    if isinstance(kern, Exception):
        if compiled:
            raise RuntimeError("torch.compile of the rasterizer kernels failed") from kern
        if "warned" not in _KERNEL_CACHE:
            warnings.warn(f"torch.compile unavailable ({type(kern).__name__}: {kern}); "
                          "using the eager rasterizer (same results, slower)")
            _KERNEL_CACHE["warned"] = True
        return _Kernels(_chunk_forward, _chunk_backward, False)
    return kern


def numba_kernels_ready() -> bool:
    """Whether ``compiled="numba"`` runs numba's kernels here (numba installed and working)."""
    from . import numba_kernels
    return numba_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN) is not None


def _sh_fn(compiled: bool):
    """SH colour evaluation, eager or compiled (per Gaussian, fused forward and backward)."""
    if not compiled:
        return eval_sh_colour
    if "sh" not in _KERNEL_CACHE:
        allow_variants()
        _KERNEL_CACHE["sh"] = torch.compile(eval_sh_colour, dynamic=True)
    return _KERNEL_CACHE["sh"]


# ----------------------------------------------------------------------------------------
# Binning
# ----------------------------------------------------------------------------------------

@dataclass
class _Plan:
    """Tile binning of one view (no gradients; built once per render).

    The padded per-chunk batches are laid out back to back in one slot array: chunk k covers
    slots ``[offset, offset + Tc * G)`` as a (Tc, G) block, tiles ``tiles`` (Tc,), and slot s
    holds the Gaussian ``slot_rows[s]`` (a visible row; ``n_vis`` = padding, opacity 0).
    """

    width: int
    height: int
    tile_size: int
    tiles_x: int
    tiles_y: int
    n_vis: int
    intersections: int = 0
    chunks: list = field(default_factory=list)   # [(tiles (Tc,), Tc, G, offset)]
    slot_rows: Optional[torch.Tensor] = None     # (S,) int64
    slot_tiles: Optional[torch.Tensor] = None    # (S,) int64 tile of each slot
    pairs: int = 0
    #: numba's path (no chunks, no padding): the intersections in (tile, depth) order, as the
    #: visible row of each (M,) int32, and each tile's offset into them (n_tiles + 1,) int64
    isect_rows: Optional[torch.Tensor] = None
    tile_start: Optional[torch.Tensor] = None


def _expand(counts: torch.Tensor):
    """For counts (n,): (owner (sum,), local index 0..count-1 within its owner (sum,))."""
    owner = torch.repeat_interleave(torch.arange(counts.shape[0], device=counts.device), counts)
    start = torch.cumsum(counts, 0) - counts
    return owner, torch.arange(owner.shape[0], device=counts.device) - start.index_select(0, owner)


def _row_spans(trow, ts: int, bbox, u, v, cov2d, extent):
    """Tiles reached in each tile row: the ellipse ``d^T cov^-1 d <= extent`` cut to the row's
    band of pixel-centre y is an interval in x (exact, from the ellipse's left and right
    boundary curves). Returns (first tile column (R,), number of tiles (R,), 0 if none)."""
    A, B, C, D = cov2d.unbind(-1)
    x0, x1, y0, y1 = bbox.unbind(-1)
    # Band of pixel-centre y offsets covered by this tile row (and the bbox).
    lo = torch.maximum(trow * ts, y0).to(torch.float64) + 0.5 - v
    hi = torch.minimum(trow * ts + ts - 1, y1).to(torch.float64) + 0.5 - v
    ylim = torch.sqrt(C * extent)
    empty = (lo > ylim) | (hi < -ylim)
    lo = torch.clamp(torch.minimum(lo, ylim), min=-ylim)
    hi = torch.clamp(torch.maximum(hi, -ylim), max=ylim)
    # Left/right boundary x(dy) = (B dy -/+ sqrt(D (C ext - dy^2))) / C, convex/concave in dy,
    # extreme at dy = -/+ B sqrt(ext / A): clamp that into the band.
    d_ext = B * torch.sqrt(extent / A)
    dl = torch.minimum(torch.maximum(-d_ext, lo), hi)
    dr = torch.minimum(torch.maximum(d_ext, lo), hi)
    xl = (B * dl - torch.sqrt(torch.clamp_min(D * (C * extent - dl * dl), 0.0))) / C
    xr = (B * dr + torch.sqrt(torch.clamp_min(D * (C * extent - dr * dr), 0.0))) / C
    i0 = torch.maximum(torch.ceil(u + xl - 0.5).to(torch.int64), x0)
    i1 = torch.minimum(torch.floor(u + xr - 0.5).to(torch.int64), x1)
    tx0 = torch.div(i0, ts, rounding_mode="floor")
    ntx = torch.where(empty | (i0 > i1), torch.zeros_like(i0),
                      torch.div(i1, ts, rounding_mode="floor") - tx0 + 1)
    return tx0, ntx


def _tile_intersections(proj, width: int, height: int, ts: int, compiled: bool):
    """(row, tile id) of every (visible Gaussian, tile) whose pixels the ellipse may reach."""
    bbox = proj.bbox
    ty0 = torch.div(bbox[:, 2], ts, rounding_mode="floor")
    row_of, k = _expand(torch.div(bbox[:, 3], ts, rounding_mode="floor") - ty0 + 1)
    trow = ty0.index_select(0, row_of) + k
    spans = _row_spans_compiled if compiled else _row_spans
    tx0, ntx = spans(trow, ts, bbox.index_select(0, row_of),
                     *proj.means2d.detach().index_select(0, row_of).unbind(-1),
                     proj.cov2d.index_select(0, row_of), proj.extent.index_select(0, row_of))
    seg, j = _expand(ntx)
    tile = (trow * -(-width // ts) + tx0).index_select(0, seg) + j
    return row_of.index_select(0, seg), tile


def _row_spans_compiled(*args):
    if "spans" not in _KERNEL_CACHE:
        _KERNEL_CACHE["spans"] = torch.compile(_row_spans, dynamic=True)
    with torch.no_grad():
        return _KERNEL_CACHE["spans"](*args)


def _build_plan(proj, width: int, height: int, tile_size: int, chunk_pairs: int,
                compiled: bool = False) -> _Plan:
    ts = tile_size
    tiles_x = -(-width // ts)
    tiles_y = -(-height // ts)
    n_tiles = tiles_x * tiles_y
    n_vis = proj.ids.shape[0]
    rows, tile = _tile_intersections(proj, width, height, ts, compiled)
    m = rows.shape[0]
    plan = _Plan(width, height, ts, tiles_x, tiles_y, n_vis, intersections=m)
    if m == 0:
        plan.slot_rows = torch.zeros(0, dtype=torch.int64, device=rows.device)
        plan.slot_tiles = torch.zeros(0, dtype=torch.int64, device=rows.device)
        return plan
    # Rows are in depth order, so a stable sort by tile gives (tile, depth) order.
    # int32 keys: torch's stable CPU sort is a radix sort for them (~20x faster than int64).
    tile_sorted, perm = torch.sort(tile.to(torch.int32), stable=True)
    rows_ext = torch.cat([rows.index_select(0, perm), torch.tensor([n_vis], device=rows.device)])
    tile_count = torch.bincount(tile_sorted, minlength=n_tiles)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    # Chunks of tiles with similar list lengths (longest first) keep padding small.
    order = torch.sort(tile_count, descending=True, stable=True).indices
    counts_sorted = tile_count.index_select(0, order)
    n_nonempty = int(torch.count_nonzero(counts_sorted))
    counts_list = counts_sorted[:n_nonempty].tolist()
    npix = ts * ts
    i = 0
    offset = 0
    slot_parts = []
    tile_parts = []
    while i < n_nonempty:
        g = counts_list[i]
        tc = max(1, min(n_nonempty - i, chunk_pairs // (npix * g)))
        tiles = order[i:i + tc]
        ar = torch.arange(g, device=rows.device)
        slots = tile_start.index_select(0, tiles).unsqueeze(1) + ar
        slots = torch.where(ar < counts_sorted[i:i + tc].unsqueeze(1), slots,
                            torch.full_like(slots, m))
        slot_parts.append(slots.reshape(-1))
        tile_parts.append(tiles.repeat_interleave(g))
        plan.chunks.append((tiles, tc, g, offset))
        offset += tc * g
        i += tc
    plan.slot_rows = rows_ext.index_select(0, torch.cat(slot_parts))
    plan.slot_tiles = torch.cat(tile_parts)
    plan.pairs = offset * npix
    return plan


def _slot_tables(slot_rows, slot_tiles, pos, per_row, tiles_x: int, ts: int):
    """(6 + C, S) planar slot table: centre relative to the slot's tile centre (subtracted in
    float64, then rounded), l11, l21, l22, opacity, values. ``pos`` (2, V+1) float64 and
    ``per_row`` (4 + C, V+1) have a zero last column for padding slots."""
    cx = (slot_tiles % tiles_x).to(torch.float64) * ts + 0.5 * ts
    cy = torch.div(slot_tiles, tiles_x, rounding_mode="floor").to(torch.float64) * ts + 0.5 * ts
    rel = torch.stack([pos[0].index_select(0, slot_rows) - cx,
                       pos[1].index_select(0, slot_rows) - cy]).to(per_row.dtype)
    return torch.cat([rel, per_row.index_select(1, slot_rows)], dim=0)


def _slot_tables_compiled(*args):
    if "slots" not in _KERNEL_CACHE:
        _KERNEL_CACHE["slots"] = torch.compile(_slot_tables, dynamic=True)
    with torch.no_grad():
        return _KERNEL_CACHE["slots"](*args)


def _pixel_offsets(tile_size: int, dtype, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(P,) x and y of the pixel centres of a tile, relative to the tile centre."""
    p = torch.arange(tile_size * tile_size, device=device)
    half = 0.5 * tile_size
    return ((p % tile_size).to(dtype) + 0.5 - half, (p // tile_size).to(dtype) + 0.5 - half)


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
        g_pad = torch.zeros(hp, wp, n_c, dtype=dtype, device=dev)
        g_pad[:plan.height, :plan.width] = g_img
        g_tiles = g_pad.view(plan.tiles_y, ts, plan.tiles_x, ts, n_c).permute(4, 0, 2, 1, 3)
        g_tiles = g_tiles.reshape(n_c, plan.tiles_y * plan.tiles_x, ts * ts)
        pxl, pyl = _pixel_offsets(ts, dtype, dev)
        n_vis = ctx.n_vis
        n_slots = geo.shape[1]
        # Per-slot gradients, planar: rows 0..5 geometry, 6.. values.
        d_slot = torch.empty(_N_GEOM + n_c, n_slots, dtype=dtype, device=dev)
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
            d_slot[_N_GEOM:, off:off + tc * g] = dv.reshape(n_c, -1)
        ctx.state = None
        d_rows = torch.zeros(_N_GEOM + n_c, n_vis + 1, dtype=dtype, device=dev)
        d_rows.index_add_(1, plan.slot_rows, d_slot)
        d_rows = d_rows[:, :n_vis]
        d_means2d = torch.zeros(ctx.n, 2, dtype=dtype, device=dev)
        d_means2d.index_copy_(0, ids, d_rows[0:2].t())
        return (d_means2d, d_rows[2:5].t(), d_rows[5], d_rows[_N_GEOM:].t(),
                None, None, None, None, None)


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
    """:class:`_Composite` through numba's kernels (float32): one kernel call over every tile
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
        d = torch.from_numpy(ctx.nk.backward(tile_start, rows, pos, geo, vals, ts, plan.tiles_x,
                                             out, last, g_out))
        ctx.arrays = None
        d_means2d = torch.zeros(ctx.n, 2, dtype=torch.float32)
        d_means2d.index_copy_(0, ids, d[0:2].t())
        return d_means2d, d[2:_N_GEOM].t(), d[_N_GEOM:].t(), None, None, None, None


def _render_numba(nk, means, log_scales, quats, logit_opacities, blocks, viewmat, K, width: int,
                  height: int, sh_degree: int, background, antialiased: bool, near: float,
                  tile_size: int, gather) -> RenderOutput:
    """:func:`render` with every per-Gaussian and per-pair step in numba (float32 inputs):
    culling, depth order and binning without autograd, then two differentiable kernels,
    projection + colour and compositing. Same outputs as the eager path to float32 rounding
    (tests/test_rasterizer.py)."""
    n = means.shape[0]
    f64 = torch.float64
    vm = np.ascontiguousarray(viewmat.detach().to(f64).numpy())
    Kd = np.ascontiguousarray(K.detach().to(f64).numpy())
    params = (means, log_scales, quats, logit_opacities)
    info, ids_np, radii = nk.cull(*(x.detach().contiguous().numpy() for x in params), vm, Kd,
                                  width, height, near, antialiased)
    ids = torch.from_numpy(ids_np)
    ts = tile_size
    plan = _Plan(width, height, ts, -(-width // ts), -(-height // ts), int(ids.shape[0]))
    tile_start, rows = nk.bin(info, ids_np, ts, plan.tiles_x, plan.tiles_x * plan.tiles_y)
    plan.tile_start, plan.isect_rows = torch.from_numpy(tile_start), torch.from_numpy(rows)
    plan.intersections = int(rows.shape[0])
    plan.pairs = plan.intersections * ts * ts

    sh_vis = torch.cat([gather(b, ids) for b in blocks if b.shape[1]], 1).to(torch.float32)
    campos = camera_centre(torch.from_numpy(vm)).numpy()
    setup = (nk, sh_degree, vm, Kd, campos, width, height, near, antialiased)
    m2d, geo, depth, colour, pos64 = _ProjectNumba.apply(
        *(gather(x, ids) for x in params), sh_vis, setup)
    values = torch.cat([colour, depth.unsqueeze(1), torch.ones(ids.shape[0], 1)], dim=1)
    means2d = torch.zeros(n, 2).index_copy(0, ids, m2d)
    if means2d.requires_grad:
        means2d.retain_grad()
    acc = _CompositeNumba.apply(means2d, geo, values, pos64, ids, plan, nk)
    alpha = acc[..., 4]
    rgb = acc[..., 0:3] + (1.0 - alpha).unsqueeze(-1) * background
    stats = dict(visible=int(ids.shape[0]), intersections=plan.intersections, pairs=plan.pairs,
                 chunks=0, compiled=False, path="numba")
    return RenderOutput(rgb=rgb, alpha=alpha, depth=acc[..., 3], means2d=means2d,
                        radii=torch.from_numpy(radii), stats=stats)


# ----------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------

def render(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
           logit_opacities: torch.Tensor, sh, viewmat: torch.Tensor,
           K: torch.Tensor, width: int, height: int, sh_degree: Optional[int] = None,
           background: Optional[torch.Tensor] = None, antialiased: bool = False,
           near: float = DEFAULT_NEAR, tile_size: int = DEFAULT_TILE_SIZE,
           compiled: Optional[bool] = None, chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
           low_memory: bool = False, gather=None) -> RenderOutput:
    """Render 3D Gaussians into one pinhole view, differentiably (INRIA 3DGS maths, CPU).

    Args:
        means: (N, 3) Gaussian centres, world coordinates (scene units, e.g. metres).
        log_scales: (N, 3) natural log of the standard deviations along the Gaussian's axes.
        quats: (N, 4) rotations as (w, x, y, z); need not be normalised (a zero quaternion is
            treated as the identity).
        logit_opacities: (N,) opacity logits (opacity = sigmoid).
        sh: (N, K, 3) spherical-harmonic colour coefficients, K = (d+1)^2, INRIA layout
            (coefficient-major, channel-last; ``sh[:, 0, :]`` is DC; colour = max(0, SH + 0.5)).
            May also be a sequence of (N, K_i, 3) blocks (e.g. DC and the rest), which are
            joined only for the visible Gaussians: for a large model this avoids copying every
            coefficient of every Gaussian on each render.
        viewmat: (4, 4) world-to-camera matrix, OpenCV camera axes (x right, y down, z
            forward), see :mod:`recgs_addon.core.model.cameras`.
        K: (3, 3) intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels; pixel (i, j) is
            centred at (i + 0.5, j + 0.5).
        width, height: image size in pixels.
        sh_degree: SH degree to evaluate, 0..3; None uses all K coefficients.
        background: (3,) colour behind the Gaussians, default black. May require grad.
        antialiased: Mip-Splatting/gsplat antialiasing: opacity *= sqrt(det(cov2d) /
            det(cov2d + 0.3 I)).
        near: near plane (scene units); Gaussians with camera-space z <= near are culled.
        tile_size: tile edge in pixels (binning granularity; results do not depend on it).
        compiled: run the per-pair maths through ``torch.compile`` (True), eagerly (False)
            or compiled when a compiler works, else eagerly with a warning (None).
        chunk_pairs: (pixel, Gaussian) pairs per chunk (working-set size).
        low_memory: keep no per-pair state between forward and backward (the backward
            replays the forward chunk by chunk): about 8 bytes less per pair, ~1/3 slower.
        gather: ``gather(x, ids)`` reads rows ``ids`` (the visible Gaussians) of a
            per-Gaussian input; default ``x.index_select(0, ids)``. A trainer passes a
            :class:`recgs_addon.core.render.rowgrads.RowGrads` so that gradients stay row-sparse.

    The dtype of ``means`` (float32 or float64) sets the compositing precision; the
    per-Gaussian projection is always float64. Gradients reach every input through
    ``loss.backward()``; see :class:`RenderOutput` for the outputs and ``means2d.grad``.
    """
    dtype = means.dtype
    n = means.shape[0]
    kern = get_kernels(compiled)
    blocks = (sh,) if isinstance(sh, torch.Tensor) else tuple(sh)
    if sh_degree is None:
        sh_degree = int(round(math.sqrt(sum(b.shape[1] for b in blocks)))) - 1
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means.device)
    background = background.to(device=means.device, dtype=dtype)

    if gather is None:
        gather = _index_rows
    if kern.numba is not None and means.device.type == "cpu" and all(x.dtype == torch.float32 for x in
                                      (means, log_scales, quats, logit_opacities)):
        if not near > 0:
            raise ValueError(f"near must be > 0, got {near}")
        try:
            return _render_numba(kern.numba, means, log_scales, quats, logit_opacities, blocks,
                                 viewmat, K, width, height, sh_degree, background, antialiased,
                                 near, tile_size, gather)
        except Exception as exc:  # noqa: BLE001 - numba failing here: eager from now on
            from . import numba_kernels
            numba_kernels.disable(exc)
            warnings.warn(f"numba kernels failed ({exc!r}); using the eager rasterizer")
            kern = get_kernels(False)
    proj = project_gaussians(means, log_scales, quats, logit_opacities, viewmat, K,
                             width, height, near=near, antialiased=antialiased,
                             compiled=kern.compiled, gather=gather)
    ids = proj.ids
    # View direction: from the camera centre to the Gaussian (world axes), INRIA.
    # Visible Gaussians have z > near > 0, so the direction is never zero.
    campos = camera_centre(viewmat.detach().to(torch.float64))
    dirs = gather(means, ids).to(torch.float64) - campos
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    sh_vis = torch.cat([gather(b, ids) for b in blocks if b.shape[1]], 1)
    colours = _sh_fn(kern.compiled)(sh_degree, sh_vis.to(dtype), dirs.to(dtype))
    values = torch.cat([colours, proj.depth.to(dtype).unsqueeze(1),
                        torch.ones(ids.shape[0], 1, dtype=dtype, device=means.device)], dim=1)
    means2d = torch.zeros(n, 2, dtype=dtype, device=means.device).index_copy(0, ids, proj.means2d.to(dtype))
    if means2d.requires_grad:
        means2d.retain_grad()

    plan = _build_plan(proj, width, height, tile_size, chunk_pairs, kern.compiled)
    acc = _Composite.apply(means2d, proj.chol.to(dtype), proj.opacity.to(dtype), values,
                           proj.means2d.detach(), ids, plan, kern, low_memory)
    alpha = acc[..., 4]
    rgb = acc[..., 0:3] + (1.0 - alpha).unsqueeze(-1) * background
    stats = dict(visible=int(ids.shape[0]), intersections=plan.intersections,
                 pairs=plan.pairs, chunks=len(plan.chunks), compiled=kern.compiled,
                 path="compiled" if kern.compiled else "eager")
    return RenderOutput(rgb=rgb, alpha=alpha, depth=acc[..., 3], means2d=means2d,
                        radii=proj.radii, stats=stats)
