"""Evaluation on the held-out views and what a run decides from it: keep-best (with the
snapshots it keeps and restores), the growth freeze of budget "auto", the SH probation and
the plateau stop.

:class:`EvaluationMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``data``,
``params``, ``objective``, ``history`` and ``step``)."""
from __future__ import annotations

import contextlib
import math
import time
from typing import Optional

import numpy as np
import torch

from ..model.gaussians import num_sh_coeffs
from ..render.rasterizer import render
from . import density
from .data import view_tensors
from .losses import psnr, ssim


#: Why a run without a time limit ends when held-out PSNR stops improving.
PLATEAU = "held-out PSNR plateau"
#: Where the photos carry moving light or the run models the water, ``keep_best`` chooses among
#: the models trained at least this share of the run (see ``best_from_share``).
BEST_FROM_SHARE = 0.5


class EvaluationMixin:
    """The trainer's held-out evaluation, snapshots and stopping rules (see the module's docstring)."""

    # --- snapshots (a method that keeps or restores a model uses these) -----------------
    def snapshot(self) -> dict:
        """A copy of the model: parameters, the active SH degree, the water's coefficients and
        the lamp's terms."""
        return {"params": {n: v.detach().clone() for n, v in self.params.items()}, "sh_degree": self.sh_degree,
                "medium": None if self.medium is None else self.medium.raw.detach().clone(),
                "lamp": None if self.lamp is None else self.lamp.raw.detach().clone()}

    def _swap_medium(self, raw, lamp_raw=None) -> tuple:
        """Put ``raw`` into the water's coefficients and ``lamp_raw`` into the lamp's terms
        (each where both exist); returns what was there."""
        old = []
        for model, new in ((self.medium, raw), (self.lamp, lamp_raw)):
            if model is None or new is None:
                old.append(None)
                continue
            old.append(model.raw.detach().clone())
            with torch.no_grad():
                model.raw.copy_(new)
        return tuple(old)

    @contextlib.contextmanager
    def using(self, snap: dict):
        """Render and evaluate with a ``snapshot()``'s model for the ``with`` block (the
        trainer's own parameters, optimiser and statistics untouched)."""
        saved = self.params, self.sh_degree
        self.params, self.sh_degree = snap["params"], snap["sh_degree"]
        saved_medium = self._swap_medium(snap.get("medium"), snap.get("lamp"))
        try:
            yield self
        finally:
            self.params, self.sh_degree = saved
            self._swap_medium(*saved_medium)

    def restore(self, snap: dict) -> None:
        """Go back to a ``snapshot()``: its parameters with fresh Adam moments and gradient
        statistics, and its SH degree."""
        self.params = {n: torch.nn.Parameter(v.detach().clone().to(self.device)) for n, v in snap["params"].items()}
        self.optimizer = self._make_optimizer()
        self.stats = density.GradientStats.zeros(self.params["means"].shape[0], self.device)
        self.sh_degree = snap["sh_degree"]
        self._swap_medium(snap.get("medium"), snap.get("lamp"))

    def restart_plateau(self, forget_best: bool = False) -> None:
        """Start counting evaluations without gain afresh (``forget_best``: and the best score
        too): a driving method does this when what the trainer fits has changed."""
        self.since_best = 0
        if forget_best:
            self.best_psnr = -math.inf

    # --- evaluation ---------------------------------------------------------------------
    @torch.no_grad()
    def render_output(self, index: int, seen: bool = True, level: int = 1):
        """The whole :class:`~..render.rasterizer.RenderOutput` (rgb, alpha, depth, ...) of
        camera ``index`` at the training resolution (``level``: that divided by it): its ``rgb``
        as the camera sees it through the water (``seen``; what the photos hold) or the seabed's
        true colour."""
        t = time.perf_counter()
        cam = self.data.camera(index, level)
        out = self.render_camera(cam)
        if seen and self.forms_image:
            out = out._replace(rgb=self.as_seen(out, cam))
        dt = time.perf_counter() - t
        if level == 1:   # the finishing's renders are at the training resolution
            self._render_s = dt if self._render_s is None else 0.8 * self._render_s + 0.2 * dt
            self._render_step = self.step
        return out

    @torch.no_grad()
    def render_camera(self, cam):
        """The :class:`~..render.rasterizer.RenderOutput` of any camera ``cam`` (a
        :class:`~..model.cameras.Camera` at its own size: a training view, a look frame), its
        ``rgb`` in true colour (no water, no lamp; :meth:`render_output` adds them)."""
        viewmat, K = view_tensors(cam, self.device)
        p = self.params
        return render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], self._sh(),
                      viewmat, K, cam.width, cam.height, sh_degree=self.sh_degree,
                      background=self._background(), compiled=self.compiler.compiled())

    def render_view(self, index: int, seen: bool = True) -> torch.Tensor:
        """(H, W, 3) render of camera ``index`` at the training resolution (not clamped), as
        seen through the water or (``seen=False``) in true colour."""
        return self.render_output(index, seen).rgb

    def render_pair(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(as seen through the water, true colour) renders of camera ``index``, both clamped to
        [0, 1], from one render (the same image twice without water)."""
        out = self.render_output(index, seen=False)
        return self.as_seen(out, self.data.view(index, 1)[0]).clamp(0, 1), out.rgb.clamp(0, 1)

    def heldout_ids(self, ids: Optional[list[int]] = None) -> list[int]:
        """The held-out views a score is taken on (``ids``, default all, cut to ``eval_views``)."""
        ids = self.data.test_ids if ids is None else ids
        return ids[: self.cfg.eval_views] if self.cfg.eval_views else ids

    @torch.no_grad()
    def heldout_psnr(self) -> Optional[float]:
        """Mean PSNR of the held-out renders against the held-out photos as captured (moving
        light and all), or None without held-out views. A held-out view's caustics are its
        own, so no model predicts them: they add the same error to every model, and the model
        closer to the caustic-free scene scores higher."""
        ids = self.heldout_ids()
        if not ids:
            return None
        return float(sum(psnr(self.render_view(i).clamp(0, 1), self.data.view(i, 1)[1], self.counts(i))
                         for i in ids) / len(ids))

    def counts(self, index: int, level: int = 1) -> Optional[torch.Tensor]:
        """(H, W) bool: the pixels of view ``index`` at pyramid ``level`` that count in losses
        and scores (off the survey's burned-in overlay, ``data.valid``), or None: all of them."""
        cam = self.data.camera(index, level)
        return self.data.valid(index, cam.height, cam.width)

    @torch.no_grad()
    def evaluate(self, ids: Optional[list[int]] = None) -> dict:
        """Mean PSNR (dB) and SSIM over held-out views at the training resolution: ``psnr`` /
        ``ssim`` against the held-out images (what the run decides on), ``psnr_gt`` /
        ``ssim_gt`` against the ground truth where the survey has one, and ``psnr_captured``
        against the held-out photos as captured (what ``keep_best`` decides on)."""
        ids = self.heldout_ids(ids)
        if not ids:
            return {}
        ps, ss, pg, sg, pc = [], [], [], [], []
        for i in ids:
            rgb, true = self.render_pair(i)   # true colour: what a ground truth holds
            photo = self.data.view(i, 1)[1]
            ref = self.objective.reference(i, photo, rgb)
            keep = self.counts(i)
            ps.append(psnr(rgb, ref, keep))
            pc.append(ps[-1] if ref is photo else psnr(rgb, photo, keep))
            ss.append(float(ssim(rgb, ref)))
            gt = self.data.gt_view(i)
            if gt is not None:
                pg.append(psnr(true, gt, keep))
                sg.append(float(ssim(true, gt)))
        out = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "psnr_captured": float(np.mean(pc))}
        if pg:
            out.update(psnr_gt=float(np.mean(pg)), ssim_gt=float(np.mean(sg)))
        return out

    def _after_eval(self, metrics: dict) -> None:
        """Growth freeze (budget auto), SH probation and the plateau stop, from held-out PSNR."""
        c = self.cfg
        value = metrics.get("psnr")
        if value is None:
            return
        self.history.append({"iteration": self.step, "psnr": value, "ssim": metrics["ssim"],
                             **{k: metrics[k] for k in ("psnr_gt", "ssim_gt", "psnr_captured") if k in metrics},
                             "gaussians": int(self.params["means"].shape[0]), "sh_degree": self.sh_degree,
                             "elapsed": round(self.elapsed, 2), "phase": self.phase})
        if c.keep_best:
            self._consider_best(metrics[self.best_by])
        if value > self.best_psnr + c.plateau_min_gain:
            self.best_psnr, self.since_best = value, 0
        else:
            self.since_best += 1
        # growth: with budget "auto", stop adding Gaussians once held-out PSNR stalls
        full_res = [h for h in self.history if h["iteration"] >= self._full_res_from()]
        if (c.budget is None and not self.growth_frozen and self.step >= c.densify_from
                and len(full_res) > c.growth_patience):
            recent = [h["psnr"] for h in full_res[-(c.growth_patience + 1):]]
            if max(recent[1:]) < recent[0] + 5 * c.plateau_min_gain:
                self.growth_frozen = True
                self.budget = int(self.params["means"].shape[0])
        # SH degree: try one more degree once growth has settled; keep it only if it helps
        if c.sh_policy == "probation" and not self.sh_state["done"] and self.growth_over():
            trial = self.sh_state["trial"]
            if trial is None and self.since_best >= 1:
                self.sh_state["trial"] = {"from": self.sh_degree, "psnr": self.best_psnr, "step": self.step}
                self.sh_degree += 1
                self.since_best = 0
            elif trial is not None and self.step - trial["step"] >= c.sh_probation:
                if self.best_psnr < trial["psnr"] + c.sh_min_gain:  # did not help: revert
                    self.sh_degree = trial["from"]
                    k = num_sh_coeffs(self.sh_degree)
                    with torch.no_grad():
                        self.params["sh_rest"][:, k - 1:] = 0
                    self.sh_state["done"] = True
                elif self.sh_degree >= c.sh_degree:
                    self.sh_state["done"] = True
                self.sh_state["trial"] = None
                self.since_best = 0
        if (c.plateau_patience and self.since_best >= c.plateau_patience
                and self.growth_over() and self.sh_state["done"]
                and self.sh_state["trial"] is None):
            if self.plateau_step is None:
                self.plateau_step = self.step
            # with a time limit the run uses its time (the best model is kept, so steps that
            # do not help cost nothing); without one a plateau ends it
            if self.time_limit_s is None:
                self.done_reason = PLATEAU

    def best_from_share(self) -> float:
        """The share of the run (its time limit, else its steps) a model must have trained to
        be kept by ``keep_best``: :data:`BEST_FROM_SHARE` where the photos carry light that moves
        over the seabed or the run models the water, else 0. Under moving light the held-out
        photos carry light no model can predict, and a blurred early model, which averages it,
        scores best on them; under water an early model's colour is the water's first guess (on
        a coastal survey with caustics, the best held-out model as seen was step 250 of 9,885,
        4.7 dB below plain against the true colour)."""
        moving = bool((getattr(self, "light", None) or {}).get("caustics"))
        return BEST_FROM_SHARE if moving or getattr(self, "medium", None) is not None else 0.0

    def run_share(self) -> float:
        """How far the run has come: its time over its limit, else its steps over its iterations."""
        if self.time_limit_s:
            return self.elapsed / self.time_limit_s
        return self.step / max(self.cfg.iterations, 1)

    def _consider_best(self, score: float) -> None:
        """Remember the model if it scores best so far on the held-out photos as captured.
        Evaluations within half a densification interval after a densification are not
        considered: new Gaussians have not yet settled; nor those before
        :meth:`best_from_share` of the run."""
        c = self.cfg
        if self.last_densify >= 0 and self.step - self.last_densify < c.densify_every // 2:
            return
        if self.run_share() < self.best_from_share():
            return
        if self.best is None or score > self.best["score"]:
            self.best = {"score": score, "step": self.step, **self.snapshot()}

    def restore_best(self) -> Optional[int]:
        """``keep_best``: at the end of a run, go back to the best model unless the current one
        scores as well; returns (and records in ``best_step``) the step the model was taken
        at, or None when nothing changed."""
        if not self.cfg.keep_best or self.best is None or self.best["step"] == self.step:
            return None
        score_now = self.heldout_psnr() if self.best_by == "psnr_captured" else self.evaluate().get(self.best_by)
        if score_now is not None and score_now >= self.best["score"]:
            return None
        self.restore(self.best)
        self.best_step = self.best["step"]
        return self.best_step
