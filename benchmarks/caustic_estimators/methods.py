"""The estimators kept for the record's comparisons, as RecGS with their own estimates.

Each subclasses :class:`recgs_addon.core.caustics.recgs.RecGS` and replaces the hooks of
``core/caustics/estimators.py``; ``register()`` lets ``--estimator NAME`` build them
(``python -m benchmarks.caustic_estimators train ...``, or ``make_method`` after ``register()``):

* ``consensus``: C = I less the multi-view consensus of the photos warped with the model's
  depth (``consensus.py``);
* ``lightfield``: a per-view light field, the low band plus one-sided coherent light over a
  floor, the survey's linear gain bringing the targets back to the mean light (``lightfield.py``);
* ``likelihood``: each point fitted to the light its views most likely saw, the survey's
  distribution of caustic gains refitted every round (``likelihood.py``).

Their settings are class attributes (the runner's ``--lf-lambda``, ``--lf-tau``,
``--light-sigma``, ``--consensus-stat``, ``--consensus-q`` set them).
"""
from __future__ import annotations

from typing import Optional

import torch

from recgs_addon.core.caustics.config import register_estimator
from recgs_addon.core.caustics.estimate import compensate_caustics
from recgs_addon.core.caustics.recgs import RecGS
from recgs_addon.core.errors import RecGSError
from recgs_addon.core.train.data import view_tensors

from . import lightfield, likelihood
from .consensus import STATS, consensus_targets

#: likelihood: training views a refit of the gain distribution renders, at most (the gains'
#: distribution needs samples, not every view; the caustic-free photos are made from the final
#: model, view by view).
FIT_VIEWS = 24


class ConsensusRecGS(RecGS):
    """C = I - (gain-restored multi-view consensus of the photos), with the model's depth."""

    #: the per-pixel statistic over the views that see a pixel (``consensus.STATS``), and the
    #: quantile of ``quantile``
    stat = "mean"
    q = 0.25

    def __init__(self, trainer, ccfg):
        if ccfg.caustic_model != "additive":
            raise RecGSError("the consensus estimator makes additive caustic maps (caustic model additive)")
        if self.stat not in STATS:
            raise ValueError(f"unknown consensus statistic {self.stat!r} (choose from {', '.join(STATS)})")
        super().__init__(trainer, ccfg)

    @property
    def _by_view(self) -> bool:
        return False

    def _estimates(self, ids):
        tr, ids = self.trainer, self.data.train_ids
        views = []
        for i in ids:
            cam, photo = self.data.view(i, 1)
            out = tr.render_output(i)
            viewmat, K = view_tensors(cam, tr.device)
            views.append(dict(photo=photo, depth=out.depth, alpha=out.alpha, viewmat=viewmat, K=K))
        targets, _, _ = consensus_targets(views, self.stat, self.q)
        return {i: v["photo"] - t for i, v, t in zip(ids, views, targets)}


class LightFieldRecGS(RecGS):
    """Per-view light fields against the render brought down to the floor light; the targets
    are the photos under the floor light brought to the survey's mean light."""

    #: TV weight (log light per pixel of edge) and dead band (log light) below which light is not taken out
    lam = 0.05
    tau = 0.02

    def __init__(self, trainer, ccfg):
        if not (0 <= self.lam < float("inf") and 0 <= self.tau < float("inf")):   # NaN fails this too
            raise RecGSError(f"light-field TV weight and dead band must be >= 0, got {self.lam}, {self.tau}")
        #: the survey's linear gain from the floor light to the mean light (3,)
        self.light_gain = torch.ones(3, device="cpu")
        super().__init__(trainer, ccfg)

    @property
    def _by_view(self) -> bool:
        return False

    def _decaustic(self, image, cmap):   # the photo under the floor light, brought to the survey's mean light
        return lightfield.scale_linear(lightfield.remove_light(image, cmap), self.light_gain)

    def _estimate(self, image, rgb, k):
        return self._light_fields([image], [rgb], k)[0]

    def _light_fields(self, images: list, renders: list, k: int) -> torch.Tensor:
        """(B, H, W) light fields of views of one size; the model renders the mean light, so its
        render is brought down by the survey gain first."""
        q = torch.stack([lightfield.grey_log_ratio(i, lightfield.scale_linear(r, 1.0 / self.light_gain))
                         for i, r in zip(images, renders)])
        return lightfield.light_fields(q, k, self.lam, self.tau)

    def _maps_from(self, ids, kept, renders):
        """Every training view's light field (batched by image size), then the survey gain that
        brings the targets under the floor light back to the photos' mean light."""
        ids = self.data.train_ids
        by_size: dict[tuple, list[int]] = {}
        for i in ids:
            by_size.setdefault(tuple(renders[i].shape), []).append(i)
        new = {}
        for group in by_size.values():
            fields = self._light_fields([self.data.view(i, 1)[1] for i in group], [renders[i] for i in group], self.k)
            new.update(zip(group, fields))
        photos = [self.data.view(i, 1)[1] for i in ids]
        self.light_gain = lightfield.linear_gain((p, lightfield.remove_light(p, new[i])) for p, i in zip(photos, ids))
        return new

    def _forget_light(self) -> None:
        self.light_gain = torch.ones(3, device="cpu")

    def summary(self) -> dict:
        return {**super().summary(), "light_gain": [round(float(x), 4) for x in self.light_gain]}

    def state_dict(self) -> dict:
        s = super().state_dict()
        s["caustic"]["light_gain"] = self.light_gain.clone()
        return s

    def load_state_dict(self, s: dict) -> None:
        if "light_gain" in s["caustic"]:   # before the maps are set: the targets use it
            self.light_gain = s["caustic"]["light_gain"].clone()
        super().load_state_dict(s)


class LikelihoodRecGS(RecGS):
    """The views fitted to the survey's gain likelihood, refitted every round; a view's light
    is its photo over the render, smoothed."""

    #: the light's blur in pixels at 320 px wide (scaled with the image)
    sigma = 1.0

    def __init__(self, trainer, ccfg):
        #: the survey's caustic gain distribution, refitted every recurrence
        self.gain_model: Optional[likelihood.GainLikelihood] = None
        self._previous_gain: Optional[likelihood.GainLikelihood] = None
        super().__init__(trainer, ccfg)

    def _sigma(self, image: torch.Tensor) -> float:
        return self.sigma * image.shape[1] / 320.0

    def _scored_against(self, image, render):   # its own light map follows the render too closely to score it
        return compensate_caustics(image, render, self._eval_k, "additive", False)

    def _decaustic(self, image, cmap):
        return likelihood.remove_light(image, cmap)

    def _estimate(self, image, rgb, k):
        return likelihood.light_map(image, rgb, self._sigma(image))

    def takes_light_off(self) -> bool:
        return self.gain_model is not None

    @torch.no_grad()
    def decaustic_image(self, index: int) -> torch.Tensor:
        """The light of the view against the model as it is now."""
        image = self.data.view(index, 1)[1]
        if self.gain_model is None:
            return image
        return self._decaustic(image, self._estimate(image, self.trainer.render_view(index), 0))

    def _set_maps(self, maps) -> None:   # the likelihood fits the photos themselves
        self.maps = {i: m.to(torch.float16) for i, m in maps.items()}
        self.targets.clear()

    def _round_views(self) -> list[int]:
        """All the training views of a small survey, an evenly spread :data:`FIT_VIEWS` of a large one."""
        ids = self.data.train_ids
        if len(ids) <= FIT_VIEWS:
            return list(ids)
        return [ids[int(k * len(ids) / FIT_VIEWS)] for k in range(FIT_VIEWS)]

    def _maps_from(self, ids, kept, renders):
        """Refit the survey's gain likelihood to the residuals of views ``ids`` (every other
        pixel of each) and fit it from now on; their light maps."""
        samples = [likelihood.log_ratio(self.data.view(i, 1)[1], renders[i])[::2, ::2].reshape(-1) for i in ids]
        self._previous_gain = self.gain_model
        self.gain_model = likelihood.GainLikelihood.fit(torch.cat(samples))
        self._use_likelihood()
        return {i: likelihood.light_map(self.data.view(i, 1)[1], renders[i], self._sigma(renders[i])) for i in ids}

    def _change(self, ids, new) -> float:   # the light maps follow the model's texture; the gains' distribution settles
        return self.gain_model.distance(self._previous_gain) if self._previous_gain is not None else 1.0

    def _use_likelihood(self) -> None:
        """Fit the views to the gain likelihood from the next step on."""
        if isinstance(self.trainer.objective, likelihood.LikelihoodObjective):
            self.trainer.objective.gain = self.gain_model
        else:
            self.trainer.set_objective(likelihood.LikelihoodObjective(self.gain_model, self._sigma,
                                                                      reference=self._reference))

    def _forget_light(self) -> None:
        self.gain_model = None

    def _view_scores(self, render, photo) -> dict:
        """The mean data term of the gain likelihood against the photo (lower is more likely)."""
        if self.gain_model is None:
            return {}
        w = render.clamp(0.02, 1.0)
        return {"nll": float((w * self.gain_model(likelihood.log_ratio(photo, render))).mean() / w.mean())}

    def state_bytes(self) -> int:
        """A light map, float16 (H, W), of each view a refit renders."""
        return 2 * self.data.training_pixels(self._round_views())

    def state_dict(self) -> dict:
        s = super().state_dict()
        s["caustic"]["gain_model"] = None if self.gain_model is None else self.gain_model.state_dict()
        return s

    def load_state_dict(self, s: dict) -> None:
        super().load_state_dict(s)
        if s["caustic"].get("gain_model") is not None:
            self.gain_model = likelihood.GainLikelihood.from_state(s["caustic"]["gain_model"])
            if self.stage != "warmup" and not self.dropped:
                self._use_likelihood()


#: Every estimator kept for comparisons, by its ``--estimator`` name.
METHODS = {"consensus": ConsensusRecGS, "lightfield": LightFieldRecGS, "likelihood": LikelihoodRecGS}


def register() -> None:
    """Let ``--estimator NAME`` (``CausticConfig.estimator``) build each of :data:`METHODS`."""
    for name, method in METHODS.items():
        register_estimator(name, method)
