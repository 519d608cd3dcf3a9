"""The 3D Gaussian Splatting optimisation loop on the CPU (or any torch device), built to
model only what the scene needs.

:class:`Trainer` runs steps, density control (``density_control.py``, its operations in
``density.py``) and evaluation on held-out views (``evaluation.py``: keep-best and the stopping
rules), keeps the run's clock and reports progress (``progress.py``), and saves/restores its
whole state (parameters, Adam moments, gradient statistics, random generators) so that a
resumed run continues exactly where the checkpoint was taken.
What each step fits comes from its :class:`~.objective.Objective` (the photos, unless a
caustic method in core/caustics/ says otherwise). Settings: ``config.py``; the survey as
the trainer sees it: ``data.py``.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import RecGSError
from ..io.colmap import load_scene
from ..model.gaussians import GaussianSet, init_from_points, num_sh_coeffs
from ..render import numba_kernels
from ..render.rasterizer import render
from ..render.rowgrads import RowGrads
from . import density, numba_ssim
from .compiling import CompileSwitch
from .config import TrainConfig
from .coverage import sparse_coverage
from .data import TrainData, block_scene, resolve_image_dir, view_tensors
from .density_control import DensityMixin
from .evaluation import EvaluationMixin
from .lamp import LampMixin
from .losses import training_loss
from .objective import Objective
from .progress import Progress, ProgressMixin
from .water import MediumMixin


PARAM_NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh_dc", "sh_rest")


#: Consecutive steps with a non-finite loss after which a run stops (its last checkpoint,
#: written before the trouble, stays as it was).
MAX_BAD_STEPS = 10


class TrainingDiverged(RecGSError):
    """NaN or Inf in the loss, the parameters or the optimiser's moments."""


class Trainer(EvaluationMixin, DensityMixin, ProgressMixin, MediumMixin, LampMixin):
    """One training run. ``run()`` until done or told to stop; ``state_dict()`` to checkpoint.

    What it fits is its :class:`~.objective.Objective` (``set_objective``): the photos by
    default. A method that changes the objective as training goes (core/caustics/) drives the
    trainer in segments with ``train_until`` and sets ``label`` to name its phase."""

    def __init__(self, data: TrainData, cfg: TrainConfig, gaussians: Optional[GaussianSet] = None,
                 light: Optional[dict] = None):
        """``cfg`` as checked by :meth:`TrainConfig.validate` (:func:`make_trainer` checks it
        before reading the survey). ``light``: what the survey's light was found to be before
        training (core/caustics/light.py, ``LightFinding.summary()``), which starts the lamp."""
        self.data, self.cfg = data, cfg
        self.objective: Objective = Objective()
        self.objective_optimizer: Optional[torch.optim.Adam] = None
        #: the phase a driving method is in (progress and history show it); None: densify/refine
        self.label: Optional[str] = None
        self._last_checkpoint: Optional[float] = None
        self._last_loss = float("nan")
        self.device = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.np_rng = np.random.default_rng(cfg.seed)
        #: what the survey's light was found to be before training (or None)
        self.light = light
        self._init_lamp(light)   # light fixed to the camera, where the survey shows it (lamp.py)
        self._init_medium()   # the water, where the survey can tell it (water.py)
        self._point_obs = None   # the points' observations both fits shared: not kept
        if gaussians is None:   # from the points' true colours (the photos' where there is no water)
            gaussians = init_from_points(data.scene.points, self.true_point_colours(), sh_degree=0)
        if len(gaussians) == 0:
            raise RecGSError("no Gaussians to train (the model has no points)")
        self.extent = data.scene.extent()
        self.sh_degree = min(gaussians.sh_degree, cfg.sh_degree) if cfg.sh_policy == "probation" else 0
        self.params = self._params_from(gaussians)
        self.optimizer = self._make_optimizer()
        self.stats = density.GradientStats.zeros(len(gaussians), self.device)
        #: what density control did over the run, summed ("cloned", "split", "pruned", "needless", ...)
        self.density_totals: dict[str, int] = {}
        self.row_grads = RowGrads()   # gradients of the rows in view only (large models)
        self.step = 0
        #: seconds of the run so far, as the time limit counts them: wall clock from
        #: :meth:`start_clock` on, training segments and the work between them alike
        self.elapsed = 0.0
        self._clock: Optional[float] = None   # perf_counter() reading at which elapsed was 0
        #: how many renders the run will still make after training (its outputs, scores and
        #: report), asked anew as the run goes (a method's needs change): set by the job; the
        #: time limit leaves room for them (:meth:`finishing_reserve`)
        self.finishing_renders: Callable[[], int] = lambda: 0
        self._render_s: Optional[float] = None   # seconds a full-resolution render took, lately,
        self._render_step = 0                     # ... timed last at this step
        #: ... and the output images written then, at ``write_s`` seconds each (one image of the
        #: training size, as the job measured it; 0 until then)
        self.finishing_writes: Callable[[], int] = lambda: 0
        self.write_s = 0.0
        self.order: list[int] = []
        self.history: list[dict] = []
        self.budget = cfg.budget  # may be frozen by "auto"
        if self.budget is None:
            cap = auto_budget(data, cfg)
            if cap is not None:
                self.budget = max(len(gaussians), cap)
        self.growth_frozen = False
        self.sh_state = {"trial": None, "done": cfg.sh_degree == 0}
        self.best_psnr = -math.inf
        self.since_best = 0
        self.reset_done = False
        self.done_reason: Optional[str] = None
        self.last_densify = -1
        #: keep_best: the model that scored best on the held-out photos as captured (or, with
        #: ``best_by = "psnr"``, against the objective's held-out references: a driving method
        #: whose references do not follow the model sets that)
        self.best_by = "psnr_captured"
        #: (``score``, ``step``, and a ``snapshot()``)
        self.best: Optional[dict] = None
        self.best_step: Optional[int] = None   # the step of the model a run ended with, if restored
        #: the step at which held-out PSNR first stopped improving (growth and SH settled), if it did
        self.plateau_step: Optional[int] = None
        #: which rasterizer path each step takes (compiled once a cold cache has warmed up)
        self.compiler = CompileSwitch(cfg.compiled, max_degree=cfg.sh_degree, device=cfg.device)
        #: seconds the first compiled step spent tracing and loading its graphs: left out of
        #: :meth:`schedule_elapsed`, so a compiler's start-up does not change what the model becomes
        self.compile_stall = 0.0
        self._stall_measured = False
        self.bad_steps = 0       # consecutive steps skipped for a non-finite loss
        self.skipped_steps = 0   # all of them (reported)

    def set_objective(self, objective: Objective) -> None:
        """Fit ``objective`` from the next step on (its extra parameters get an Adam of their own)."""
        self.objective = objective
        groups = objective.param_groups()
        self.objective_optimizer = torch.optim.Adam(groups, eps=1e-15) if groups else None

    # --- parameters ---------------------------------------------------------------------
    def _params_from(self, g: GaussianSet) -> dict:
        k = num_sh_coeffs(self.cfg.sh_degree)
        sh = np.zeros((len(g), k, 3), np.float32)
        m = min(k, g.sh.shape[1])
        sh[:, :m] = g.sh[:, :m]
        t = lambda a: torch.nn.Parameter(torch.tensor(np.ascontiguousarray(a), dtype=torch.float32,  # noqa: E731
                                                      device=self.device))
        return {"means": t(g.means), "log_scales": t(g.log_scales), "quats": t(g.quats),
                "logit_opacities": t(g.logit_opacities), "sh_dc": t(sh[:, :1]), "sh_rest": t(sh[:, 1:])}

    def _make_optimizer(self) -> torch.optim.Adam:
        c = self.cfg
        lrs = {"means": c.lr_means * self.extent, "log_scales": c.lr_scales, "quats": c.lr_quats,
               "logit_opacities": c.lr_opacity, "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest}
        groups = [{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in PARAM_NAMES]
        try:  # one fused kernel per group: ~5x faster than foreach on a 1M-Gaussian CPU model
            return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
        except (RuntimeError, TypeError, ValueError):  # a device or torch without fused Adam
            return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    def gaussians(self) -> GaussianSet:
        """The current model at its active SH degree (what a PLY export holds)."""
        p = {n: v.detach().cpu().numpy() for n, v in self.params.items()}
        k = num_sh_coeffs(self.sh_degree)
        sh = np.concatenate([p["sh_dc"], p["sh_rest"][:, : k - 1]], 1)
        return GaussianSet(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], sh)

    def _sh(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The active SH coefficients as (DC, rest) blocks: :func:`render` joins them only for
        the Gaussians in view (a full concatenation copied every coefficient on every step)."""
        k = num_sh_coeffs(self.sh_degree)
        return self.params["sh_dc"], self.params["sh_rest"][:, : k - 1]

    # --- schedule -----------------------------------------------------------------------
    def level(self) -> int:
        for until, factor in self.cfg.pyramid:
            if self.step < until:
                return int(factor)
        return 1

    def _full_res_from(self) -> int:
        return max([int(until) for until, _ in self.cfg.pyramid], default=0)

    def _means_lr(self) -> float:
        """INRIA's log-linear decay over the iteration limit. Not over a time limit: decayed
        over 5 minutes, it left short runs 1.5 dB below (benchmarks/RESULTS.md#training-lr-time)."""
        c = self.cfg
        t = min(1.0, self.step / max(1, c.iterations))
        return math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final)) * self.extent

    def _next_view(self) -> int:
        if not self.order:
            self.order = [int(i) for i in self.np_rng.permutation(self.data.train_ids)]
        return self.order.pop()

    # --- one step -----------------------------------------------------------------------
    def train_step(self) -> float:
        self.compiler.note_step(self.step)
        # before own_threads: a finished warm-up gives torch its core back in compiled(), and
        # own_threads must read that count (its exit restores what it read)
        path = self.compiler.compiled()
        # numba's path: its kernels get torch's threads, torch one (numba_kernels.own_threads)
        with numba_kernels.own_threads() if path == "numba" else contextlib.nullcontext():
            return self._train_step(path)

    def _forward(self, index: int, level: int, path, weights: Optional[torch.Tensor] = None):
        """Render training view ``index`` at pyramid ``level`` on ``path`` and take the loss
        against the objective's target: (camera, render output, loss). ``weights``: (N,) zeros
        the backward fills with the view's blending weights (rasterizer.render)."""
        c = self.cfg
        cam, img = self.data.view(index, level)
        viewmat, K = view_tensors(cam, self.device)
        rg = self.row_grads
        k = num_sh_coeffs(self.sh_degree)   # active SH coefficients, as in _sh()
        p = {n: rg.track(n, v, cols=k - 1 if n == "sh_rest" else None) for n, v in self.params.items()}
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], (p["sh_dc"], p["sh_rest"]),
                     viewmat, K, cam.width, cam.height, sh_degree=self.sh_degree,
                     background=self._background(), compiled=path, gather=rg, weights=weights)
        log_l = None
        if self.forms_image:   # fit the photos as the lamp lit them and the water showed them
            rgb, log_l = self.seen_and_lamp(out, cam)
            out = out._replace(rgb=rgb)
        target, weight = self.objective.target(index, img, out.rgb.detach())
        if log_l is not None:   # under a lamp the frame's dark parts count as if evenly lit
            even = self.lamp_weight(log_l)
            weight = even if weight is None else weight * even
        keep = self.counts(index, level)   # a burned-in overlay does not count
        rgb = out.rgb
        if keep is not None:
            weight = keep.to(img.dtype) if weight is None else weight * keep
            # its pixels show the target, so the SSIM windows that reach into it from outside
            # take nothing from the render there either: the overlay gets no gradient at all
            rgb = torch.where(keep.unsqueeze(-1), rgb, target.detach())
        loss = training_loss(rgb, target, c.lambda_dssim if self.objective.use_ssim else 0.0, weight,
                             self.objective.loss_kind,
                             fast_ssim=numba_ssim.ssim_term if path == "numba" and numba_ssim.load() else None)
        return cam, out, loss

    def dry_step(self, index: int):
        """One forward and backward pass on training view ``index`` at the training resolution
        that changes nothing (the gradients are dropped): what a step costs now, for
        ``plan.time_steps``. Returns the path it ran on."""
        path = self.compiler.compiled()
        with numba_kernels.own_threads() if path == "numba" else contextlib.nullcontext():
            _, _, loss = self._forward(index, 1, path)
            loss.backward()
            self.row_grads.write()
        for v in self.params.values():
            v.grad = None
        return path

    def _train_step(self, path) -> float:
        c = self.cfg
        level = self.level()
        index = self._next_view()
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = self._means_lr()
        gather_stats = self.densifying() and (self._uses_gradient_stats() or c.density.uses_significance())
        weights = None
        if gather_stats and c.density.uses_significance():
            weights = torch.zeros(self.params["means"].shape[0], dtype=torch.float32, device=self.device)
        cam, out, loss = self._forward(index, level, path, weights)
        value = loss.item()
        if not math.isfinite(value):   # skip the update: the parameters keep their last good values
            self.bad_steps += 1
            self.skipped_steps += 1
            self.step += 1
            if self.bad_steps >= MAX_BAD_STEPS:
                raise TrainingDiverged(f"training diverged: the loss was {value} for {self.bad_steps} steps in a row "
                                       f"(last at step {self.step}, view {self.data.scene.cameras[index].name})")
            return value
        self.bad_steps = 0
        loss.backward()
        self.row_grads.write()   # .grad of the parameters: the visible rows' gradients, zero elsewhere
        if any(c.density.regularisers()):
            value += self._regulariser_grad(out.radii > 0)
        if gather_stats:
            if weights is not None:   # in pixels of the training resolution
                weights *= self.data.pixel_area(index, cam)
            self.stats.add(out.means2d.grad if self._uses_gradient_stats() else None, out.radii,
                           cam.width, cam.height, weights)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if self.densifying():
            c.density.after_step(self)
        if self.objective_optimizer is not None:
            self.objective_optimizer.step()
            self.objective_optimizer.zero_grad(set_to_none=True)
        self._medium_step()
        self._lamp_step()
        self.step += 1
        if self.densifying() and self.step >= c.densify_from and self.step % c.densify_every == 0:
            self.densify()
            self.last_densify = self.step
        if (c.opacity_reset_every and self.step < c.densify_until and self.step % c.opacity_reset_every == 0
                and not self.growth_frozen):
            density.reset_opacity(self.params, self.optimizer)
            self.reset_done = True
        if c.sh_policy == "schedule" and self.step % c.sh_every == 0 and self.sh_degree < c.sh_degree:
            self.sh_degree += 1
        return value

    def _regulariser_grad(self, in_view: torch.Tensor) -> float:
        """3DGS-MCMC's L1 terms, ``opacity_reg * mean(opacity) + scale_reg * mean(scale) /
        extent`` over the whole model, differentiated on the Gaussians in view (``in_view``
        (N,) bool; the others would get a constant push with nothing to weigh it against).
        Their gradient is added to ``.grad`` in closed form after the render's backward, the
        same sum under row-sparse and plain gradients (tests/test_train.py). Returns the terms'
        value (for the reported loss)."""
        opacity_reg, scale_reg = self.cfg.density.regularisers()
        n = self.params["means"].shape[0]
        ids = torch.nonzero(in_view).squeeze(1)
        value = 0.0
        with torch.no_grad():
            for name, weight in (("logit_opacities", opacity_reg / n),
                                 ("log_scales", scale_reg / (3 * n * self.extent))):
                if not weight:
                    continue
                p = self.params[name]
                x = p.detach()[ids]
                f = torch.sigmoid(x) if name == "logit_opacities" else x.exp()
                g = f * (1 - f) if name == "logit_opacities" else f
                value += weight * float(f.sum())
                if p.grad is None:
                    p.grad = torch.zeros_like(p)
                p.grad.index_add_(0, ids, (weight * g).to(p.grad.dtype))
        return value

    def check_finite(self) -> None:
        """Raise :class:`TrainingDiverged` if a parameter or an Adam moment holds NaN or Inf
        (every ``log_every`` steps and before every checkpoint: a broken model is never saved)."""
        for name, v in self.params.items():
            if not bool(torch.isfinite(v).all()):
                bad = int((~torch.isfinite(v)).reshape(len(v), -1).any(1).sum())
                raise TrainingDiverged(f"training diverged: {bad} Gaussians have NaN/Inf in '{name}' at step "
                                       f"{self.step}")
        if self.medium is not None and not bool(torch.isfinite(self.medium.raw).all()):
            raise TrainingDiverged(f"training diverged: the water's coefficients hold NaN/Inf at step {self.step}")
        if self.lamp is not None and not bool(torch.isfinite(self.lamp.raw).all()):
            raise TrainingDiverged(f"training diverged: the lamp's terms hold NaN/Inf at step {self.step}")
        for group in self.optimizer.param_groups:
            for p in group["params"]:
                for key, moment in self.optimizer.state.get(p, {}).items():
                    if torch.is_tensor(moment) and moment.numel() > 1 and not bool(torch.isfinite(moment).all()):
                        raise TrainingDiverged(f"training diverged: Adam's {key} of '{group['name']}' holds NaN/Inf "
                                               f"at step {self.step}")

    # --- the loop -----------------------------------------------------------------------
    def run(self, on_progress: Optional[Callable[[Progress], None]] = None,
            should_stop: Optional[Callable[[], bool]] = None,
            on_checkpoint: Optional[Callable[["Trainer"], None]] = None, checkpoint_every_s: float = 60.0) -> str:
        """Train until a limit, a plateau or ``should_stop()``. Returns the reason it stopped."""
        reason = self.train_until(on_progress=on_progress, should_stop=should_stop, on_checkpoint=on_checkpoint,
                                  checkpoint_every_s=checkpoint_every_s)
        if reason != "stopped":
            self.restore_best()
            self.finish(on_progress)
        return reason

    def train_until(self, until: Optional[Callable[[], bool]] = None,
                    on_progress: Optional[Callable[[Progress], None]] = None,
                    should_stop: Optional[Callable[[], bool]] = None,
                    on_checkpoint: Optional[Callable[["Trainer"], None]] = None,
                    checkpoint_every_s: float = 60.0) -> str:
        """Train one segment. Before each step, in this order: the iteration and time limits
        and a plateau found by the last evaluation (``done_reason``) end the segment with that
        reason; ``should_stop()`` ends it with ``"stopped"``; ``until()`` ends it with
        ``"until"`` (a driving method has work to do before the next step). ``done_reason``
        stays set until the caller clears it. Checkpoints are taken every
        ``checkpoint_every_s`` seconds, counted across segments."""
        c = self.cfg
        if self._clock is None:
            self.start_clock()
        t_start = self._clock
        self.elapsed = time.perf_counter() - t_start   # the work since the last segment counts too
        self.compiler.take_stall()   # a path loaded before the clock started is not the run's
        if self._last_checkpoint is None:
            self._last_checkpoint = time.perf_counter()
        losses = []
        while True:
            if self.step >= c.iterations:
                self.done_reason = self.done_reason or "iteration limit"
            if not self.done_reason and self.time_is_up():
                self.done_reason = "time limit"
            if self.done_reason:
                return self.done_reason
            if should_stop is not None and should_stop():
                return "stopped"
            if until is not None and until():
                return "until"
            prev_level = self.level()
            first_compiled = not self._stall_measured and self.compiler.compiled() is True
            t_step = time.perf_counter()
            losses.append(self.train_step())
            if first_compiled:
                self.compile_stall += time.perf_counter() - t_step
                self._stall_measured = True
            self.compile_stall += self.compiler.take_stall()   # numba's kernels loaded mid-run
            if self.level() != prev_level:
                self.data.drop_level(prev_level)
            self.elapsed = time.perf_counter() - t_start
            evaluated = {}
            if self.step % c.eval_every == 0 or self.step >= c.iterations:
                evaluated = self.evaluate()
                self._after_eval(evaluated)
                self.elapsed = time.perf_counter() - t_start
            recent = [v for v in losses[-c.log_every:] if math.isfinite(v)]
            self._last_loss = float(np.mean(recent)) if recent else float("nan")
            if self.step % c.log_every == 0:
                self.check_finite()
            if on_progress and (self.step % c.log_every == 0 or self.step == 1 or evaluated or self.done_reason):
                on_progress(self.progress(self._last_loss, evaluated))
            if on_checkpoint and time.perf_counter() - self._last_checkpoint >= checkpoint_every_s:
                on_checkpoint(self)
                self._last_checkpoint = time.perf_counter()

    # --- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        self.check_finite()
        return {
            "config": asdict(self.cfg), "step": self.step, "elapsed": self.elapsed,
            "params": {n: v.detach().cpu().clone() for n, v in self.params.items()},
            "optimizer": self.optimizer.state_dict(), "stats": self.stats.state_dict(),
            "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(),
            "np_rng": self.np_rng.bit_generator.state, "order": list(self.order),
            "history": self.history, "budget": self.budget, "growth_frozen": self.growth_frozen,
            "sh_degree": self.sh_degree, "sh_state": self.sh_state, "best_psnr": self.best_psnr,
            "since_best": self.since_best, "reset_done": self.reset_done, "done_reason": self.done_reason,
            "objective_optimizer": None if self.objective_optimizer is None else self.objective_optimizer.state_dict(),
            "last_densify": self.last_densify, "density_totals": dict(self.density_totals),
            "compile_stall": self.compile_stall, "plateau_step": self.plateau_step,
            "medium": self._medium_state(), "lamp": self._lamp_state(),
            "best": None if self.best is None else {
                **self.best, "params": {n: v.detach().cpu() for n, v in self.best["params"].items()}},
        }

    def load_state_dict(self, s: dict) -> None:
        self.step, self.elapsed = s["step"], s["elapsed"]
        self._clock = None   # the clock goes on from the saved time when training resumes
        self.params = {n: torch.nn.Parameter(v.to(self.device)) for n, v in s["params"].items()}
        self.optimizer = self._make_optimizer()
        fused = [g.get("fused") for g in self.optimizer.param_groups]
        self.optimizer.load_state_dict(s["optimizer"])
        for g, f in zip(self.optimizer.param_groups, fused):  # the saved flags are the old run's
            g["fused"] = f
            if f:
                g["foreach"] = None
        self.stats = density.GradientStats(**s["stats"]).to(self.device)
        self.gen.set_state(s["gen"])
        torch.set_rng_state(s["torch_rng"])
        self.np_rng.bit_generator.state = s["np_rng"]
        self.order = list(s["order"])
        self.history = list(s["history"])
        self.budget, self.growth_frozen = s["budget"], s["growth_frozen"]
        self.sh_degree, self.sh_state = s["sh_degree"], s["sh_state"]
        self.best_psnr, self.since_best = s["best_psnr"], s["since_best"]
        self.reset_done = s["reset_done"]
        self.last_densify = s.get("last_densify", -1)   # checkpoints before keep_best have neither
        self.density_totals = dict(s.get("density_totals", {}))
        self.compile_stall = s.get("compile_stall", 0.0)
        self.plateau_step = s.get("plateau_step")
        self._stall_measured = False   # this process's own first compiled step adds to it
        self.best = s.get("best")
        self._load_medium_state(s.get("medium"))
        self._load_lamp_state(s.get("lamp"))
        if self.objective_optimizer is not None and s.get("objective_optimizer") is not None:
            self.objective_optimizer.load_state_dict(s["objective_optimizer"])
        # limits are checked again against this run's settings (a resume may raise them)
        self.done_reason = None if s["done_reason"] in ("iteration limit", "time limit") else s["done_reason"]


def auto_budget(data: TrainData, cfg: TrainConfig) -> Optional[int]:
    """The most Gaussians an automatic budget allows (None: no cap): ``training pixels /
    pixels_per_gaussian``, and ``seabed pixels / surface_pixels_per_gaussian``, where the seabed's
    pixels are the training pixels over the median number of training views that see a sparse
    point (a survey whose views overlap 12 times holds a twelfth of its pixels' worth of
    seabed). The smaller of the two."""
    caps = []
    pixels = data.training_pixels()
    rule = cfg.density
    if rule.pixels_per_gaussian > 0:
        caps.append(pixels / rule.pixels_per_gaussian)
    if rule.surface_pixels_per_gaussian > 0:
        views = sparse_coverage(data).median_views
        if views >= 1:
            caps.append(pixels / views / rule.surface_pixels_per_gaussian)
    return int(min(caps)) if caps else None


def make_trainer(scene_dir: str | Path, cfg: TrainConfig, images: Optional[str | Path] = None,
                 gaussians: Optional[GaussianSet] = None, gt_images: Optional[str | Path] = None,
                 light: Optional[dict] = None) -> Trainer:
    """Load a survey and build its trainer; all input checks happen here, before any work.
    ``images``: the folder to train on (default ``SCENE/images``); ``gt_images``: a folder of
    ground-truth images with the same names, for scoring only; ``light``: see :class:`Trainer`."""
    return Trainer(load_data(scene_dir, cfg, images, gt_images), cfg, gaussians, light)


def load_data(scene_dir: str | Path, cfg: TrainConfig, images: Optional[str | Path] = None,
              gt_images: Optional[str | Path] = None) -> TrainData:
    """Load a survey for training (:func:`make_trainer`'s checks and reading, without the trainer)."""
    cfg.validate()
    scene_dir = Path(scene_dir)
    image_dir = None
    if images is not None:
        image_dir = resolve_image_dir(scene_dir, images)
        if image_dir.is_dir() and not any(image_dir.iterdir()):
            raise RecGSError(f"{image_dir}: image folder is empty")
    elif (scene_dir / "images").is_dir() and not any((scene_dir / "images").iterdir()):
        raise RecGSError(f"{scene_dir / 'images'}: image folder is empty")
    scene = load_scene(scene_dir, image_dir=image_dir)
    gt_scene = load_scene(scene_dir, image_dir=resolve_image_dir(scene_dir, gt_images)) if gt_images is not None else None
    test_names = None
    if cfg.block is not None:   # one block of a survey trained in blocks
        scene = block_scene(scene, cfg.block)
        gt_scene = None if gt_scene is None else block_scene(gt_scene, cfg.block)
        test_names = list(cfg.block["test"])
    return TrainData(scene, cfg.downscale, cfg.holdout_every, cfg.device, gt_scene=gt_scene, max_side=cfg.max_side,
                     test_names=test_names)
