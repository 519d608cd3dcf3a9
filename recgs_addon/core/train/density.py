"""Adaptive density control: clone, split, prune and opacity reset (INRIA 3DGS), with the
optimiser state kept in step with the parameters (gsplat's ``strategy/ops.py`` idea).

Parameters live in a dict of leaf tensors ``params[name]`` of shape (N, ...), all optimised
by one ``torch.optim.Adam`` with one parameter group per name. Every operation replaces the
tensors and the matching Adam moments, so no stale state survives a change of N.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..model.gaussians import logit
from ..render.projection import quat_to_rotmat

#: Opacity below which a Gaussian is pruned (INRIA: 0.005).
PRUNE_OPACITY = 0.005
#: Opacity cap at a reset (INRIA: 0.01).
RESET_OPACITY = 0.01
#: A Gaussian larger than this fraction of the scene extent is split rather than cloned.
PERCENT_DENSE = 0.01
#: Split children are scaled down by this factor (INRIA: 1 / (0.8 * 2)).
SPLIT_SCALE_DIVISOR = 1.6
#: Prune Gaussians whose largest axis exceeds this fraction of the scene extent.
PRUNE_WORLD_SCALE = 0.1
#: Prune Gaussians whose screen radius exceeded this many pixels (after the first reset).
PRUNE_SCREEN_RADIUS = 20


def _replace(params: dict, optimizer: torch.optim.Optimizer, fn) -> None:
    """Apply ``fn(name, tensor, is_state) -> tensor`` to every parameter and its Adam moments."""
    for group in optimizer.param_groups:
        old = group["params"][0]
        name = group["name"]
        new = torch.nn.Parameter(fn(name, old.detach(), False), requires_grad=old.requires_grad)
        state = optimizer.state.pop(old, None)
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = fn(name, state[key], True)
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new


def remove(params: dict, optimizer, keep: torch.Tensor) -> None:
    """Keep only the Gaussians where ``keep`` (N,) bool is True."""
    _replace(params, optimizer, lambda name, t, is_state: t[keep].clone())


def append(params: dict, optimizer, new_values: dict) -> None:
    """Append Gaussians (``new_values[name]`` of shape (M, ...)); their Adam moments start at 0."""
    def grow(name, t, is_state):
        extra = new_values[name].to(t.dtype)
        return torch.cat([t, torch.zeros_like(extra) if is_state else extra], 0)

    _replace(params, optimizer, grow)


def reset_opacity(params: dict, optimizer, cap: float = RESET_OPACITY) -> None:
    """Cap every opacity at ``cap`` and zero its Adam moments (INRIA's periodic reset)."""
    cap_logit = float(logit(cap))
    for group in optimizer.param_groups:
        if group["name"] != "logit_opacities":
            continue
        p = group["params"][0]
        with torch.no_grad():
            p.clamp_(max=cap_logit)
        st = optimizer.state.get(p)
        if st:
            st["exp_avg"].zero_()
            st["exp_avg_sq"].zero_()


def split_values(params: dict, select: torch.Tensor, generator: torch.Generator, n_children: int = 2) -> dict:
    """New Gaussians replacing the selected ones: ``n_children`` samples from each Gaussian,
    scales divided by 1.6 (INRIA's densify_and_split)."""
    idx = torch.nonzero(select).squeeze(1)
    out = {}
    scales = params["log_scales"].detach()[idx].exp()
    R = quat_to_rotmat(params["quats"].detach()[idx])
    for name, p in params.items():
        out[name] = p.detach()[idx].repeat_interleave(n_children, 0) if name != "means" else None
    local = torch.randn(len(idx), n_children, 3, generator=generator, dtype=scales.dtype) * scales[:, None, :]
    offsets = torch.einsum("nij,nkj->nki", R, local).reshape(-1, 3)
    out["means"] = params["means"].detach()[idx].repeat_interleave(n_children, 0) + offsets.to(params["means"].dtype)
    out["log_scales"] = (scales / SPLIT_SCALE_DIVISOR).log().repeat_interleave(n_children, 0)
    return out


@dataclass
class GradientStats:
    """Accumulated screen-space gradient norms (INRIA's xyz_gradient_accum / denom).

    Gradients are in NDC units (pixel gradient times W/2, H/2) so INRIA's threshold applies.
    """

    accum: torch.Tensor
    count: torch.Tensor
    max_radius: torch.Tensor

    @classmethod
    def zeros(cls, n: int) -> "GradientStats":
        return cls(torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.int64),
                   torch.zeros(n, dtype=torch.int32))

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        vis = radii > 0
        g = means2d_grad.detach().to(torch.float64)
        g = torch.stack([g[:, 0] * width / 2, g[:, 1] * height / 2], 1).norm(dim=1)
        self.accum += torch.where(vis, g, torch.zeros_like(g))
        self.count += vis.to(torch.int64)
        self.max_radius = torch.maximum(self.max_radius, radii.to(torch.int32))

    def mean(self) -> torch.Tensor:
        return self.accum / self.count.clamp_min(1)

    def state_dict(self) -> dict:
        return {"accum": self.accum, "count": self.count, "max_radius": self.max_radius}
