"""Adaptive density control: clone, split, prune and opacity reset (INRIA 3DGS), with the
optimiser state kept in step with the parameters (gsplat's ``strategy/ops.py`` idea).

Parameters live in a dict of leaf tensors ``params[name]`` of shape (N, ...), all optimised
by one ``torch.optim.Adam`` with one parameter group per name. Every operation replaces the
tensors and the matching Adam moments, so no stale state survives a change of N.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

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
    # drawn on the CPU by the trainer's CPU generator whatever the device: the same model on every device
    local = torch.randn(len(idx), n_children, 3, generator=generator, dtype=scales.dtype,
                        device=generator.device).to(scales.device)
    local = local * scales[:, None, :]
    offsets = torch.einsum("nij,nkj->nki", R, local).reshape(-1, 3)
    out["means"] = params["means"].detach()[idx].repeat_interleave(n_children, 0) + offsets.to(params["means"].dtype)
    out["log_scales"] = (scales / SPLIT_SCALE_DIVISOR).log().repeat_interleave(n_children, 0)
    return out


@dataclass
class GradientStats:
    """What density control reads of the steps since the last densification: the accumulated
    screen-space gradient norms (INRIA's xyz_gradient_accum / denom), the largest screen radius,
    and each Gaussian's peak blending weight (the most pixels it supplied to one training view,
    counted at the training resolution: the significance ``Strategy.prune_weight`` reads).

    Gradients are in NDC units (pixel gradient times W/2, H/2) so INRIA's threshold applies.
    ``count`` is the views in which a Gaussian was drawn.
    """

    accum: torch.Tensor
    count: torch.Tensor
    max_radius: torch.Tensor
    peak_weight: Optional[torch.Tensor] = None   # (N,) float32; None in checkpoints from before
    #: rows from here on were made by the last densification: not yet judged (a copy needs a
    #: window of steps to move off its original before what it supplies means anything)
    young_from: Optional[int] = None

    def __post_init__(self):
        n = self.accum.shape[0]
        if self.peak_weight is None:
            self.peak_weight = torch.zeros(n, dtype=torch.float32, device=self.accum.device)
        if self.young_from is None:
            self.young_from = n

    @classmethod
    def zeros(cls, n: int, device=None, young: int = 0) -> "GradientStats":
        """Fresh statistics of ``n`` Gaussians, the last ``young`` of them new."""
        return cls(torch.zeros(n, dtype=torch.float64, device=device), torch.zeros(n, dtype=torch.int64, device=device),
                   torch.zeros(n, dtype=torch.int32, device=device), young_from=n - min(max(young, 0), n))

    def to(self, device) -> "GradientStats":
        return GradientStats(self.accum.to(device), self.count.to(device), self.max_radius.to(device),
                             self.peak_weight.to(device), self.young_from)

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int,
            weights: Optional[torch.Tensor] = None) -> None:
        """One view's screen gradients (``means2d_grad`` (N, 2) pixels, or None) and ``radii``;
        ``weights`` (N,): the view's blending weights in training pixels."""
        vis = radii > 0
        if means2d_grad is not None:
            g = means2d_grad.detach().to(torch.float64)
            g = torch.stack([g[:, 0] * width / 2, g[:, 1] * height / 2], 1).norm(dim=1)
            self.accum += torch.where(vis, g, torch.zeros_like(g))
        self.count += vis.to(torch.int64)
        self.max_radius = torch.maximum(self.max_radius, radii.to(torch.int32))
        if weights is not None:
            torch.maximum(self.peak_weight, weights.to(self.peak_weight.dtype), out=self.peak_weight)

    def mean(self) -> torch.Tensor:
        return self.accum / self.count.clamp_min(1)

    def needless(self, min_weight: float, min_views: int) -> torch.Tensor:
        """(N,) bool: Gaussians that no view needs: drawn in at least ``min_views`` training views
        since the last densification, and under ``min_weight`` pixels in every one of them (the
        ones that densification made are not judged yet)."""
        out = (self.count >= min_views) & (self.peak_weight < min_weight)
        out[self.young_from:] = False
        return out

    def state_dict(self) -> dict:
        return {"accum": self.accum.cpu(), "count": self.count.cpu(), "max_radius": self.max_radius.cpu(),
                "peak_weight": self.peak_weight.cpu(), "young_from": self.young_from}


# --- relocation under a fixed budget (3DGS-MCMC, Kheradmand et al. 2024) -----------------

#: A Gaussian below this opacity is dead: relocation moves it onto a live one (3DGS-MCMC's
#: threshold; the default preset raises it, ``TrainConfig.relocate_opacity``).
DEAD_OPACITY = 0.005
#: At most this many copies of one Gaussian (the original included) in one relocation.
MAX_COPIES = 51
#: Opacities after a split stay below this (1 - opacity is raised to 1/N).
MAX_OPACITY = 1.0 - 1e-6


def split_opacity_scale(opacity: torch.Tensor, scale: torch.Tensor, copies: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scale for each of ``copies`` Gaussians that replace one of opacity
    ``opacity`` and scale ``scale`` at the same place (3DGS-MCMC, eq. 9-10).

    Args:
        opacity: (M,) opacities in (0, 1).
        scale: (M, 3) standard deviations (not logs).
        copies: (M,) int, N >= 1 Gaussians the original becomes.

    Returns: (M,) new opacity ``o' = 1 - (1 - o)^(1/N)`` (N copies stacked show the original's
    peak opacity) and (M, 3) new scale ``s * o / D`` with
    ``D = sum_{j=1..N} C(N, j) (-1)^(j+1) o'^j / sqrt(j)``, which keeps the integral of the
    stacked opacity along each axis, ``int 1 - (1 - o' g(x/s'))^N dx = int o g(x/s) dx``
    (tests/test_train.py checks it by quadrature). Computed in float64: with
    ``N o' <= -log(1 - o)`` the alternating terms stay small.
    """
    o = opacity.to(torch.float64).clamp(1e-12, MAX_OPACITY)
    n = copies.to(torch.float64).clamp(1, MAX_COPIES)
    o_new = 1.0 - torch.pow(1.0 - o, 1.0 / n)
    j = torch.arange(1, MAX_COPIES + 1, dtype=torch.float64, device=o.device)
    log_binom = torch.lgamma(n[:, None] + 1) - torch.lgamma(j + 1) - torch.lgamma((n[:, None] - j).clamp_min(0) + 1)
    terms = torch.exp(log_binom) * torch.pow(o_new[:, None], j) / j.sqrt() * torch.where(j % 2 == 1, 1.0, -1.0)
    terms = torch.where(j[None, :] <= n[:, None], terms, torch.zeros_like(terms))
    denom = terms.sum(1)
    new_scale = scale.to(torch.float64) * (o / denom)[:, None]
    return o_new.to(opacity.dtype), new_scale.to(scale.dtype)


def _copy_sources(params: dict, sources: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """The distinct rows of ``sources`` and their new opacity logits and log scales, each
    becoming 1 + (times drawn) Gaussians."""
    uniq, times = torch.unique(sources, return_counts=True)
    opac = torch.sigmoid(params["logit_opacities"].detach()[uniq])
    scale = params["log_scales"].detach()[uniq].exp()
    o_new, s_new = split_opacity_scale(opac, scale, times + 1)
    o_new = o_new.clamp(1e-12, MAX_OPACITY)
    return uniq, {"logit_opacities": torch.log(o_new) - torch.log1p(-o_new), "log_scales": s_new.log()}


def _draw(params: dict, alive: torch.Tensor, count: int, generator: torch.Generator,
          score: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``count`` indices of live Gaussians drawn with probability proportional to opacity
    (3DGS-MCMC), or to opacity times ``score`` (N,) where that is positive somewhere."""
    idx = torch.nonzero(alive).squeeze(1)
    w = torch.sigmoid(params["logit_opacities"].detach()[idx]).to(torch.float64)
    if score is not None:
        ws = w * score.detach()[idx].to(torch.float64).clamp_min(0)
        if bool(ws.sum() > 0) and bool(torch.isfinite(ws).all()):
            w = ws
    return idx[torch.multinomial(w.cpu(), count, replacement=True, generator=generator).to(idx.device)]


def share_opacity(params: dict, rows: torch.Tensor) -> None:
    """Make each of ``rows`` (distinct) ready to be copied once: its opacity and scale become
    those of one of two stacked Gaussians that render as it did (:func:`split_opacity_scale`)."""
    uniq, new = _copy_sources(params, rows)
    with torch.no_grad():
        for name, values in new.items():
            params[name][uniq] = values.to(params[name].dtype)


def relocate(params: dict, optimizer, generator: torch.Generator, dead_opacity: float = DEAD_OPACITY,
             score: Optional[torch.Tensor] = None, needless: Optional[torch.Tensor] = None) -> int:
    """Move every dead Gaussian (opacity below ``dead_opacity``, not finite, or ``needless``
    (N,) bool: no view needs it) onto a live one drawn by opacity; the source and its copies
    share its opacity and shrink so that together they render about as it did (:func:`split_opacity_scale`). The Adam moments of every row
    touched start again at zero. Returns the number moved."""
    op = torch.sigmoid(params["logit_opacities"].detach())
    finite = torch.isfinite(params["means"].detach()).all(1) & torch.isfinite(op)
    dead = (op < dead_opacity) | ~finite
    if needless is not None:
        dead |= needless
    alive = ~dead
    n_dead = int(dead.sum())
    if n_dead == 0 or not bool(alive.any()):
        return 0
    sources = _draw(params, alive, n_dead, generator, score)
    uniq, new = _copy_sources(params, sources)
    dead_idx = torch.nonzero(dead).squeeze(1)
    rows = torch.cat([uniq, dead_idx])

    def write(name, t, is_state):
        t = t.clone()
        if is_state:
            t[rows] = 0
            return t
        if name in new:
            t[uniq] = new[name].to(t.dtype)
        t[dead_idx] = t[sources]
        return t

    _replace(params, optimizer, write)
    return n_dead


def grow(params: dict, optimizer, count: int, generator: torch.Generator,
         score: Optional[torch.Tensor] = None, dead_opacity: float = DEAD_OPACITY) -> int:
    """Add ``count`` Gaussians as copies of live ones (opacity at least ``dead_opacity``)
    drawn by opacity (the same split as :func:`relocate`); new rows start with zero Adam
    moments. Returns the number added."""
    op = torch.sigmoid(params["logit_opacities"].detach())
    alive = op >= dead_opacity
    if count <= 0 or not bool(alive.any()):
        return 0
    sources = _draw(params, alive, count, generator, score)
    uniq, new = _copy_sources(params, sources)

    def write(name, t, is_state):
        t = t.clone()
        if is_state:
            t[uniq] = 0
            return torch.cat([t, torch.zeros_like(t[sources])])
        if name in new:
            t[uniq] = new[name].to(t.dtype)
        return torch.cat([t, t[sources]])

    _replace(params, optimizer, write)
    return count


#: 3DGS-MCMC's noise reaches Gaussians below about this opacity (a steep sigmoid around it).
NOISE_OPACITY = 0.005
NOISE_SHARPNESS = 100.0


def perturb_means(params: dict, lr_means: float, noise_lr: float, generator: torch.Generator) -> int:
    """3DGS-MCMC's exploration noise: move nearly transparent Gaussians by
    ``Sigma @ eps * noise_lr * lr_means * sigmoid(-k (opacity - t))`` (``Sigma`` the Gaussian's
    covariance, ``eps`` standard normal), so that they wander where the data can use them
    while opaque ones stay put. Only rows where the factor exceeds 1e-4 are touched (the
    others would move by less than a ten-thousandth of the step). Returns how many moved."""
    op = torch.sigmoid(params["logit_opacities"].detach())
    gate = torch.sigmoid(-NOISE_SHARPNESS * (op - NOISE_OPACITY))
    rows = torch.nonzero(gate > 1e-4).squeeze(1)
    if rows.numel() == 0:
        return 0
    R = quat_to_rotmat(params["quats"].detach()[rows])
    s2 = params["log_scales"].detach()[rows].exp().square()
    cov = R @ (s2[:, :, None] * R.transpose(1, 2))
    eps = torch.randn(len(rows), 3, generator=generator, dtype=cov.dtype, device=generator.device).to(cov.device)
    step = (cov @ eps[:, :, None]).squeeze(2) * (gate[rows] * noise_lr * lr_means)[:, None]
    with torch.no_grad():
        params["means"].index_add_(0, rows, step.to(params["means"].dtype))
    return int(rows.numel())
