"""Density control as the trainer runs it: when it densifies, how many Gaussians it may add
(the budget, ``growth_rate``) and when growth is over; INRIA's clone/split/prune or
3DGS-MCMC's relocation and growth, with the operations themselves in ``density.py``.

:class:`DensityMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``params``,
``optimizer``, ``stats``, ``budget`` and ``step``)."""
from __future__ import annotations

import torch

from . import density


class DensityMixin:
    """The trainer's density control (see the module's docstring)."""

    def densifying(self) -> bool:
        return self.step < self.cfg.densify_until and not self.growth_frozen

    def _uses_gradient_stats(self) -> bool:
        """Density control reads the accumulated screen gradients (clone/split, or MCMC
        drawing by gradient); otherwise a step need not accumulate them."""
        c = self.cfg
        return c.strategy == "adc" or c.mcmc_draw == "gradient"

    def _growth_room(self, n: int, unbounded: int) -> int:
        """Gaussians density control may add to a model of ``n``: up to the budget (``unbounded``
        without one), at most ``growth_rate`` of the model."""
        room = (self.budget - n) if self.budget is not None else unbounded
        if self.cfg.growth_rate > 0:
            room = min(room, max(1, int(self.cfg.growth_rate * n)))
        return room

    def growth_over(self) -> bool:
        """Density control adds no more Gaussians: growth frozen, past its last step, or the
        model at its budget (within 1 %: pruning keeps it just below). The SH probation and
        the plateau stop wait for this, not for the end of the densification window: a model
        that reaches its budget early should not train its remaining minutes at SH degree 0."""
        n = int(self.params["means"].shape[0])
        return (self.growth_frozen or not self.densifying()
                or (self.budget is not None and self.step > self.cfg.densify_from and n >= 0.99 * self.budget))

    def densify(self) -> dict:
        """Clone small and split large Gaussians with high screen gradient, within the budget;
        prune transparent, huge and never-visible ones."""
        c = self.cfg
        if c.strategy == "mcmc":
            return self._relocate_and_grow()
        p = self.params
        n0 = p["means"].shape[0]
        grads = self.stats.mean().to(self.device)
        max_scale = p["log_scales"].detach().exp().max(1).values
        high = grads >= c.densify_grad_threshold
        clone = high & (max_scale <= density.PERCENT_DENSE * self.extent)
        split = high & ~clone
        room = self._growth_room(n0, unbounded=n0 * 10)
        want = int(clone.sum() + split.sum())  # a split adds one net Gaussian
        if want > max(room, 0):
            cand = torch.nonzero(clone | split).squeeze(1)
            keep = cand[torch.argsort(grads[cand], descending=True, stable=True)[: max(room, 0)]]
            sel = torch.zeros_like(clone)
            sel[keep] = True
            clone &= sel
            split &= sel
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            density.append(p, self.optimizer, {n: v.detach()[clone] for n, v in p.items()})
        if n_split:
            children = density.split_values(p, torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=self.device)]), self.gen)
            density.append(p, self.optimizer, children)
        n = p["means"].shape[0]
        opac = torch.sigmoid(p["logit_opacities"].detach())
        prune = opac < density.PRUNE_OPACITY
        prune[:n0] |= split  # split originals are replaced by their children
        if self.reset_done:
            radius = torch.cat([self.stats.max_radius, torch.zeros(n - n0, dtype=torch.int32, device=self.device)])
            big = p["log_scales"].detach().exp().max(1).values > density.PRUNE_WORLD_SCALE * self.extent
            prune |= (radius > density.PRUNE_SCREEN_RADIUS) | big
        if bool(prune.all()):
            prune[torch.argmax(opac)] = False  # never prune everything (the backward needs one)
        if prune.any():
            density.remove(p, self.optimizer, ~prune)
        self.stats = density.GradientStats.zeros(p["means"].shape[0], self.device)
        return {"cloned": n_clone, "split": n_split, "pruned": int(prune.sum())}

    def _relocate_and_grow(self) -> dict:
        """3DGS-MCMC's density control: move dead Gaussians onto live ones, then add copies of
        live ones (drawn by opacity) up to the budget, at most ``growth_rate`` of the model."""
        c, p = self.cfg, self.params
        score = self.stats.mean().to(self.device) if c.mcmc_draw == "gradient" else None
        moved = density.relocate(p, self.optimizer, self.gen, dead_opacity=c.relocate_opacity, score=score)
        n = p["means"].shape[0]
        added = density.grow(p, self.optimizer, self._growth_room(n, unbounded=n), self.gen, score=score,
                             dead_opacity=c.relocate_opacity)
        self.stats = density.GradientStats.zeros(p["means"].shape[0], self.device)
        return {"relocated": moved, "added": added}
