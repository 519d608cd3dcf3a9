"""Density control strategies: which Gaussians are added, moved and removed as training goes,
each with its own settings (as gsplat's ``strategy/`` package has them).

* :class:`CloneSplit` (``"adc"``, the default): INRIA's adaptive density control, clone small
  and split large Gaussians whose screen-space gradient is high, prune transparent ones.
* :class:`MCMC` (``"mcmc"``): 3DGS-MCMC, move faded Gaussians onto live ones and grow by
  copies drawn by opacity, under L1 regularisers on opacity and scale.

A strategy's defaults are the default preset's (benchmarks/RESULTS.md#training-density-default,
#budget-by-seabed, #training-relocation-five-minutes). Each also sets how large an automatic
budget may grow (``pixels_per_gaussian``, ``surface_pixels_per_gaussian``: trainer.auto_budget).
The operations on the parameters and optimiser state are in :mod:`.density`; the trainer calls
:meth:`Strategy.densify` on its densification steps and :meth:`Strategy.after_step` after
each optimiser step while the model is densifying.

Nothing here imports torch until a strategy runs: the settings are read in Blender's own
process (the sidebar, batch mode), which has no torch.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..errors import RecGSError


@dataclass
class Strategy:
    """What every density control has: its name and the automatic budget's rule."""
    #: at most (training pixels / this) Gaussians under an automatic budget (0: no such cap)
    pixels_per_gaussian: float = 0.0
    #: ... and at most (training pixels / median views of a sparse point / this) (0: none)
    surface_pixels_per_gaussian: float = 0.0
    #: significance: a Gaussian drawn in at least ``prune_views`` training views since the last
    #: densification that supplied under this many pixels to each of them (its blending weight,
    #: at the training resolution) is one no view needs, and goes; growth copies only Gaussians
    #: that supply at least twice this, so that each copy is one a view carries (0: off). A
    #: quarter of a pixel: 1 px took 7 % of the model a densification and shook the fit
    #: (benchmarks/RESULTS.md#prune-by-significance)
    prune_weight: float = 0.25
    prune_views: int = 3
    #: at most this share of the model goes as needless in one densification, the least
    #: significant first (1: no cap; a cap of 2 % did not steady the fit where 1 px pruning
    #: shook it, a smaller prune_weight did: benchmarks/RESULTS.md#prune-by-significance)
    prune_share: float = 1.0
    #: the strategy's name (what the command line's ``--density`` and a checkpoint give)
    name: str = field(default="", init=False)

    def validate(self) -> None:
        if self.pixels_per_gaussian < 0 or self.surface_pixels_per_gaussian < 0:
            raise RecGSError(f"{self.name}: pixels per Gaussian must be 0 (no cap) or above")
        if not self.prune_weight >= 0:
            raise RecGSError(f"{self.name}: --prune-weight must be 0 (off) or a number of pixels above it, "
                             f"got {self.prune_weight}")
        if self.prune_views < 1 or not 0 < self.prune_share <= 1:
            raise RecGSError(f"{self.name}: prune_views must be at least 1 and prune_share in (0, 1], got "
                             f"{self.prune_views} and {self.prune_share}")

    def uses_gradient_stats(self) -> bool:
        """Whether densification reads the screen-space gradients a step accumulates."""
        return False

    def uses_significance(self) -> bool:
        """Whether densification reads the blending weights a step records."""
        return self.prune_weight > 0

    def needless(self, tr):
        """(N,) bool: the Gaussians no view needs (see ``prune_weight``), or None when off."""
        if not self.uses_significance():
            return None
        import torch

        out = tr.stats.needless(self.prune_weight, self.prune_views).to(tr.device)
        most = int(self.prune_share * out.shape[0])
        if int(out.sum()) > most:   # the least significant first
            rows = torch.nonzero(out).squeeze(1)
            peak = tr.stats.peak_weight.to(tr.device)[rows]
            out[:] = False
            out[rows[torch.argsort(peak, stable=True)[:most]]] = True
        return out

    def regularisers(self) -> tuple[float, float]:
        """(opacity, scale) weights of the L1 terms on the whole model (0: none)."""
        return 0.0, 0.0

    def densify(self, tr) -> dict:
        """One densification: counts of what it did (and ``young``: the rows it made, at the
        end of the model, which the next one does not judge as needless yet)."""
        raise NotImplementedError

    def after_step(self, tr) -> None:
        """Called after each optimiser step while the model is densifying."""


@dataclass
class CloneSplit(Strategy):
    """INRIA's adaptive density control (see the module)."""
    pixels_per_gaussian: float = 8.0
    #: one per 5 pixels of seabed: with significance pruning, 0.70x the Gaussians of 3.5 and
    #: higher held-out scores in five-minute runs (benchmarks/RESULTS.md#prune-by-significance)
    surface_pixels_per_gaussian: float = 5.0
    #: mean screen-space gradient above which a Gaussian is cloned or split
    grad_threshold: float = 2e-4
    #: with significance on, a clone and its original share the original's opacity and shrink
    #: so that the pair renders as the original did (3DGS-MCMC's split), instead of INRIA's
    #: copy, which makes the spot more opaque until the steps after undo it
    clone_keeps_render: bool = True
    name: str = field(default="adc", init=False)

    def uses_gradient_stats(self) -> bool:
        return True

    def densify(self, tr) -> dict:
        """Clone small and split large Gaussians with high screen gradient, within the budget
        (the room those no view needs leave included); prune transparent, huge and
        never-visible ones, and those no view needs."""
        import torch

        from . import density

        p = tr.params
        n0 = p["means"].shape[0]
        grads = tr.stats.mean().to(tr.device)
        max_scale = p["log_scales"].detach().exp().max(1).values
        high = grads >= self.grad_threshold
        needless = self.needless(tr)
        if needless is not None:   # copies of a Gaussian that supplies little would supply less
            high &= tr.stats.peak_weight.to(tr.device) >= 2 * self.prune_weight
        clone = high & (max_scale <= density.PERCENT_DENSE * tr.extent)
        split = high & ~clone
        n_needless = int(needless.sum()) if needless is not None else 0
        room = tr._growth_room(n0 - n_needless, unbounded=n0 * 10)
        want = int(clone.sum() + split.sum())  # a split adds one net Gaussian
        if want > max(room, 0):
            cand = torch.nonzero(clone | split).squeeze(1)
            keep = cand[torch.argsort(grads[cand], descending=True, stable=True)[: max(room, 0)]]
            sel = torch.zeros_like(clone)
            sel[keep] = True
            clone &= sel
            split &= sel
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone and needless is not None and self.clone_keeps_render:
            density.share_opacity(p, torch.nonzero(clone).squeeze(1))
        if n_clone:
            density.append(p, tr.optimizer, {n: v.detach()[clone] for n, v in p.items()})
        if n_split:
            mask = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=tr.device)])
            density.append(p, tr.optimizer, density.split_values(p, mask, tr.gen))
        n = p["means"].shape[0]
        opac = torch.sigmoid(p["logit_opacities"].detach())
        prune = opac < density.PRUNE_OPACITY
        prune[:n0] |= split  # split originals are replaced by their children
        if needless is not None:
            prune[:n0] |= needless
        if tr.reset_done:
            radius = torch.cat([tr.stats.max_radius, torch.zeros(n - n0, dtype=torch.int32, device=tr.device)])
            big = p["log_scales"].detach().exp().max(1).values > density.PRUNE_WORLD_SCALE * tr.extent
            prune |= (radius > density.PRUNE_SCREEN_RADIUS) | big
        if bool(prune.all()):
            prune[torch.argmax(opac)] = False  # never prune everything (the backward needs one)
        if prune.any():
            density.remove(p, tr.optimizer, ~prune)
        return {"cloned": n_clone, "split": n_split, "pruned": int(prune.sum()), "needless": n_needless,
                "young": int((~prune[n0:]).sum())}


@dataclass
class MCMC(Strategy):
    """3DGS-MCMC (see the module). Its defaults: the paper's regularisers, relocation below
    opacity 0.1 (the paper's 0.005 left the budget on faint Gaussians: +0.27 and +0.51 dB at
    59,733 Gaussians after 3000 steps, two seeds, 8 % less time a step; nerfstudio culls below
    0.1 too) and one Gaussian per 6x6 block of training pixels."""
    pixels_per_gaussian: float = 36.0
    #: off unless asked (``--prune-weight``): relocation already moves what fades, and moving the
    #: needless too is unmeasured
    prune_weight: float = 0.0
    #: L1 weight on the mean opacity (3DGS-MCMC: 0.01)
    opacity_reg: float = 0.01
    #: L1 weight on the mean scale over the scene's extent (3DGS-MCMC: 0.01, unnormalised)
    scale_reg: float = 0.01
    #: Gaussians below this opacity are relocated (3DGS-MCMC: 0.005)
    relocate_opacity: float = 0.1
    #: draw sources by "opacity" (3DGS-MCMC) or "gradient" (opacity x screen gradient)
    draw: str = "opacity"
    #: exploration noise on nearly transparent Gaussians (3DGS-MCMC: 5e5; 0: none)
    noise_lr: float = 0.0
    name: str = field(default="mcmc", init=False)

    def validate(self) -> None:
        super().validate()
        if not 0 < self.relocate_opacity < 1:
            raise RecGSError(f"relocate_opacity must be between 0 and 1, got {self.relocate_opacity}")
        if self.draw not in ("opacity", "gradient"):
            raise RecGSError(f"mcmc: draw must be opacity or gradient, got {self.draw!r}")

    def uses_gradient_stats(self) -> bool:
        return self.draw == "gradient"

    def regularisers(self) -> tuple[float, float]:
        return self.opacity_reg, self.scale_reg

    def densify(self, tr) -> dict:
        """Move dead Gaussians onto live ones, then add copies of live ones (drawn by opacity)
        up to the budget, at most ``growth_rate`` of the model."""
        from . import density

        p = tr.params
        score = tr.stats.mean().to(tr.device) if self.draw == "gradient" else None
        moved = density.relocate(p, tr.optimizer, tr.gen, dead_opacity=self.relocate_opacity, score=score,
                                 needless=self.needless(tr))
        n = p["means"].shape[0]
        added = density.grow(p, tr.optimizer, tr._growth_room(n, unbounded=n), tr.gen, score=score,
                             dead_opacity=self.relocate_opacity)
        return {"relocated": moved, "added": added}

    def after_step(self, tr) -> None:
        if self.noise_lr:
            from . import density

            density.perturb_means(tr.params, tr._means_lr(), self.noise_lr, tr.gen)


#: name -> strategy class
STRATEGIES: dict[str, type[Strategy]] = {cls().name: cls for cls in (CloneSplit, MCMC)}
#: The density control of every mode unless asked otherwise: INRIA's clone/split. The caustic
#: methods need its sharper model (on the sample, 4 minutes, recgs: caustic-free images 23.61 dB
#: against MCMC's 21.88), and plain 3DGS scores higher with it too: 5 minutes on clean photos,
#: +2.0 dB held-out on the 24-photo sample and +3.0 and +3.5 dB on a 144-frame dive survey
#: (benchmarks/RESULTS.md#training-density-default).
DEFAULT_STRATEGY = "adc"
#: Settings saved by checkpoints from before the strategies owned them -> the strategy's name.
_RENAMED = {"densify_grad_threshold": "grad_threshold", "mcmc_draw": "draw"}


def _strategy_class(name: str) -> type[Strategy]:
    """The class of strategy ``name``; RecGSError for an unknown name."""
    if name not in STRATEGIES:
        raise RecGSError(f"unknown density strategy {name!r} (choose {' or '.join(STRATEGIES)})")
    return STRATEGIES[name]


def strategy_fields(name: str) -> set[str]:
    """The settings strategy ``name`` takes (unknown names refused)."""
    return {f.name for f in fields(_strategy_class(name)) if f.init}


def make_strategy(name: str = DEFAULT_STRATEGY, **settings) -> Strategy:
    """Strategy ``name`` with ``settings`` over its defaults (unknown names refused)."""
    return _strategy_class(name)(**settings)


def strategy_from_dict(d: dict) -> Strategy:
    """The strategy a checkpoint's config saved: ``{"name": ..., settings}``, or the flat keys of
    the config from before the strategies owned their settings (``strategy`` and its fields)."""
    name = d.get("name", d.get("strategy", DEFAULT_STRATEGY))
    own = strategy_fields(name)
    settings = {_RENAMED.get(k, k): v for k, v in d.items()}
    settings.setdefault("prune_weight", 0.0)   # saved before significance pruning: a resumed run goes on without
    return make_strategy(name, **{k: v for k, v in settings.items() if k in own})


def default_strategy() -> Strategy:
    return make_strategy(DEFAULT_STRATEGY)

