"""Caustic removal: the recurrent loop of RecGS (Zhang et al. 2024) and its baselines.

``CausticTrainer`` is the :class:`~.train.Trainer` with caustic-free targets, by ``cfg.mode``:

* ``recgs``: train plain 3DGS on the captured images I (warm-up: until density control has
  stopped growing the model, held-out PSNR plateaus, ``cfg.warmup`` steps, or
  ``cfg.warmup_share`` of the time limit, whichever comes first), then recur:
  render every training view, low-pass the residual ``R = I - render`` (core/caustics.py)
  into the caustic estimate ``C`` (less its mean per view and channel unless
  ``cfg.caustic_dc``: caustics move light without adding any, and a DC term would carry the
  warm-up model's brightness error, see docs/caustics.md), train ``cfg.recurrence_steps``
  steps against ``I - C``, and repeat until ``C`` stops changing (``mean |C_new - C_old| / mean |C_new| <
  cfg.recurrence_tol``), or at ``cfg.max_recurrences`` or the time/iteration limit.
  ``cfg.caustic_model = "multiplicative"`` estimates a log-gain
  ``L = lowpass(log(I + e) - log(render + e))`` and fits ``(I + e) exp(-L) - e`` instead,
  since caustics modulate the light; ``cfg.caustic_k = 0`` picks the block size from the
  residual spectrum at the first recurrence (``caustics.choose_k``).

  Do no harm: C is *dropped* and the model trains on as plain 3DGS on the captured images
  (stage ``settle``) when C is negligible (``mean |C| < cfg.caustic_floor``) or does not
  settle (its change shrinks by less than ``cfg.stall_ratio`` per round while ``mean |C|``
  grows by more than ``cfg.stall_growth``: an estimate of a caustic field converges, one that
  follows model error keeps growing, which is what happens without caustics); these go on
  from the current model. When ``cfg.recurrence_patience`` rounds in a row score more than
  ``cfg.harm_tol`` dB below the plain model on the held-out views against the captured photos
  (``heldout_score``), the plain model the recurrences started from comes back first.
* ``filter2d``: fit ``I - lowpass(I - mean I)`` per image from the start (no 3D reasoning).
* ``joint``: learn a per-image ``k x k`` Fourier field with the Gaussians, fitting
  ``render + field_i`` to ``I`` (the alternative the paper reports as failing: the fields and
  the Gaussians trade the low frequencies of the scene between them).

Held-out views are scored for the run's growth, SH and plateau decisions against the held-out
image with its caustics compensated the same way (``I - lowpass(I - render)``), so moving
light does not read as model error; the do-no-harm test uses the photos as captured, since
compensation would hide the low-frequency drift it looks for. Scores against ground truth
come from ``TrainData.gt_view`` and are only reported.
"""
from __future__ import annotations

from typing import Optional

import torch

from . import caustics, density
from .losses import psnr
from .train import Trainer

#: Offset (in [0, 1] intensity) inside the logarithms of the multiplicative model.
LOG_EPS = 0.02
PLATEAU = "held-out PSNR plateau"


class CausticTrainer(Trainer):
    def __init__(self, data, cfg, gaussians=None):
        super().__init__(data, cfg, gaussians)
        self.k: Optional[int] = cfg.caustic_k or None
        self.eval_k = cfg.caustic_k or caustics.DEFAULT_K
        self.maps: dict[int, torch.Tensor] = {}  # recgs: C or log-gain per training view (full res)
        self.recurrence = 0
        self.rec_history: list[dict] = []
        self.next_due: Optional[int] = None
        self.stage = "warmup" if cfg.mode == "recgs" else cfg.mode
        #: recgs: the plain model the recurrences start from (``score``: held-out PSNR against
        #: the captured images; ``params``, ``sh_degree``), and rounds in a row that scored worse
        self.plain: Optional[dict] = None
        self.misses = 0
        self.drop_reason: Optional[str] = None  # why C was dropped (see _drop), if it was
        self.fields = None
        if cfg.mode == "filter2d":
            self._set_filter2d_targets()
        elif cfg.mode == "joint":
            self.fields = caustics.CausticFields(len(data.scene.cameras), self.eval_k).to(self.device)
            self.field_opt = torch.optim.Adam(self.fields.parameters(), lr=cfg.lr_sh_dc * 2, eps=1e-15)

    # --- targets ---------------------------------------------------------------------------
    def _set_filter2d_targets(self) -> None:
        if self.k is None:
            imgs = [self.data.view(i, 1)[1] for i in self.data.train_ids]
            self.k = caustics.choose_k([m - m.mean(dim=(0, 1), keepdim=True) for m in imgs])
        for i in self.data.train_ids:
            self.data.targets[i] = caustics.filter2d(self.data.view(i, 1)[1], self.k)

    def _decaustic(self, image: torch.Tensor, cmap: torch.Tensor) -> torch.Tensor:
        if self.cfg.caustic_model == "multiplicative":
            return (image + LOG_EPS) * torch.exp(-cmap) - LOG_EPS
        return image - cmap

    def _estimate(self, image: torch.Tensor, rgb: torch.Tensor, k: int) -> torch.Tensor:
        if self.cfg.caustic_model == "multiplicative":
            resid = torch.log(image + LOG_EPS) - torch.log(rgb.clamp_min(0) + LOG_EPS)
        else:
            resid = image - rgb
        est = caustics.lowpass(resid, k)
        if not self.cfg.caustic_dc:
            est = est - est.mean(dim=(0, 1), keepdim=True)
        return est

    def caustic_map(self, index: int) -> torch.Tensor:
        """Additive caustic estimate ``C = I - (caustic-free I)`` of a training view (full res)."""
        image = self.data.view(index, 1)[1]
        return image - self.decaustic_image(index)

    @torch.no_grad()
    def decaustic_image(self, index: int) -> torch.Tensor:
        """Caustic-free estimate of a training view's image (not clipped)."""
        image = self.data.view(index, 1)[1]
        if self.fields is not None:
            return image - self.fields.field(index, image.shape[0], image.shape[1])
        if self.cfg.mode == "filter2d":
            return self.data.targets[index]
        cmap = self.maps.get(index)
        return image if cmap is None else self._decaustic(image, cmap)

    # --- the recurrence --------------------------------------------------------------------
    @torch.no_grad()
    def recur(self) -> dict:
        """One re-estimation of C for every training view; updates the targets."""
        ids = self.data.train_ids
        renders = {i: self.render_view(i) for i in ids}
        if self.k is None:
            self.k = caustics.choose_k([self.data.view(i, 1)[1] - renders[i] for i in ids])
        new = {i: self._estimate(self.data.view(i, 1)[1], renders[i], self.k) for i in ids}
        old = [self.maps.get(i, torch.zeros_like(new[i])) for i in ids]
        change = caustics.caustic_change([new[i] for i in ids], old)
        self.maps = new
        for i in ids:
            self.data.targets[i] = self._decaustic(self.data.view(i, 1)[1], new[i])
        self.recurrence += 1
        level = caustics.mean_abs([self.caustic_map(i) for i in ids])
        entry = {"recurrence": self.recurrence, "iteration": self.step, "elapsed": round(self.elapsed, 2),
                 "c_change": change, "mean_abs_c": level, "k": self.k}
        self.rec_history.append(entry)
        return entry

    def _schedule(self) -> None:
        c = self.cfg
        if self.stage == "warmup" and (self.step >= c.warmup or self._warmup_time_up() or self._growth_over()):
            self._start_recurrences()
        if self.stage != "recurrence" or self.next_due is None or self.step < self.next_due:
            return
        if self.recurrence and self._judge_round():
            return
        entry = self.recur()
        prev = self.rec_history[-2] if len(self.rec_history) >= 2 else None
        if entry["mean_abs_c"] < c.caustic_floor:
            self._drop(f"no caustics to remove (mean |C| {entry['mean_abs_c']:.4f})", restore=False)
        elif entry["c_change"] < c.recurrence_tol:
            self.done_reason = f"caustic estimate converged (change {entry['c_change']:.3f})"
        elif prev is not None and self._stalled(entry):
            # a caustic field's estimate settles geometrically; one that keeps changing and
            # growing follows model error (surveys without caustics)
            self._drop(f"caustic estimate is not settling (change {prev['c_change']:.3f} -> "
                       f"{entry['c_change']:.3f}, mean |C| {prev['mean_abs_c']:.4f} -> {entry['mean_abs_c']:.4f})",
                       restore=False)
        elif self.recurrence >= c.max_recurrences:
            self.done_reason = "recurrence limit"
        if self.stage == "recurrence":
            self.next_due = None if self.done_reason else self.step + c.recurrence_steps

    def _stalled(self, entry: dict) -> bool:
        """The last round's C changed by more than ``stall_ratio`` of the round before (and more
        than twice the tolerance) while ``mean |C|`` grew by more than ``stall_growth``."""
        c, prev = self.cfg, self.rec_history[-2]
        return (entry["c_change"] > max(c.stall_ratio * prev["c_change"], 2 * c.recurrence_tol)
                and entry["mean_abs_c"] > (1 + c.stall_growth) * prev["mean_abs_c"])

    def _growth_over(self) -> bool:
        """Density control has stopped adding Gaussians (frozen, at its budget, or past its
        last step): from here the model's low frequencies change little, so C can hold
        caustics rather than the model's own growing pains."""
        n = int(self.params["means"].shape[0])
        return self.step > self.cfg.densify_from and (not self._densifying() or (self.budget is not None and n >= self.budget))

    def _warmup_time_up(self) -> bool:
        """With a time limit, the warm-up gets at most ``warmup_share`` of it."""
        c = self.cfg
        return c.max_minutes is not None and self.elapsed >= c.warmup_share * 60 * c.max_minutes

    # --- do no harm: the held-out check of the recurrences ------------------------------------
    @torch.no_grad()
    def heldout_score(self) -> Optional[float]:
        """Mean PSNR of the held-out renders against the captured held-out images, caustics and
        all. A held-out view's caustics are its own, so no model predicts them: they add the same
        error to every model, and the model closer to the caustic-free scene scores higher
        (unlike the compensated score of ``evaluate``, this also sees low-frequency drift)."""
        ids = self.heldout_ids()
        if not ids:
            return None
        return float(sum(psnr(self.render_view(i).clamp(0, 1), self.data.view(i, 1)[1]) for i in ids) / len(ids))

    def _harm(self, score: Optional[float]) -> Optional[str]:
        """Why ``score`` counts as hurting held-out views (more than ``harm_tol`` dB below the
        plain model), or None."""
        if score is None or self.plain is None or self.plain["score"] is None:
            return None
        if score >= self.plain["score"] - self.cfg.harm_tol:
            return None
        return f"caustic estimate hurt held-out views ({score:.2f} dB against {self.plain['score']:.2f} dB)"

    def _snapshot(self, score: Optional[float]) -> None:
        """Remember the plain model (before any C) and its held-out score."""
        self.plain = {"score": score, "sh_degree": self.sh_degree,
                      "params": {n: v.detach().clone() for n, v in self.params.items()}}
        self.misses = 0

    def _judge_round(self) -> bool:
        """Score the model trained against the last estimate of C on the held-out views. If
        ``recurrence_patience`` rounds in a row score more than ``harm_tol`` dB below the plain
        model the recurrences started from, C is taking real scene content (on a survey without
        caustics it only absorbs model error): go back to the plain model, drop C, and let it
        train on as plain 3DGS until the held-out plateau or a limit. Returns whether the
        recurrences are over."""
        score = self.heldout_score()
        self.rec_history[-1]["psnr_heldout"] = score
        harm = self._harm(score)
        self.misses = self.misses + 1 if harm else 0
        if not harm or self.misses < self.cfg.recurrence_patience:
            return False
        self._drop(harm)
        return True

    def _drop(self, why: str, restore: bool = True) -> None:
        """End the recurrences without C: the model trains on as plain 3DGS on the captured
        images (stage ``settle``) until the held-out plateau or a limit. ``restore``: start from
        the plain model the recurrences started from (when C hurt held-out views); otherwise go
        on from the current model and its Adam state, so no steps are thrown away."""
        if restore:
            b = self.plain
            self.params = {n: torch.nn.Parameter(v.clone()) for n, v in b["params"].items()}
            self.optimizer = self._make_optimizer()
            self.stats = density.GradientStats.zeros(self.params["means"].shape[0])
            self.sh_degree = b["sh_degree"]
        self.maps = {}
        self.data.targets.clear()  # targets = the captured images
        self.misses = 0
        self.drop_reason = why
        self.stage, self.next_due = "settle", None
        self.best_psnr, self.since_best = -float("inf"), 0

    @property
    def dropped(self) -> bool:
        return self.drop_reason is not None

    def run(self, *args, **kwargs) -> str:
        reason = super().run(*args, **kwargs)
        if reason != "stopped" and self.stage == "recurrence":
            # the same test when a limit ends the run: a caustic estimate that hurts held-out
            # views is dropped, and the run ends with the plain model
            harm = self._harm(self.heldout_score())
            if harm:
                self._drop(harm)
        return reason

    def _start_recurrences(self) -> None:
        self.stage = "recurrence"
        self.next_due = self.step
        self.since_best = 0
        self._snapshot(self.heldout_score())  # the plain model is the one not to fall below

    def _continue_after(self, reason: str) -> bool:
        if self.cfg.mode != "recgs" or reason != PLATEAU:
            return False
        if self.stage == "settle":
            return False
        if self.stage == "warmup":
            self._start_recurrences()
        return True  # during recurrences the convergence test decides, not the plateau

    # --- hooks of the base trainer ---------------------------------------------------------
    def _prediction(self, rgb: torch.Tensor, index: int) -> torch.Tensor:
        if self.fields is None:
            return rgb
        return rgb + self.fields.field(index, rgb.shape[0], rgb.shape[1])

    def _after_step(self) -> None:
        if self.fields is not None:
            self.field_opt.step()
            self.field_opt.zero_grad(set_to_none=True)

    def _eval_reference(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        image = self.data.view(index, 1)[1]
        if self.cfg.mode == "filter2d":
            return caustics.filter2d(image, self.k or self.eval_k)
        return self._decaustic(image, self._estimate(image, rgb, self.eval_k))

    def _phase(self) -> str:
        if self.cfg.mode == "recgs":
            return self.stage
        return super()._phase()

    def _progress_extra(self) -> dict:
        if not self.rec_history:
            return {}
        last = self.rec_history[-1]
        return {"recurrence": self.recurrence, "c_change": last["c_change"]}

    # --- checkpoints -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        s = super().state_dict()
        s["caustic"] = {
            "k": self.k, "maps": {int(i): m.cpu() for i, m in self.maps.items()}, "recurrence": self.recurrence,
            "rec_history": self.rec_history, "next_due": self.next_due, "stage": self.stage,
            "fields": None if self.fields is None else self.fields.state_dict(),
            "field_opt": None if self.fields is None else self.field_opt.state_dict(),
            "plain": None if self.plain is None else {
                **self.plain, "params": {n: v.cpu() for n, v in self.plain["params"].items()}},
            "misses": self.misses, "drop_reason": self.drop_reason,
        }
        return s

    def load_state_dict(self, s: dict) -> None:
        super().load_state_dict(s)
        cs = s["caustic"]
        self.k, self.recurrence, self.stage = cs["k"], cs["recurrence"], cs["stage"]
        self.rec_history, self.next_due = list(cs["rec_history"]), cs["next_due"]
        self.maps = {int(i): m.to(self.device) for i, m in cs["maps"].items()}
        b = cs.get("plain")
        self.plain = None if b is None else {
            **b, "params": {n: v.to(self.device) for n, v in b["params"].items()}}
        # checkpoints written before the do-no-harm tests have none of these
        self.misses, self.drop_reason = cs.get("misses", 0), cs.get("drop_reason")
        for i, m in self.maps.items():
            self.data.targets[i] = self._decaustic(self.data.view(i, 1)[1], m)
        if self.cfg.mode == "filter2d":
            self._set_filter2d_targets()
        if self.fields is not None and cs["fields"] is not None:
            self.fields.load_state_dict(cs["fields"])
            self.field_opt.load_state_dict(cs["field_opt"])
