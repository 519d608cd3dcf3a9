"""The recurrent loop of RecGS (Zhang et al. 2024), with the remedies measured in benchmarks/RESULTS.md.

:class:`RecGS` drives a :class:`~..train.trainer.Trainer` in segments and fills its objective
with caustic-free targets:

* Warm-up: plain 3DGS on the captured images I for ``ccfg.warmup`` steps or
  ``ccfg.warmup_share`` of the training time, whichever comes first; without a time limit also
  until density control has stopped growing the model or held-out PSNR plateaus. With a time
  limit the plain model gets its whole share, counted from its first step: it is what the
  recurrences' C is measured against (an immature model's own error reads as caustics) and
  what the end-of-run choice compares with.
* Recurrences: render every training view and estimate each view's caustics ``C`` (each
  estimator's maps and targets: ``estimators.py``): by default
  the low-pass of the residual ``R = I - render`` (``fft_filter.py``, ``estimate.py``; less
  its mean per view and channel unless ``ccfg.caustic_dc``: caustics move light without adding
  any), or the targets from the passes that saw each point (``ccfg.estimator = "passes"``,
  ``passes.py``). Train ``ccfg.recurrence_steps`` steps against ``I - C``, and repeat
  until ``C`` stops changing (``mean |C_new - C_old| / mean |C_new| < ccfg.recurrence_tol``),
  or at ``ccfg.max_recurrences`` or the time/iteration limit. ``ccfg.caustic_model =
  "multiplicative"`` estimates a log-gain ``L = lowpass(log(I + e) - log(render + e))`` and
  fits ``(I + e) exp(-L) - e``; ``ccfg.caustic_k = 0`` picks the block size from the residual
  spectrum at the first recurrence (``fft_filter.choose_k``).
* Robust trimming (``ccfg.robust_k`` > 0, ``robust.py``): pixels much brighter than the
  render do not count in the loss, C is low-passed over the pixels that count, and at the end
  the colours are rescaled to the photos' mean light (``ccfg.gain_restore``).
* Do no harm: C is *dropped* and the model trains on as plain 3DGS on the captured images
  (stage ``settle``) when C is negligible (``mean |C| < ccfg.caustic_floor``) or does not
  settle (its change shrinks by less than ``ccfg.stall_ratio`` per round while ``mean |C|``
  grows by more than ``ccfg.stall_growth``: an estimate of a caustic field converges, one that
  follows model error keeps growing, which is what happens without caustics); these go on
  from the current model. When ``ccfg.recurrence_patience`` rounds in a row score more than
  ``ccfg.harm_tol`` dB below the plain model on the held-out views against the captured photos
  (``Trainer.heldout_psnr``), the plain model the recurrences started from comes back first.
  The run ends with the best model on the held-out photos (``TrainConfig.keep_best``), and
  the end-of-run choice (:func:`prefers_recgs`) between the caustic-free model and the plain
  one, which keeps a plain model that trained less only where it is clearly better.

The baselines ``filter2d`` and ``joint`` are in ``baselines.py``.

Held-out views are scored for the run's growth, SH and plateau decisions against the held-out
photo during the warm-up (plain 3DGS decides as plain 3DGS) and, once C is in use, against the
photo with its caustics compensated the same way (``I - lowpass(I - render)``), so moving
light does not read as model error; the do-no-harm test uses the photos as captured, since
compensation would hide the low-frequency drift it looks for. Scores against ground truth
come from ``TrainData.gt_view`` and are only reported. Settings: ``config.py``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Callable, Optional

import numpy as np
import torch

from ..io.looks import read_looks
from ..train.evaluation import PLATEAU
from ..train.losses import psnr
from ..train.trainer import Progress, Trainer
from . import fft_filter
from .config import CausticConfig
from . import estimators
from .estimate import estimate_caustics, remove_caustics
from .estimators import Estimates, choose_estimator
from .method import Method
from .robust import TrimmedTargets, apply_gain, colour_gain

#: Once C has settled, it is refreshed every this many rounds' steps (a time-limited run trains on)
REFRESH_EVERY = 5


def fair_competitor(plain: dict, recgs: dict) -> bool:
    """Whether the plain candidate trained about as much as the caustic-free one (scores of
    ``RecGS._scores`` with their ``steps`` and ``gaussians``): at least :data:`FAIR_SHARE` of its
    steps and of its Gaussians. A candidate without those counts (older summaries) is taken as fair."""
    if "steps" not in plain or "steps" not in recgs:
        return True
    return (plain["steps"] >= FAIR_SHARE * recgs["steps"]
            and plain.get("gaussians", 0) >= FAIR_SHARE * recgs.get("gaussians", 0))


def prefers_recgs(recgs: dict, plain: dict) -> tuple[bool, str]:
    """Whether the RecGS model beats the plain one on the held-out views (scores of
    ``RecGS._scores``), and why.

    The plain candidate is the warm-up's model: it trained a share of the steps the caustic-free
    one did. A model that trained less (:func:`fair_competitor`) is kept only where it is clearly
    better, by more than :data:`UNFAIR_HARM_DB`, against the held-out photos as captured (a
    score no estimate enters and that neither a blank nor an untrained render wins), or against
    the passes' references; never for a tie, nor on the relit score. An untrained one is never
    kept. Against a fair competitor: where the passes estimator made references for the held-out
    frames (caustic-free, gathered from the training frames alone), by PSNR against them, unless
    its relit score against the held-out photos (:func:`relit_psnr`, no estimate involved) falls
    more than :data:`RELIT_HARM_DB` below the plain model's; where the estimator scores the
    views by a likelihood of its own (``nll``: the benchmarks' gain likelihood), by that, with
    PSNR against the captured photos not falling more than :data:`HARM_DB`; otherwise by that
    PSNR, where a difference within :data:`TIE_DB` is a tie that goes to the caustic-free model.
    benchmarks/bench_caustics.py reports how often this agrees with ground truth."""
    if "psnr_captured" not in recgs or "psnr_captured" not in plain:
        return True, "no held-out views to judge by"
    dp = recgs["psnr_captured"] - plain["psnr_captured"]
    if plain.get("steps") == 0:
        return True, "the plain model had not trained"
    if not fair_competitor(plain, recgs):
        why = (f"the plain model trained {plain['steps']:,} steps to {plain.get('gaussians', 0):,} Gaussians against "
               f"{recgs['steps']:,} to {recgs.get('gaussians', 0):,}, so it is kept only where clearly better: "
               f"PSNR against the held-out photos {dp:+.2f} dB")
        if "psnr_reference" in recgs and "psnr_reference" in plain:
            dr = recgs["psnr_reference"] - plain["psnr_reference"]
            why += f", against the references from the passes {dr:+.2f} dB"
            if dr < -UNFAIR_HARM_DB:
                return False, why
        return dp >= -UNFAIR_HARM_DB, why
    if "psnr_reference" in recgs and "psnr_reference" in plain:
        dr = recgs["psnr_reference"] - plain["psnr_reference"]
        why = f"PSNR against the held-out frames' references from the passes {dr:+.2f} dB"
        key = f"psnr_relit{RELIT_CHECK_K}"
        if key in recgs and key in plain:   # the estimator does not grade itself alone
            dl = recgs[key] - plain[key]
            why += f", against the held-out photos relit {dl:+.2f} dB"
            if dl < -RELIT_HARM_DB:
                return False, why
        return dr > -TIE_DB, why
    if "nll" in recgs and "nll" in plain:
        dn = recgs["nll"] - plain["nll"]
        ok = dn < 0 and dp > -HARM_DB
        return ok, f"likelihood {recgs['nll']:.4f} against {plain['nll']:.4f}, PSNR {dp:+.2f} dB"
    return dp > -TIE_DB, f"PSNR against the held-out photos {dp:+.2f} dB"


#: The plain candidate is a fair competitor where it trained at least this share of the
#: caustic-free model's steps and holds at least this share of its Gaussians.
FAIR_SHARE = 0.5
#: How much better against the held-out photos as captured (or the passes' references) a plain
#: candidate that trained less must be to be kept: on footage without caustics that the light
#: finding took for caustics, the caustic-free model fell 6.3-6.7 dB below the photos
#: (benchmarks/RESULTS.md#end-of-run-check); under real caustics it led the shorter-trained plain
#: model there by 0.2-0.3 dB.
UNFAIR_HARM_DB = 1.0

#: Filter sizes of the relit score (:func:`relit_psnr`) the end-of-run candidates get.
RELIT_K = (9, 25)
#: The relit score that checks the passes' references at the end of a run, and how far below the
#: plain model's it may fall before the caustic-free model is refused whatever the references say:
#: the references come from the estimator, and on footage without caustics it graded itself up
#: (+2.5 and +3.7 dB against its references, -6.7 and -6.3 dB against the photos, on two real
#: clips). The relit score needs no estimate; on the caustic surveys where it was recorded it
#: agreed with ground truth or tied (benchmarks/RESULTS.md#end-of-run-check).
RELIT_CHECK_K = 25
RELIT_HARM_DB = 0.5
#: The most the relit score's light may brighten or darken a render (a factor). Unbounded, it lit
#: a black render up to the photo's own low frequencies; on the tests' survey (light of +-50 %)
#: a bound of 3 left the untrained sparse points 0.4 dB below the trained model relit at k = 9,
#: 2 kept them 3.7 dB below, and 1.5 clipped the survey's own light (the trained model's score
#: at k = 25 down by 2.4 dB).
RELIT_MAX_GAIN = 2.0


def relit_psnr(render: torch.Tensor, photo: torch.Tensor, k: int, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR against ``photo`` of ``render`` lit by the light that differs between them at the
    ``k x k`` lowest frequencies (their log ratio, low-passed, its mean kept, bounded by
    :data:`RELIT_MAX_GAIN`): a score of the seabed's texture that no light over the photo
    (caustics' broad part, exposure, a lamp's cone) moves, and that needs no caustic estimate.
    The render is relit, not the photo: a photo darkened to a dark render would score the
    blank render's error at the blank render's scale, and a blank render win. ``mask`` (H, W)
    bool: the pixels that count (the light is taken over them alone)."""
    render = render.clamp(0, 1)
    light = estimate_caustics(photo, render, k, "multiplicative", dc=True,
                              weight=None if mask is None else mask.to(photo.dtype))
    bound = math.log(RELIT_MAX_GAIN)
    return psnr(remove_caustics(render, -light.clamp(-bound, bound), "multiplicative").clamp(0, 1), photo, mask)


#: The share of a time limit the warm-up (plain 3DGS) takes at most, by estimator. The low-pass
#: estimate measures C against the model, which must be mature first (a shorter warm-up read the
#: model's own error as caustics, benchmarks/RESULTS.md); the passes' targets do not depend on
#: the model, so their warm-up only makes the plain model the end-of-run choice compares with
#: and the depth the plane sweep tries beside the points', and the caustic-free targets get the
#: rest (0.2 scored 0.5 dB above 0.5 on a dive survey; 0.1 against 0.2, five minutes: +0.19,
#: +0.10, +0.03 dB on three caustic surveys, the same on the README's two-minute job; the plain
#: fallback 0.7-1.9 dB weaker against the ground truth, benchmarks/RESULTS.md#water-caustics-steps).
WARMUP_SHARE = {"passes": 0.1}
#: The warm-up trains at least this many steps (or ``ccfg.warmup``, where fewer) whatever its
#: share of the time: the plain model the end-of-run choice weighs is never the untrained points.
WARMUP_MIN_STEPS = 100

#: The share of a time limit the caustic work (the pass estimator) may take, so that training
#: keeps the rest: beyond it by the plan's estimate the work is done on smaller frames
#: (:data:`PASS_SCALES`), or not at all; beyond it by the clock while it runs, it is given up.
#: Either way the run then trains as plain 3DGS.
CAUSTIC_TIME_SHARE = 0.5
#: The frames the pass estimator may work on to fit that share: the training size divided by
#: each of these in turn.
PASS_SCALES = (1, 2, 4)

#: How far the caustic-free model may fall below the plain one in PSNR against the held-out
#: photos as captured and still be kept when the likelihood prefers it: a held-out photo's own
#: caustics are no model's, and a model of the mean light meets them differently than one of
#: their median.
HARM_DB = 0.3
#: A difference of PSNR against the held-out photos as captured within this is a tie, kept by
#: the caustic-free model: those photos carry their own caustics, which the plain model shows
#: in part (it took in the light its views agreed on) and the caustic-free model does not, so a
#: tie there is a lead against the seabed itself. Decisions measured against ground truth:
#: benchmarks/RESULTS.md#caustics-dive-surveys.
TIE_DB = 0.1


class RecGS(Estimates, Method):
    def __init__(self, trainer: Trainer, ccfg: CausticConfig):
        #: why the estimator is what it is (``auto``: chosen from the survey's views per point)
        self.estimator_why = "set by the user"
        if ccfg.estimator == "auto":
            chosen, self.estimator_why = choose_estimator(trainer.data)
            ccfg = dataclasses.replace(ccfg, estimator=chosen)
        super().__init__(trainer, ccfg)
        self.k: Optional[int] = ccfg.caustic_k or None
        self.targets = TrimmedTargets(ccfg.robust_k, reference=self._reference)
        trainer.set_objective(self.targets)
        self.gain: Optional[list] = None    # the colour gain applied at the end (gain_restore)
        self.maps: dict[int, torch.Tensor] = {}  # C or log-gain per training view (full res)
        self.recurrence = 0
        self.rec_history: list[dict] = []
        self.next_due: Optional[int] = None
        self.stage = "warmup"
        #: the run's clock (``schedule_elapsed``) at the warm-up's first step, and the seconds
        #: the caustic work is planned to take (``plan.py`` sets it; the warm-up's share leaves it out)
        self.warmup_start: Optional[float] = None
        self.planned_seconds = 0.0
        #: seconds the pass estimator may run before it is given up (``fit_work``; None: no limit),
        #: and the frames' size it works at (the training size divided by this)
        self.pass_deadline: Optional[float] = None
        self.pass_scale = 1
        self._max_looks: Optional[int] = None   # see max_looks
        #: the plain model the recurrences start from (``score``: held-out PSNR against the
        #: captured images; ``params``, ``sh_degree``), and rounds in a row that scored worse
        self.plain: Optional[dict] = None
        self.misses = 0
        self.drop_reason: Optional[str] = None  # why C was dropped (see _drop), if it was
        #: at the end: how the RecGS model, the plain model and the kept best score (``_scores``)
        self.candidates: Optional[dict] = None
        #: the step at which C first settled (``recurrence_tol``), if it did
        self.converged_at: Optional[int] = None
        #: passes: the passes' part of every training view's target (``_make_pass_estimates``)
        #: and what it drew on
        self.geometry: Optional[dict] = None
        self.pass_info: Optional[dict] = None
        #: the run has ended: a view's caustic-free photo is made against the model kept
        self.final = False
        #: passes: each held-out frame's caustic-free reference, gathered from the training
        #: frames (what held-out renders are scored against once C is in use, and what the
        #: end-of-run choice judges by)
        self.references: Optional[dict[int, torch.Tensor]] = None
        #: what light the survey shows (``light.py``; ``LightFinding.summary()``), looked at
        #: before anything is removed
        self.light: Optional[dict] = trainer.light if ccfg.caustics == "auto" else None
        if self.light is not None and not self.light["caustics"]:
            self._drop(f"{self.light['reason']}: trained as plain 3DGS", restore=False)

    @property
    def stage(self) -> str:
        return self._stage

    @stage.setter
    def stage(self, value: str) -> None:
        self._stage = value
        self.trainer.label = value

    # --- the recurrence --------------------------------------------------------------------
    @torch.no_grad()
    def recur(self) -> dict:
        """One re-estimation of C for every training view; updates the targets."""
        tr = self.trainer
        ids = self._round_views()
        new = self._estimates(ids)
        if not new and self._passes and (self.geometry or {}).get("overrun"):   # given up: no C this round
            self.recurrence += 1
            entry = {"recurrence": self.recurrence, "iteration": tr.step, "elapsed": round(tr.elapsed, 2),
                     "c_change": 0.0, "mean_abs_c": 0.0, "k": self.k, "overrun": self.geometry["overrun"]}
            self.rec_history.append(entry)
            return entry
        change = self._change(ids, new)
        self._set_maps(new)
        self.recurrence += 1
        photos = {i: self.data.view(i, 1)[1] for i in ids}
        level = fft_filter.mean_abs([photos[i] - self._decaustic(photos[i], self.maps[i].float()) for i in ids])
        entry = {"recurrence": self.recurrence, "iteration": tr.step, "elapsed": round(tr.elapsed, 2),
                 "c_change": change, "mean_abs_c": level, "k": self.k}
        if self._passes:
            entry["light_std"] = self.geometry["light"]["light_std"]
        self.rec_history.append(entry)
        return entry

    def _round_views(self) -> list[int]:
        """The training views a round estimates C of (all of them)."""
        return self.data.train_ids

    def _change(self, ids: list[int], new: dict[int, torch.Tensor]) -> float:
        """How much a round's maps ``new`` moved from the last (relative mean absolute change)."""
        old = [self.maps[i].float() if i in self.maps else torch.zeros_like(new[i]) for i in ids]
        return fft_filter.caustic_change([new[i] for i in ids], old)

    def _due(self) -> bool:
        """Work is due before the next step: the warm-up is over, or a recurrence is due."""
        c, tr = self.ccfg, self.trainer
        if self.stage == "warmup":
            if self._time_limited():   # the plain model the recurrences start from uses its share
                return tr.step >= c.warmup or self._warmup_time_up()
            return tr.step >= c.warmup or self._warmup_time_up() or self._growth_over()
        return self.stage == "recurrence" and self.next_due is not None and tr.step >= self.next_due

    def _schedule(self) -> Optional[str]:
        """Do the work ``_due`` found; returns why the run ends, if it does."""
        c = self.ccfg
        if self.stage == "warmup":
            self._start_recurrences()
        if self.recurrence and self._judge_round():
            return None
        entry = self.recur()
        prev = self.rec_history[-2] if len(self.rec_history) >= 2 else None
        done = None
        if self._passes and (self.geometry or {}).get("overrun"):
            self._drop(self.geometry["overrun"], restore=False)
        elif entry.get("light_std") is not None and entry["light_std"] < estimators.LIGHT_FLOOR:
            self._drop(f"no moving light between the frames (its standard deviation {entry['light_std']:.3f} "
                       f"log units, below {estimators.LIGHT_FLOOR})", restore=False)
        elif entry["mean_abs_c"] < c.caustic_floor:
            self._drop(f"no caustics to remove (mean |C| {entry['mean_abs_c']:.4f})", restore=False)
        elif entry["c_change"] < c.recurrence_tol:
            if self.converged_at is None:
                self.converged_at = self.trainer.step
            if not self._time_limited():
                done = f"caustic estimate converged (change {entry['c_change']:.3f})"
        elif prev is not None and self._stalled(entry):
            # a caustic field's estimate settles geometrically; one that keeps changing and
            # growing follows model error (surveys without caustics)
            self._drop(f"caustic estimate is not settling (change {prev['c_change']:.3f} -> "
                       f"{entry['c_change']:.3f}, mean |C| {prev['mean_abs_c']:.4f} -> {entry['mean_abs_c']:.4f})",
                       restore=False)
        elif self.recurrence >= c.max_recurrences and not self._time_limited():
            done = "recurrence limit"
        if self.stage == "recurrence":
            # once C has settled, a run with time left trains on against it and refreshes it now and then
            every = c.recurrence_steps * (REFRESH_EVERY if self.converged_at is not None else 1)
            last = self.recurrence >= c.max_recurrences
            self.next_due = None if done or last else self.trainer.step + every
        return done

    def _time_limited(self) -> bool:
        """The run was given a time limit: it uses all of it (a converged estimate keeps the
        model improving on the caustic-free targets; the kept model is chosen at the end)."""
        return self.trainer.time_limit_s is not None

    def _stalled(self, entry: dict) -> bool:
        """The last round's C changed by more than ``stall_ratio`` of the round before (and more
        than twice the tolerance) while ``mean |C|`` grew by more than ``stall_growth``."""
        c, prev = self.ccfg, self.rec_history[-2]
        return (entry["c_change"] > max(c.stall_ratio * prev["c_change"], 2 * c.recurrence_tol)
                and entry["mean_abs_c"] > (1 + c.stall_growth) * prev["mean_abs_c"])

    def _growth_over(self) -> bool:
        """Density control has stopped adding Gaussians (frozen, at its budget, or past its
        last step): from here the model's low frequencies change little, so C can hold
        caustics rather than the model's own growing pains."""
        tr = self.trainer
        return tr.step > tr.cfg.densify_from and tr.growth_over()

    def _warmup_time_up(self) -> bool:
        """With a time limit, the warm-up gets at most ``warmup_share`` (by default the
        estimator's :data:`WARMUP_SHARE`) of the time training has: counted from its first step,
        of what the limit leaves once the work before it (reading, the light finding, the
        water's fit, a compiler's start-up), the caustic work the plan expects
        (``planned_seconds``) and the finishing are taken off. Counted from the job's start,
        a cold numba cache and the work before training spent the whole share before the first
        step, and the plain model the run falls back to was the untrained sparse points. It
        trains at least :data:`WARMUP_MIN_STEPS` steps all the same."""
        c, tr = self.ccfg, self.trainer
        limit = tr.time_limit_s
        if limit is None:
            return False
        if self.warmup_start is None:
            self.warmup_start = tr.schedule_elapsed()
        if tr.step < min(c.warmup, WARMUP_MIN_STEPS):
            return False
        share = c.warmup_share if c.warmup_share is not None else WARMUP_SHARE.get(c.estimator, 0.5)
        training = limit - self.warmup_start - self.planned_seconds - tr.finishing_reserve()
        return tr.schedule_elapsed() - self.warmup_start >= share * max(0.0, training)

    # --- do no harm: the held-out check of the recurrences ------------------------------------
    def _harm(self, score: Optional[float], plain: Optional[float]) -> Optional[str]:
        """Why ``score`` counts as hurting held-out views (more than ``harm_tol`` dB below the
        plain model's ``plain``), or None."""
        if score is None or plain is None:
            return None
        if score >= plain - self.ccfg.harm_tol:
            return None
        return f"caustic estimate hurt held-out views ({score:.2f} dB against {plain:.2f} dB)"

    @torch.no_grad()
    def _reference_psnr(self, snap: Optional[dict] = None) -> float:
        """Mean PSNR of the held-out renders (of ``snap``'s model, default the trainer's) against
        the passes' references."""
        tr = self.trainer
        ids = [i for i in tr.heldout_ids() if i in self.references]
        with tr.using(snap) if snap is not None else contextlib.nullcontext():
            return float(np.mean([psnr(tr.render_view(i).clamp(0, 1), self.references[i].float(), tr.counts(i))
                                  for i in ids]))

    def _snapshot(self, score: Optional[float]) -> None:
        """Remember the plain model (before any C) and its held-out score: the model now, or the
        best the warm-up kept (``keep_best``) where that scored higher."""
        tr = self.trainer
        best = tr.best
        if best is not None and score is not None and best["score"] > score:
            self.plain = {"score": best["score"], "step": best["step"], "params": best["params"],
                          "sh_degree": best["sh_degree"]}
        else:
            self.plain = {"score": score, "step": tr.step, **tr.snapshot()}
        self.misses = 0

    def _judge_round(self) -> bool:
        """Score the model trained against the last estimate of C on the held-out views. If
        ``recurrence_patience`` rounds in a row score more than ``harm_tol`` dB below the plain
        model the recurrences started from, C is taking real scene content (on a survey without
        caustics it only absorbs model error): go back to the plain model, drop C, and let it
        train on as plain 3DGS until the held-out plateau or a limit. Returns whether the
        recurrences are over. With the passes' references both are scored against them: the
        held-out photos' own caustics would count the caustic-free model's gain as harm."""
        if self.references is not None and self.plain is not None:
            if "reference_score" not in self.plain:
                self.plain["reference_score"] = self._reference_psnr(self.plain)
            score, plain = self._reference_psnr(), self.plain["reference_score"]
            against = "references"
        else:
            score, plain = self.trainer.heldout_psnr(), (self.plain or {}).get("score")
            against = "captured"
        self.rec_history[-1].update(psnr_heldout=score, heldout_vs=against)
        harm = self._harm(score, plain)
        self.misses = self.misses + 1 if harm else 0
        if not harm or self.misses < self.ccfg.recurrence_patience:
            return False
        self._drop(harm)
        return True

    def _drop(self, why: str, restore: bool = True) -> None:
        """End the recurrences without C: the model trains on as plain 3DGS on the captured
        images (stage ``settle``) until the held-out plateau or a limit. ``restore``: start from
        the plain model the recurrences started from (when C hurt held-out views); otherwise go
        on from the current model and its Adam state, so no steps are thrown away."""
        if restore:
            self.trainer.restore(self.plain)
        self._forget_light()
        if self.trainer.objective is not self.targets:
            self.trainer.set_objective(self.targets)
        self._set_maps({})  # targets = the captured images
        self.references = None   # held-out views are scored against their photos again
        self.trainer.best_by, self.trainer.best = "psnr_captured", None
        self.misses = 0
        self.drop_reason = why
        self._plain_loss()
        self.stage, self.next_due = "settle", None
        self.trainer.restart_plateau(forget_best=True)

    def _forget_light(self) -> None:
        """What an estimator learnt of the survey's light besides the maps, forgotten where C is
        dropped (none here)."""

    def _plain_loss(self) -> None:
        """Without C, no trimming and no L2 either: the run ends as plain 3DGS."""
        self.targets.k = 0.0
        self.targets.loss_kind = "l1"

    @property
    def dropped(self) -> bool:
        return self.drop_reason is not None

    def _start_recurrences(self) -> None:
        self.stage = "recurrence"
        self.targets.loss_kind = self.ccfg.fit_loss
        self.next_due = self.trainer.step
        self.trainer.restart_plateau()
        self._snapshot(self.trainer.heldout_psnr())  # the plain model is the one not to fall below
        self.trainer.best = None   # from here the best model of the recurrences (``_decide``)

    # --- the loop --------------------------------------------------------------------------
    def run(self, on_progress: Optional[Callable[[Progress], None]] = None,
            should_stop: Optional[Callable[[], bool]] = None,
            on_checkpoint: Optional[Callable[[Trainer], None]] = None, checkpoint_every_s: float = 60.0) -> str:
        tr = self.trainer
        progress = None if on_progress is None else (lambda p: on_progress(self._annotate(p)))
        while True:
            reason = tr.train_until(self._due, progress, should_stop, on_checkpoint, checkpoint_every_s)
            if reason == "stopped":
                return reason
            if reason == "until":
                reason = self._schedule()
                if reason is None:
                    continue
                tr.done_reason = reason
            elif reason == PLATEAU and self.stage in ("warmup", "recurrence"):
                # after the warm-up's plateau come the recurrences; during them the convergence
                # test decides, not the plateau
                if self.stage == "warmup":
                    self._start_recurrences()
                tr.done_reason = None
                continue
            break
        if self.stage == "recurrence" and self.plain is not None:
            self._decide()
        else:
            tr.restore_best()
        if self.ccfg.robust_k and self.ccfg.gain_restore:
            self.restore_gain()
        tr.finish(progress)
        return reason

    def _decide(self) -> None:
        """Never worse than plain: at the end of the recurrences, keep the RecGS model only where
        the held-out photos, as captured, show it better than the plain model the recurrences
        started from (:meth:`prefers_recgs`); otherwise the plain model comes back. Both
        candidates' scores, and the choice, go into the run's summary."""
        tr = self.trainer
        if tr.restore_best() is None:
            tr.best_step = None
        recgs_step = tr.step if tr.best_step is None else tr.best_step
        self.candidates = {"recgs": self._scores(tr.snapshot(), recgs_step),
                           "plain": self._scores(self.plain, self.plain.get("step", 0))}
        keep, why = prefers_recgs(self.candidates["recgs"], self.candidates["plain"])
        self.candidates["kept"], self.candidates["why"] = ("recgs" if keep else "plain"), why
        if not keep:
            tr.restore(self.plain)
            tr.best_step = self.plain.get("step")
            self.drop_reason = f"the held-out views do not show the caustic-free model better ({why})"
        # the exported caustic-free photos and maps come from the model kept: view by view as
        # they are written (one render each), or all at once for the estimators that need that
        self.final = True
        if self.maps and not self._by_view:
            self._set_maps(self._estimates(self.data.train_ids))

    @torch.no_grad()
    def _scores(self, snap: dict, steps: int) -> dict:
        """How a model (a ``snapshot()``, trained ``steps`` steps) does on the held-out views:
        its steps and Gaussians, PSNR against the photos as captured, against the references the
        passes made (where they did), the estimator's own scores (``_view_scores``) and PSNR against ground truth (where
        the survey has it, reported only)."""
        tr = self.trainer
        ids = tr.heldout_ids()
        out: dict = {"steps": int(steps), "gaussians": int(snap["params"]["means"].shape[0])}
        if not ids:
            return out
        with tr.using(snap):
            cap, ref, gt, relit, own = [], [], [], {k: [] for k in RELIT_K}, {}
            for i in ids:
                rgb, true = tr.render_pair(i)
                photo = self.data.view(i, 1)[1]
                keep = tr.counts(i)
                cap.append(psnr(rgb, photo, keep))
                for k in RELIT_K:
                    relit[k].append(relit_psnr(rgb, photo, k, keep))
                if self.references is not None and i in self.references:
                    ref.append(psnr(rgb, self.references[i].float(), keep))
                for key, v in self._view_scores(rgb, photo).items():
                    own.setdefault(key, []).append(v)
                g = self.data.gt_view(i)
                if g is not None:
                    gt.append(psnr(true, g, keep))
        out["psnr_captured"] = round(sum(cap) / len(cap), 4)
        for k, v in relit.items():
            out[f"psnr_relit{k}"] = round(sum(v) / len(v), 4)
        if ref:
            out["psnr_reference"] = round(sum(ref) / len(ref), 4)
        for key, v in own.items():
            out[key] = round(sum(v) / len(v), 5)
        if gt:
            out["psnr_gt"] = round(sum(gt) / len(gt), 4)
        return out

    def _view_scores(self, render: torch.Tensor, photo: torch.Tensor) -> dict[str, float]:
        """An estimator's own scores of a held-out render against its photo (none here)."""
        return {}

    @torch.no_grad()
    def restore_gain(self) -> list:
        """Scale the model's colours so its renders of the training views hold the photos'
        mean light (trimming fits a darker model); returns the per-channel gain."""
        tr = self.trainer
        g = colour_gain((self.data.view(i, 1)[1], tr.render_view(i)) for i in self.data.train_ids)
        apply_gain(tr.params, g)
        self.gain = [round(float(x), 4) for x in g]
        return self.gain

    def _annotate(self, p: Progress) -> Progress:
        if self.rec_history:
            p.extra.update(recurrence=self.recurrence, c_change=self.rec_history[-1]["c_change"])
        return p

    def finishing_renders(self) -> int:
        """The end-of-run choice scores both candidates (and the best of the recurrences) on
        the held-out views; the caustic-free photos render every training view once more but
        those whose estimate does not follow the model (``_model_free``). Nothing once C is
        dropped: the run ends as plain 3DGS."""
        if self.dropped:
            return 0
        return 3 * len(self.data.test_ids) + sum(not self._model_free(i) for i in self.data.train_ids)

    def planned_work(self, scale: Optional[int] = None, looks: Optional[int] = None):
        """The pass estimator's expected cost (``cost.py``), where it will run: every training
        and held-out frame at 1 / ``scale`` of the training size (default: the run's
        ``pass_scale``), and ``looks`` of the survey's look frames (default: those the run may
        use, ``max_looks``)."""
        if self.dropped or not self._passes:
            return None
        from .cost import pass_cost
        scale = self.pass_scale if scale is None else scale
        sizes = [self.data.camera(i, scale) for i in self.data.train_ids + self.data.test_ids]
        looks = self.max_looks if looks is None else looks
        return pass_cost([(c.width, c.height) for c in sizes], looks=looks, look_size=(sizes[0].width, sizes[0].height))

    @property
    def max_looks(self) -> int:
        """The look frames the pass estimator may gather from (the survey's, or as many as fit
        the caustic work's share of the time and memory, ``fit_work``)."""
        if self._max_looks is None:
            found = read_looks(self.data.scene.scene_dir) if self.ccfg.looks != "off" else None
            self._max_looks = len(found.looks) if found is not None else 0
        return self._max_looks

    def fit_work(self, time_limit_s, room_bytes) -> Optional[str]:
        """The caustic work keeps at most :data:`CAUSTIC_TIME_SHARE` of a time limit and fits the
        memory the plan leaves: at the training resolution where it can, else on frames of half or
        a quarter of it (:data:`PASS_SCALES`; the targets are brought back to full size by the
        light they take off, ``Estimates._lift``). Where none fits the run trains as plain 3DGS
        and says why."""
        if self.planned_work() is None:
            return None
        why = None
        listed = self.max_looks
        for scale in PASS_SCALES:
            work = self.planned_work(scale, looks=0)
            if listed:   # the look frames that fit beside the keyframes' work
                one = self.planned_work(scale, looks=1)
                dt, db = one.seconds - work.seconds, one.bytes - work.bytes
                fits = listed
                if time_limit_s is not None and dt > 0:
                    fits = min(fits, int((CAUSTIC_TIME_SHARE * time_limit_s - work.seconds) / dt))
                if room_bytes is not None and db > 0:
                    fits = min(fits, int((room_bytes - work.bytes) / db))
                work = self.planned_work(scale, looks=max(0, fits))
            if time_limit_s is not None and work.seconds > CAUSTIC_TIME_SHARE * time_limit_s:
                why = (f"the caustic work would take about {work.seconds:.0f} s here ({work.megapixels:.1f} megapixels "
                       f"of frames), more than {100 * CAUSTIC_TIME_SHARE:.0f} % of the {time_limit_s:.0f}-s limit")
            elif room_bytes is not None and work.bytes > room_bytes:
                why = (f"the caustic work would need about {work.bytes / 2 ** 30:.1f} GB of memory here "
                       f"({work.megapixels:.1f} megapixels of frames), more than the "
                       f"{max(0, room_bytes) / 2 ** 30:.1f} GB left beside training")
            else:
                self.pass_scale, self.planned_seconds, self._max_looks = scale, work.seconds, work.looks
                self.pass_deadline = None if time_limit_s is None else CAUSTIC_TIME_SHARE * time_limit_s
                return None
        self._drop(f"{why}, even on frames of 1/{PASS_SCALES[-1]} the size: trained as plain 3DGS (a longer limit, "
                   "a lower resolution or fewer photos would fit it)", restore=False)
        return why

    def state_bytes(self) -> int:
        """The maps and the targets, float16 (H, W, 3) each, of every training view."""
        return (6 + self.targets.bytes_per_pixel()) * self.data.training_pixels()

    def summary(self) -> dict:
        return {**super().summary(), "estimator": self.ccfg.estimator, "estimator_why": self.estimator_why,
                "candidates": self.candidates, "caustic_k": self.k, "recurrences": self.rec_history, "caustics_dropped": self.drop_reason,
                "psnr_heldout_plain": (self.plain or {}).get("score"), "colour_gain": self.gain,
                "passes": self.pass_info, "light": self.light}

    # --- checkpoints -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        s = super().state_dict()
        s["caustic"] = {
            "k": self.k, "maps": {int(i): m.cpu() for i, m in self.maps.items()}, "recurrence": self.recurrence,
            "rec_history": self.rec_history, "next_due": self.next_due, "stage": self.stage,
            "plain": None if self.plain is None else {
                **self.plain, "params": {n: v.cpu() for n, v in self.plain["params"].items()}},
            "misses": self.misses, "drop_reason": self.drop_reason,
            "converged_at": self.converged_at, "warmup_start": self.warmup_start,
        }
        return s

    def load_state_dict(self, s: dict) -> None:
        super().load_state_dict(s)
        cs = s["caustic"]
        self.k, self.recurrence, self.stage = cs["k"], cs["recurrence"], cs["stage"]
        self.rec_history, self.next_due = list(cs["rec_history"]), cs["next_due"]
        self.plain = cs.get("plain")
        # checkpoints written before the do-no-harm tests have none of these
        self.misses, self.drop_reason = cs.get("misses", 0), cs.get("drop_reason")
        self.converged_at = cs.get("converged_at")
        self.warmup_start = cs.get("warmup_start")
        if self.stage != "warmup":
            self.targets.loss_kind = self.ccfg.fit_loss
        if self.dropped:
            self._plain_loss()
        self._set_maps({int(i): m.to(self.trainer.device) for i, m in cs["maps"].items()})
