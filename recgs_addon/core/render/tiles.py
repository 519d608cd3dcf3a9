"""Tile binning of one view (no gradients): which tiles each visible Gaussian's ellipse
reaches (exact per tile row), the stable sort by tile, chunks of tiles with similar list
lengths as padded slot batches (:class:`_Plan`), and the per-slot tables and pixel offsets
the compositing reads."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

from .kernels import _KERNEL_CACHE

#: Number of per-Gaussian attributes in the intersection table before the values:
#: (mean x, mean y relative to the tile centre, l11, l21, l22, opacity).
_N_GEOM = 6


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
    #: numba's and the GPU path (no chunks, no padding): the intersections in (tile, depth) order, as the
    #: visible row of each (M,) int32, and each tile's offset into them (n_tiles + 1,) int64
    isect_rows: Optional[torch.Tensor] = None
    tile_start: Optional[torch.Tensor] = None
    #: (N,) where the backward adds each Gaussian's blending weight in the view (pixels), if asked
    weights: Optional[torch.Tensor] = None


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


def _sort_by_tile(rows: torch.Tensor, tile: torch.Tensor, n_tiles: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The intersections (visible row, tile) in (tile, depth) order: (rows (M,), count per tile
    (n_tiles,)). Rows come in depth order, so a stable sort by tile keeps depth order inside a
    tile; int32 keys: torch's stable CPU sort is a radix sort for them (~20x faster than int64)."""
    tile_sorted, perm = torch.sort(tile.to(torch.int32), stable=True)
    return rows.index_select(0, perm), torch.bincount(tile_sorted, minlength=n_tiles)


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
    rows_sorted, tile_count = _sort_by_tile(rows, tile, n_tiles)
    rows_ext = torch.cat([rows_sorted, torch.tensor([n_vis], device=rows.device)])
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
