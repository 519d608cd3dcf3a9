"""Real spherical harmonics of degree 0..3, as in INRIA 3DGS (``utils/sh_utils.py``).

Layout (INRIA, gsplat): coefficients are stored coefficient-major, channel-last,
``sh[:, k, c]`` with ``k = 0 .. (d+1)^2 - 1`` and ``c`` in (r, g, b); ``sh[:, 0, :]`` is the DC
term. The colour seen from direction ``dir`` (unit vector from the camera centre to the
Gaussian, world axes) is ``max(0, sum_k Y_k(dir) sh[:, k, :] + 0.5)``.

The signs and constants below are INRIA's, so PLY files written by INRIA, gsplat or
SuperSplat render the same colours here.
"""
from __future__ import annotations

import torch

from .gaussians import SH_C0, SH_C1, SH_C2, SH_C3, num_sh_coeffs  # noqa: F401  (one source)

#: Colour offset: INRIA stores colour - 0.5 in the DC term (``RGB2SH``/``SH2RGB``).
SH_COLOUR_OFFSET = 0.5


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The (d+1)^2 real SH basis functions in INRIA's order and sign convention.

    Args:
        degree: 0..3.
        dirs: (N, 3) unit view directions (world axes).
    Returns:
        (N, (degree+1)^2) basis values, same dtype as ``dirs``.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    n = dirs.shape[0]
    cols = [torch.full((n,), SH_C0, dtype=dirs.dtype, device=dirs.device)]
    if degree > 0:
        x, y, z = dirs.unbind(-1)
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
        if degree > 1:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            cols += [SH_C2[0] * xy,
                     SH_C2[1] * yz,
                     SH_C2[2] * (2.0 * zz - xx - yy),
                     SH_C2[3] * xz,
                     SH_C2[4] * (xx - yy)]
            if degree > 2:
                cols += [SH_C3[0] * y * (3.0 * xx - yy),
                         SH_C3[1] * xy * z,
                         SH_C3[2] * y * (4.0 * zz - xx - yy),
                         SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                         SH_C3[4] * x * (4.0 * zz - xx - yy),
                         SH_C3[5] * z * (xx - yy),
                         SH_C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(cols, dim=-1)


def eval_sh_colour(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """View-dependent colour ``max(0, SH(dir) + 0.5)``.

    Args:
        degree: SH degree to use, 0..3 (only the first (degree+1)^2 coefficients are read).
        sh: (N, K, 3) coefficients, K >= (degree+1)^2, INRIA layout (``sh[:, 0]`` is DC).
        dirs: (N, 3) unit directions from the camera centre to each Gaussian (world axes).
    Returns:
        (N, 3) colours, >= 0 (not clamped above). The clamp at 0 has zero gradient below 0,
        as in INRIA's ``clamp_min``.
    """
    k = num_sh_coeffs(degree)
    if sh.shape[1] < k:
        raise ValueError(f"sh has {sh.shape[1]} coefficients, degree {degree} needs {k}")
    basis = sh_basis(degree, dirs.to(sh.dtype))                    # (N, k)
    if torch.compiler.is_compiling():
        # Unrolled sum over coefficients: under torch.compile a reduction over this short axis
        # was parallelised pathologically (37 ms instead of 0.7 ms on 2 threads).
        raw = basis[:, 0:1] * sh[:, 0, :]
        for i in range(1, k):
            raw = raw + basis[:, i:i + 1] * sh[:, i, :]           # (N, 3)
    else:
        # Eagerly, one batched product: the unrolled sum's backward makes a zero tensor the
        # size of ``sh`` for every coefficient (16 at degree 3): 67-79 ms against 19-23 ms
        # forward + backward at 37k Gaussians, 1 thread; same numbers (bit for bit, measured).
        raw = torch.bmm(basis.unsqueeze(1), sh[:, :k, :]).squeeze(1)
    return torch.clamp_min(raw + SH_COLOUR_OFFSET, 0.0)
