"""numba kernels of the rasterizer (imported by :mod:`.numba_kernels` only, after it has
pointed numba's cache at RecGS's folder: the cache location is fixed when these decorators run).

Every kernel is serial and works on a range of its items (tiles, Gaussians, gradient fields):
:mod:`.numba_kernels` runs the ranges on threads of its own (``nogil``). numba's ``parallel``
mode would do the same with its own pool, but compiles ~2.5x slower (41 against 14 s measured
for all kernels, cold cache), and its OpenMP pool is a second one beside torch's.

The kernels live in two modules by concern, imported here so that :mod:`.numba_kernels` sees
one namespace (``impl.cull``, ``impl.composite_forward``, ...): :mod:`._numba_project` (per
Gaussian: cull, depth order, projection and SH colour) and :mod:`._numba_tiles` (binning and
compositing). Importing this module runs their decorators.
"""
from __future__ import annotations

from ._numba_project import cull, project_backward, project_forward, visible_in_depth_order  # noqa: F401
from ._numba_tiles import (bin_count, bin_fill, bin_offsets, composite_backward,  # noqa: F401
                           composite_forward, gather_rows)
