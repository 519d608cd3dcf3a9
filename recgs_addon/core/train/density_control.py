"""Density control as the trainer runs it: when it densifies, how many Gaussians it may add
(the budget, ``growth_rate``) and when growth is over; what a densification does is the
configured strategy's (``strategies.py``: INRIA's clone/split/prune or 3DGS-MCMC's relocation
and growth), with the operations themselves in ``density.py``.

:class:`DensityMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``params``,
``optimizer``, ``stats``, ``budget`` and ``step``)."""
from __future__ import annotations


from . import density


class DensityMixin:
    """The trainer's density control (see the module's docstring)."""

    def densifying(self) -> bool:
        """Density control runs: before ``densify_until`` steps, growth not frozen, and with a time
        limit before ``densify_until_share`` of it (a run that ends right after a densification
        ends on Gaussians that have not settled)."""
        c = self.cfg
        if self.step >= c.densify_until or self.growth_frozen:
            return False
        return not (self.time_limit_s and c.densify_until_share < 1.0 and self.run_share() >= c.densify_until_share)

    def _uses_gradient_stats(self) -> bool:
        """Density control reads the accumulated screen gradients (clone/split, or MCMC
        drawing by gradient); otherwise a step need not accumulate them."""
        return self.cfg.density.uses_gradient_stats()

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
        """One densification of the configured strategy (strategies.py), then fresh gradient
        statistics for the next window. Returns what it did (counts)."""
        info = self.cfg.density.densify(self)
        young = info.pop("young", 0)   # the rows it made, at the end
        self.stats = density.GradientStats.zeros(self.params["means"].shape[0], self.device, young=young)
        for key, count in info.items():
            self.density_totals[key] = self.density_totals.get(key, 0) + int(count)
        return info
