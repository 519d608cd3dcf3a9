"""Exact k-nearest-neighbour distances with numpy only (no scipy in Blender's Python).

Points are binned into a uniform grid whose cells hold about ``k`` points on average. For a
query point every point within one cell size ``s`` lies in the 27 cells around its own, so
its k nearest among those candidates are exact whenever the k-th distance is at most ``s``.
Points for which that does not hold (sparse regions) are asked again with a grid twice as
coarse, until every answer is exact. Candidate pairs are generated in bulk (sorted cell ids,
``searchsorted`` ranges, ``np.repeat``), never in a per-point Python loop.
"""
from __future__ import annotations

import numpy as np

_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], np.int64)
#: Mean points an occupied cell may hold before the cells are made smaller.
MAX_OCCUPANCY = 4.0
#: Candidate pairs evaluated at once (bounds the memory of one pass: ~40 bytes a pair).
_CHUNK_PAIRS = 4_000_000


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """(N,) int64 key of (N, 3) non-negative integer cells (21 bits an axis)."""
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


def _knn_pass(pts: np.ndarray, query: np.ndarray, k: int, size: float):
    """k smallest distances (Q, k) from ``pts[query]`` to the other points among its 27 cells
    of edge ``size`` (inf where fewer than k candidates)."""
    lo = pts.min(0)
    cells = np.floor((pts - lo) / size).astype(np.int64) + 1       # +1: the -1 offsets stay >= 0
    keys = _cell_keys(cells)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    out = np.full((len(query), k), np.inf)
    # chunk the queries so that the candidate pairs of one chunk fit in memory
    mean_occ = max(1.0, len(pts) / max(1, len(np.unique(sorted_keys))))
    step = max(1, int(_CHUNK_PAIRS / (27 * mean_occ)))
    for c0 in range(0, len(query), step):
        q = query[c0:c0 + step]
        nb = _cell_keys((cells[q][:, None, :] + _OFFSETS[None]).reshape(-1, 3))
        start = np.searchsorted(sorted_keys, nb, side="left")
        count = np.searchsorted(sorted_keys, nb, side="right") - start
        owner = np.repeat(np.repeat(np.arange(len(q)), 27), count)
        first = np.repeat(start - np.cumsum(count) + count, count)
        cand = order[first + np.arange(count.sum())]
        d = np.linalg.norm(pts[cand] - pts[q[owner]], axis=1)
        d[cand == q[owner]] = np.inf                                 # not the point itself
        # k smallest per owner (pairs come grouped by owner, each group non-empty: a point's
        # own cell holds it): k passes of a grouped minimum, each taking one element out
        begin = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=len(q)))[:-1]])
        for r in range(k):
            m = np.minimum.reduceat(d, begin)
            out[c0:c0 + len(q), r] = m
            hit = np.flatnonzero(d == m[owner])
            _, first = np.unique(owner[hit], return_index=True)
            d[hit[first]] = np.inf
    return out


def occupancy(pts: np.ndarray, size: float) -> float:
    """Mean points an occupied cell of edge ``size`` holds."""
    cells = np.floor((pts - pts.min(0)) / size).astype(np.int64)
    return len(pts) / len(np.unique(_cell_keys(cells)))


def cell_size(pts: np.ndarray) -> float:
    """The grid's first cell edge for (N, 3) points: cells holding about two points on average
    (measured: 1, 2 and k + 1 per cell cost the same within 10 %; sparse regions are asked
    again, coarser). Sized over the bounding box, then halved while the occupied cells hold
    more than :data:`MAX_OCCUPANCY`: a survey's points lie on a surface, with outliers far off
    that stretch the box, so the box's cells would hold hundreds (and every query would compare
    with thousands)."""
    extent = float(np.max(pts.max(0) - pts.min(0)))
    span = np.maximum(pts.max(0) - pts.min(0), extent * 1e-6)
    size = float(np.prod(span) * 2.0 / len(pts)) ** (1 / 3)
    size = min(max(size, extent / 2 ** 20), extent)                  # 21 bits an axis
    while size / 2 >= extent / 2 ** 20 and occupancy(pts, size) > MAX_OCCUPANCY:
        size /= 2
    return size


def knn_distances(points: np.ndarray, k: int) -> np.ndarray:
    """(N, k) distances of each point to its k nearest other points, ascending (exact).
    Needs N > k."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if n <= k:
        raise ValueError(f"need more than k = {k} points, got {n}")
    extent = float(np.max(pts.max(0) - pts.min(0)))
    if extent == 0.0:
        return np.zeros((n, k))
    size = cell_size(pts)
    out = np.empty((n, k))
    todo = np.arange(n)
    while len(todo):
        d = _knn_pass(pts, todo, k, size)
        ok = d[:, -1] <= size
        out[todo[ok]] = d[ok]
        todo = todo[~ok]
        size *= 2.0
        if size > 2 * extent and len(todo):                         # the whole cloud is one cell
            out[todo] = _knn_pass(pts, todo, k, 4 * extent + 1.0)
            break
    return out
