"""Differentiable Gaussian rasterizer for the CPU, in pure torch (INRIA 3DGS maths).

Entry point: :func:`render`. Design and measured speed: ``docs/dev/rasterizer.md``.

Pipeline
--------
1. :func:`recgs_addon.core.render.projection.project_gaussians` (per Gaussian, float64, autograd):
   a cheap conservative candidate test, then the exact cull on the candidates, EWA-project,
   0.3 px dilation, opacity-aware radius, stable depth sort.
2. Colours from spherical harmonics (:mod:`recgs_addon.core.model.sh`, autograd).
3. Binning (no gradient, :mod:`.tiles`): every visible Gaussian is listed in each tile that its
   opacity-aware ellipse reaches (exact per tile row, not the bounding square); the list is
   stably sorted by tile, so inside a tile it stays in depth order (ties by index).
4. Compositing (:class:`.composite._Composite`, hand-written backward): tiles are grouped into
   chunks of similar list length; each chunk is a padded batch ``[tiles, Gaussians, pixels per
   tile]``. Front-to-back transmittance is an inclusive ``cumprod`` over the depth axis, which
   is the same sequence of float multiplications as INRIA's loop, and makes its early stop exact:
   the running product is non-increasing, so "stop at the first Gaussian whose
   ``T (1 - alpha)`` would drop below 1e-4, without adding it" selects exactly the samples
   whose inclusive product is >= 1e-4. The backward uses the forward's falloff and
   transmittance (or, with ``low_memory``, replays the forward chunk by chunk) and
   ``dC/dalpha_i = v_i T_i - (sum_{k>i} v_k alpha_k T_k) / (1 - alpha_i)`` with a reverse
   cumulative sum; ``1 - alpha >= 0.01`` because alpha is clamped at 0.99.

The per-pair maths of step 4 (:mod:`.chunks`) runs either eagerly or through ``torch.compile``
(:mod:`.kernels`; it fuses them into a few C++ loops, about 10-30x faster here); both give the
same numbers to ~1e-7. numba's path (:mod:`.numba_path`, :mod:`.numba_kernels`) runs steps 1-4
in numba for float32 inputs.

This module holds :func:`render`, its result type, the choice of kernels (:func:`get_kernels`)
and the pipeline of numba's path (:func:`_render_numba`); it re-exports the constants and names
other modules import from it.
"""
from __future__ import annotations

import math
import warnings
from typing import NamedTuple, Optional

import numpy as np
import torch

from .chunks import ALPHA_MAX, T_MIN, _chunk_backward, _chunk_forward
from .composite import _Composite
from .kernels import _KERNEL_CACHE, _Kernels, _compiled_kernels, _sh_fn, _smoke_test
from .numba_path import _CompositeNumba, _ProjectNumba
from .projection import ALPHA_MIN, _index_rows, camera_centre, drawn_in_depth_order, project_gaussians
from .tiles import _Plan, _build_plan
from .triton_path import _CompositeTriton, _ProjectTriton

#: Default near plane (scene units), INRIA.
DEFAULT_NEAR = 0.2
#: Default tile size in pixels (fastest measured on the CPU, benchmarks/RESULTS.md#rasterizer-design-trials).
DEFAULT_TILE_SIZE = 4
#: Default number of (pixel, Gaussian) pairs per chunk: bounds the temporaries of a pass to
#: roughly 60 bytes x this and keeps the working set in cache (2^16..2^20 measured).
DEFAULT_CHUNK_PAIRS = 1 << 18
#: Tile edge of the GPU path (Triton): a tile's 256 pixels are one program's lanes.
TRITON_TILE_SIZE = 16


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
    numba's (``"numba"``: no C++ compiler needed; the rest of the render runs eagerly) or the
    eager ones marked for Triton's GPU kernels (``"triton"``: :func:`_triton_kernels` loads
    them in the render, for its device)."""
    if compiled is False:
        return _Kernels(_chunk_forward, _chunk_backward, False)
    if compiled == "triton":   # the GPU kernels; on CPU tensors in Triton's interpreter (tests)
        return _Kernels(_chunk_forward, _chunk_backward, False, triton=True)
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


def _triton_kernels(device: torch.device):
    """Triton's kernels (:class:`.triton_kernels.TritonKernels`) for tensors on ``device``
    (compiled for a CUDA device, in the interpreter for CPU tensors), or None with a warning,
    once: the eager path then."""
    from . import triton_kernels
    tk = triton_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN, device=device.type)
    if tk is None and "warned_triton" not in _KERNEL_CACHE:
        warnings.warn(f"Triton kernels unavailable ({triton_kernels.error()!r}); using the eager rasterizer")
        _KERNEL_CACHE["warned_triton"] = True
    return tk


def _flat_plan(width: int, height: int, ts: int, n_vis: int, tile_start, rows, weights) -> _Plan:
    """The plan of a whole-view path (numba's, Triton's): no chunks, no padding; ``rows`` (M,)
    int32, the visible row of each intersection in (tile, depth) order, ``tile_start``
    (n_tiles + 1,) int64 each tile's offset into them."""
    plan = _Plan(width, height, ts, -(-width // ts), -(-height // ts), n_vis)
    plan.tile_start, plan.isect_rows = tile_start, rows
    plan.intersections = int(rows.shape[0])
    plan.pairs = plan.intersections * ts * ts
    plan.weights = weights
    return plan


def _screen(n: int, ids, m2d, colour, depth):
    """The compositing's values (V, 5) (rgb, depth, 1) and the screen positions of every
    Gaussian (N, 2) (0 where culled; its ``.grad`` kept for density control)."""
    values = torch.cat([colour, depth.unsqueeze(1), torch.ones(ids.shape[0], 1, device=ids.device)], dim=1)
    means2d = torch.zeros(n, 2, device=ids.device).index_copy(0, ids, m2d)
    if means2d.requires_grad:
        means2d.retain_grad()
    return values, means2d


def _flat_output(acc, background, means2d, radii, plan: _Plan, path: str) -> RenderOutput:
    """A whole-view path's accumulated (H, W, 5) image as :class:`RenderOutput`."""
    alpha = acc[..., 4]
    rgb = acc[..., 0:3] + (1.0 - alpha).unsqueeze(-1) * background
    stats = dict(visible=plan.n_vis, intersections=plan.intersections, pairs=plan.pairs,
                 chunks=0, compiled=False, path=path)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=acc[..., 3], means2d=means2d, radii=radii, stats=stats)


def _render_numba(nk, means, log_scales, quats, logit_opacities, blocks, viewmat, K, width: int,
                  height: int, sh_degree: int, background, antialiased: bool, near: float,
                  tile_size: int, gather, weights) -> RenderOutput:
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
    tiles_x = -(-width // ts)
    tile_start, rows = nk.bin(info, ids_np, ts, tiles_x, tiles_x * -(-height // ts))
    plan = _flat_plan(width, height, ts, int(ids.shape[0]), torch.from_numpy(tile_start), torch.from_numpy(rows),
                      weights)

    sh_vis = torch.cat([gather(b, ids) for b in blocks if b.shape[1]], 1).to(torch.float32)
    campos = camera_centre(torch.from_numpy(vm)).numpy()
    setup = (nk, sh_degree, vm, Kd, campos, width, height, near, antialiased)
    m2d, geo, depth, colour, pos64 = _ProjectNumba.apply(
        *(gather(x, ids) for x in params), sh_vis, setup)
    values, means2d = _screen(n, ids, m2d, colour, depth)
    acc = _CompositeNumba.apply(means2d, geo, values, pos64, ids, plan, nk)
    return _flat_output(acc, background, means2d, torch.from_numpy(radii), plan, "numba")


def _render_triton(tk, means, log_scales, quats, logit_opacities, blocks, viewmat, K, width: int,
                   height: int, sh_degree: int, background, antialiased: bool, near: float,
                   gather, weights) -> RenderOutput:
    """:func:`render` on the GPU path (float32 inputs on a CUDA device, or CPU tensors in
    Triton's interpreter): culling and binning in Triton kernels without autograd (the depth
    order and the sort by tile torch's), then two differentiable Triton kernels, projection +
    colour and compositing (one launch each way). Same outputs as the eager path to float32 rounding
    (tests/test_triton_kernels.py)."""
    n = means.shape[0]
    f64 = torch.float64
    params = (means, log_scales, quats, logit_opacities)
    vm = viewmat.detach().to(device=means.device, dtype=f64)
    view = tk.view_arrays(vm, K.detach().to(device=means.device, dtype=f64), camera_centre(vm), near)
    with torch.no_grad():
        info = tk.cull(tuple(x.detach().contiguous() for x in params), view, width, height, antialiased)
        ids, radii = drawn_in_depth_order(info)
        info = info.index_select(0, ids).contiguous()
    sh_vis = torch.cat([gather(b, ids) for b in blocks if b.shape[1]], 1)
    m2d, geo, depth, colour, pos64 = _ProjectTriton.apply(
        *(gather(x, ids) for x in params), sh_vis, (tk, sh_degree, view, width, height, antialiased))
    values, means2d = _screen(n, ids, m2d, colour, depth)
    ts = TRITON_TILE_SIZE
    tiles_x = -(-width // ts)
    plan = _flat_plan(width, height, ts, int(ids.shape[0]), *tk.bin(info, ts, tiles_x, tiles_x * -(-height // ts)),
                      weights)
    acc = _CompositeTriton.apply(means2d, geo[:, :3], geo[:, 3], values, pos64, ids, plan, tk)
    return _flat_output(acc, background, means2d, radii, plan, "triton")


# ----------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------

def render(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
           logit_opacities: torch.Tensor, sh, viewmat: torch.Tensor,
           K: torch.Tensor, width: int, height: int, sh_degree: Optional[int] = None,
           background: Optional[torch.Tensor] = None, antialiased: bool = False,
           near: float = DEFAULT_NEAR, tile_size: int = DEFAULT_TILE_SIZE,
           compiled: Optional[bool] = None, chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
           low_memory: bool = False, gather=None, weights: Optional[torch.Tensor] = None) -> RenderOutput:
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
            or compiled when a compiler works, else eagerly with a warning (None); ``"numba"``:
            numba's kernels (CPU, float32); ``"triton"``: culling, binning, projection, colour
            and compositing in Triton's kernels (a CUDA device, float32; CPU tensors only in
            Triton's interpreter), in 16x16 tiles whatever ``tile_size``.
        chunk_pairs: (pixel, Gaussian) pairs per chunk (working-set size).
        low_memory: keep no per-pair state between forward and backward (the backward
            replays the forward chunk by chunk): about 8 bytes less per pair, ~1/3 slower.
        gather: ``gather(x, ids)`` reads rows ``ids`` (the visible Gaussians) of a
            per-Gaussian input; default ``x.index_select(0, ids)``. A trainer passes a
            :class:`recgs_addon.core.render.rowgrads.RowGrads` so that gradients stay row-sparse.
        weights: optional (N,) tensor into which ``backward()`` adds each Gaussian's blending
            weight in this view, ``sum over pixels of alpha_i T_i`` (the pixels' worth of the
            image it supplies; 0 where culled), at no extra pass: the significance density
            control reads. Filled only when the render's backward runs.

    The dtype of ``means`` (float32 or float64) sets the compositing precision; the
    per-Gaussian projection is always float64. Gradients reach every input through
    ``loss.backward()``; see :class:`RenderOutput` for the outputs and ``means2d.grad``.
    """
    if not near > 0:
        raise ValueError(f"near must be > 0, got {near}")
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
    # the kernels are float32 (float64 renders stay eager)
    f32 = all(x.dtype == torch.float32 for x in (means, log_scales, quats, logit_opacities))
    if kern.numba is not None and means.device.type == "cpu" and f32:
        try:
            return _render_numba(kern.numba, means, log_scales, quats, logit_opacities, blocks,
                                 viewmat, K, width, height, sh_degree, background, antialiased,
                                 near, tile_size, gather, weights)
        except Exception as exc:  # noqa: BLE001 - numba failing here: eager from now on
            from . import numba_kernels
            numba_kernels.disable(exc)
            warnings.warn(f"numba kernels failed ({exc!r}); using the eager rasterizer")
            kern = get_kernels(False)
    tk = _triton_kernels(means.device) if kern.triton and f32 else None
    if tk is not None:
        return _render_triton(tk, means, log_scales, quats, logit_opacities, blocks, viewmat, K, width,
                              height, sh_degree, background, antialiased, near, gather, weights)
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
    plan.weights = weights
    acc = _Composite.apply(means2d, proj.chol.to(dtype), proj.opacity.to(dtype), values,
                           proj.means2d.detach(), ids, plan, kern, low_memory)
    alpha = acc[..., 4]
    rgb = acc[..., 0:3] + (1.0 - alpha).unsqueeze(-1) * background
    stats = dict(visible=int(ids.shape[0]), intersections=plan.intersections,
                 pairs=plan.pairs, chunks=len(plan.chunks), compiled=kern.compiled,
                 path="compiled" if kern.compiled else "eager")
    return RenderOutput(rgb=rgb, alpha=alpha, depth=acc[..., 3], means2d=means2d,
                        radii=proj.radii, stats=stats)
