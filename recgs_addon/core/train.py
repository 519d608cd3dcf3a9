"""3D Gaussian Splatting optimisation on the CPU (or any torch device), built to model only
what the scene needs.

* :class:`TrainConfig` holds every setting; :func:`preset` gives ``default`` (lean: coarse to
  fine, growth under a budget that stops once held-out PSNR stops improving, SH degree raised
  only when it helps held-out views, stop on a held-out plateau) and ``vanilla`` (INRIA's
  schedule: 30k iterations, densify every 100 from 500 to 15k, opacity reset every 3k,
  SH degree +1 every 1k).
* :class:`TrainData` loads the survey, holds out every Nth image by sorted name (LLFF) and
  keeps an image pyramid for coarse-to-fine training.
* :class:`Trainer` runs steps, density control and evaluation, and saves/restores its whole
  state (parameters, Adam moments, gradient statistics, random generators) so that a resumed
  run continues exactly where the checkpoint was taken.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from . import density
from .cameras import Camera
from .colmap import Scene, load_scene
from .errors import RecGSError
from .gaussians import GaussianSet, init_from_points, num_sh_coeffs
from .losses import psnr, ssim, training_loss
from .rasterizer import render
from .rowgrads import RowGrads

#: Smallest image side (pixels) accepted after downscaling.
MIN_IMAGE_SIDE = 8
#: Training modes: plain 3DGS (on the captured images, or ``oracle`` on ground truth) and the
#: caustic-removal methods of core/recgs.py.
MODES = ("3dgs", "oracle", "recgs", "filter2d", "joint")


@dataclass
class TrainConfig:
    preset: str = "default"
    iterations: int = 30_000            # upper bound on optimisation steps
    max_minutes: Optional[float] = None  # wall-clock limit (None: none)
    budget: Optional[int] = None         # max Gaussians; None = "auto" (stop growth on plateau)
    downscale: int = 1                   # training resolution = image size / downscale
    sh_degree: int = 3                   # cap on the SH degree
    sh_policy: str = "probation"         # "probation" (raise only if it helps) | "schedule" (INRIA)
    sh_every: int = 1000                 # "schedule": +1 degree every this many steps
    seed: int = 0
    device: str = "cpu"
    holdout_every: int = 8               # LLFF: every 8th image by sorted name is held out; 0 = none
    # learning rates (INRIA); means scaled by the scene extent, decayed log-linearly
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lambda_dssim: float = 0.2
    # density control
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4
    opacity_reset_every: int = 3000
    # coarse to fine: ((until_step, extra downscale factor), ...); the last level is 1
    pyramid: tuple = ()
    # evaluation and stopping
    eval_every: int = 1000
    eval_views: int = 0                  # 0 = all held-out views
    plateau_patience: int = 0            # evals without a gain of plateau_min_gain dB -> stop; 0 = never
    plateau_min_gain: float = 0.02
    growth_patience: int = 3             # budget auto: evals without plateau_min_gain*5 dB -> stop growth
    growth_rate: float = 0.0             # max fractional growth per densification (0 = unlimited)
    pixels_per_gaussian: float = 0.0     # budget auto: at most (training pixels / this) Gaussians
    sh_probation: int = 1000             # steps given to a new SH degree before it is judged
    sh_min_gain: float = 0.05            # dB a new SH degree must add on held-out views
    log_every: int = 50
    background: tuple = (0.0, 0.0, 0.0)
    compiled: Optional[bool] = None      # rasterizer through torch.compile: None = when available
    # caustic removal (core/recgs.py): mode 3dgs | oracle (plain) | recgs | filter2d | joint
    mode: str = "3dgs"
    caustic_k: int = 0                   # low-pass block size (odd; the paper: 9); 0 = from the residual spectrum
    caustic_dc: bool = False             # recgs: keep C's DC term (the paper); False: C has zero mean per view
    caustic_model: str = "additive"      # additive: I - C (paper) | multiplicative: I / exp(C_log)
    warmup: int = 3000                   # recgs: at most this many plain steps before the first recurrence
    warmup_share: float = 0.5            # recgs: ... and at most this share of the time limit
    recurrence_patience: int = 2         # recgs: rounds in a row that hurt held-out views before C is dropped
    harm_tol: float = 0.5                # recgs: dB below the plain model's held-out PSNR that counts as hurting
    stall_ratio: float = 0.6             # recgs: C is not settling when its change shrinks by less than
    stall_growth: float = 0.15           # ... this per round while mean |C| grows by more than this
    recurrence_steps: int = 200          # recgs: optimisation steps per recurrence
    max_recurrences: int = 40
    recurrence_tol: float = 0.1          # stop when mean |dC| / mean |C| falls below this
    caustic_floor: float = 0.01          # recgs: C is dropped when mean |C| is below this (1 % of full scale)

    #: Settings added since a release, with the value that reproduces runs saved before them.
    _BEFORE = {"caustic_dc": True}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The config saved in a checkpoint (``asdict`` form); a setting newer than the
        checkpoint takes the value the run was made with, so a resume continues it unchanged."""
        d = {**cls._BEFORE, **d}
        return cls(**{**d, "pyramid": tuple(tuple(x) for x in d["pyramid"]), "background": tuple(d["background"])})

    def validate(self) -> None:
        """Refuse settings no run can use (called before any data is read)."""
        if self.downscale < 1:
            raise RecGSError(f"downscale must be an integer >= 1, got {self.downscale}")
        if self.budget is not None and self.budget < 1:
            raise RecGSError(f"budget must be at least 1 Gaussian, got {self.budget}")
        if self.mode not in MODES:
            raise RecGSError(f"unknown mode {self.mode!r} (choose from {', '.join(MODES)})")
        if self.caustic_k < 0 or (self.caustic_k and self.caustic_k % 2 == 0):
            raise RecGSError(f"caustic filter size must be a positive odd number (or 0 = auto), got {self.caustic_k}")
        if self.caustic_model not in ("additive", "multiplicative"):
            raise RecGSError(f"unknown caustic model {self.caustic_model!r} (additive or multiplicative)")
        if self.recurrence_steps < 1:
            raise RecGSError(f"recurrence steps must be at least 1, got {self.recurrence_steps}")


def preset(name: str, **overrides) -> TrainConfig:
    """``vanilla``: INRIA's schedule. ``default``: the lean schedule measured in docs/training.md."""
    if name == "vanilla":
        cfg = TrainConfig(preset="vanilla", iterations=30_000, sh_policy="schedule",
                          plateau_patience=0, budget=10**9, eval_every=1000)
    elif name == "default":
        cfg = TrainConfig(preset="default", iterations=30_000, densify_from=200, densify_until=4000,
                          densify_every=100, opacity_reset_every=0, pyramid=((300, 2),),
                          eval_every=250, plateau_patience=4, growth_patience=2, sh_policy="probation",
                          growth_rate=0.25, pixels_per_gaussian=8.0)
    else:
        raise RecGSError(f"unknown preset {name!r} (choose default or vanilla)")
    return replace(cfg, **{k: v for k, v in overrides.items() if v is not None})


def holdout_split(names: list[str], every: int) -> tuple[list[int], list[int]]:
    """(train indices, test indices) into ``sorted(names)`` order: every ``every``-th image
    (0, every, 2*every, ...) is held out, as in LLFF/Mip-NeRF 360; ``every`` = 0 keeps all."""
    order = sorted(range(len(names)), key=lambda i: names[i])
    if every <= 0:
        return order, []
    test = [i for k, i in enumerate(order) if k % every == 0]
    train = [i for k, i in enumerate(order) if k % every != 0]
    return train, test


class TrainData:
    """Cameras and images of a survey for training and evaluation.

    Images are read once per pyramid level (OIIO box filter) and kept as (H, W, 3) float32
    tensors. Cameras are scaled to match each level.
    """

    def __init__(self, scene: Scene, downscale: int, holdout_every: int, device: str = "cpu",
                 gt_scene: Optional[Scene] = None):
        self.scene = scene
        self.gt_scene = gt_scene
        #: full-resolution replacement targets by camera index (caustic-free estimates)
        self.targets: dict[int, torch.Tensor] = {}
        self.downscale = downscale
        self.device = device
        names = [c.name for c in scene.cameras]
        self.train_ids, self.test_ids = holdout_split(names, holdout_every)
        if not self.train_ids:
            raise RecGSError(f"{scene.image_dir}: no training images left after holding out every "
                             f"{holdout_every}th image")
        for cam in scene.cameras:
            w, h = round(cam.width / downscale), round(cam.height / downscale)
            if min(w, h) < MIN_IMAGE_SIDE:
                raise RecGSError(f"{scene.image_path(cam)}: downscale {downscale} would make this "
                                 f"{cam.width}x{cam.height} image {w}x{h}, below {MIN_IMAGE_SIDE} px")
        self._cache: dict[tuple[int, int], tuple[Camera, torch.Tensor]] = {}

    def view(self, index: int, level: int = 1) -> tuple[Camera, torch.Tensor]:
        """(camera, image (H, W, 3)) of camera ``index`` at extra downscale ``level``."""
        key = (index, level)
        if key not in self._cache:
            cam = self.scene.cameras[index]
            f = self.downscale * level
            img = self.scene.load_image(cam, downscale=f)
            self._cache[key] = (cam.resized(img.shape[1], img.shape[0]), torch.from_numpy(img).to(self.device))
        return self._cache[key]

    def target(self, index: int, level: int = 1) -> tuple[Camera, torch.Tensor]:
        """(camera, what to fit) of camera ``index``: the replacement target if one is set
        (area-averaged to the level's size), else the image."""
        cam, img = self.view(index, level)
        t = self.targets.get(index)
        if t is None:
            return cam, img
        if t.shape[:2] != img.shape[:2]:
            t = torch.nn.functional.adaptive_avg_pool2d(t.permute(2, 0, 1), img.shape[:2]).permute(1, 2, 0)
        return cam, t

    def gt_view(self, index: int) -> Optional[torch.Tensor]:
        """Ground-truth image (H, W, 3) of camera ``index`` at the training resolution, if any."""
        if self.gt_scene is None:
            return None
        key = (index, "gt")
        if key not in self._cache:
            cam = self.gt_scene.cameras[index]
            self._cache[key] = (cam, torch.from_numpy(self.gt_scene.load_image(cam, self.downscale)).to(self.device))
        return self._cache[key][1]

    def drop_level(self, level: int) -> None:
        for key in [k for k in self._cache if k[1] == level]:
            del self._cache[key]


def _view_tensors(cam: Camera, device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor(cam.viewmat, dtype=torch.float32, device=device),
            torch.tensor(cam.K, dtype=torch.float32, device=device))


PARAM_NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh_dc", "sh_rest")


@dataclass
class Progress:
    phase: str
    iteration: int
    loss: float
    gaussians: int
    sh_degree: int
    elapsed: float
    eta: Optional[float]
    psnr_test: Optional[float] = None
    ssim_test: Optional[float] = None
    psnr_test_gt: Optional[float] = None   # against the survey's ground truth, where it has one
    recurrence: Optional[int] = None       # recgs: recurrences done
    c_change: Optional[float] = None       # recgs: relative change of C in the last recurrence


class Trainer:
    """One training run. ``run()`` until done or told to stop; ``state_dict()`` to checkpoint."""

    def __init__(self, data: TrainData, cfg: TrainConfig, gaussians: Optional[GaussianSet] = None):
        cfg.validate()
        self.data, self.cfg = data, cfg
        self.device = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.np_rng = np.random.default_rng(cfg.seed)
        if gaussians is None:
            gaussians = init_from_points(data.scene.points, data.scene.colors, sh_degree=0)
        if len(gaussians) == 0:
            raise RecGSError("no Gaussians to train (the model has no points)")
        self.extent = data.scene.extent()
        self.sh_degree = min(gaussians.sh_degree, cfg.sh_degree) if cfg.sh_policy == "probation" else 0
        self.params = self._params_from(gaussians)
        self.optimizer = self._make_optimizer()
        self.stats = density.GradientStats.zeros(len(gaussians))
        self.row_grads = RowGrads()   # gradients of the rows in view only (large models)
        self.step = 0
        self.elapsed = 0.0
        self.order: list[int] = []
        self.history: list[dict] = []
        self.budget = cfg.budget  # may be frozen by "auto"
        if self.budget is None and cfg.pixels_per_gaussian > 0:
            pixels = sum(data.scene.cameras[i].width * data.scene.cameras[i].height for i in data.train_ids)
            self.budget = max(len(gaussians), int(pixels / cfg.downscale ** 2 / cfg.pixels_per_gaussian))
        self.growth_frozen = False
        self.sh_state = {"trial": None, "done": cfg.sh_degree == 0}
        self.best_psnr = -math.inf
        self.since_best = 0
        self.reset_done = False
        self.done_reason: Optional[str] = None

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
        c = self.cfg
        t = min(1.0, self.step / max(1, c.iterations))
        return math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final)) * self.extent

    def _next_view(self) -> int:
        if not self.order:
            self.order = [int(i) for i in self.np_rng.permutation(self.data.train_ids)]
        return self.order.pop()

    # --- one step -----------------------------------------------------------------------
    def train_step(self) -> float:
        c = self.cfg
        level = self.level()
        index = self._next_view()
        cam, img = self.data.target(index, level)
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = self._means_lr()
        viewmat, K = _view_tensors(cam, self.device)
        rg = self.row_grads
        k = num_sh_coeffs(self.sh_degree)   # active SH coefficients, as in _sh()
        p = {n: rg.track(n, v, cols=k - 1 if n == "sh_rest" else None) for n, v in self.params.items()}
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], (p["sh_dc"], p["sh_rest"]),
                     viewmat, K, cam.width, cam.height, sh_degree=self.sh_degree,
                     background=torch.tensor(c.background, dtype=torch.float32), compiled=c.compiled,
                     gather=rg)
        loss = training_loss(self._prediction(out.rgb, index), img, c.lambda_dssim)
        loss.backward()
        rg.write()   # .grad of the parameters: the visible rows' gradients, zero elsewhere
        if self._densifying() and out.means2d.grad is not None:
            self.stats.add(out.means2d.grad, out.radii, cam.width, cam.height)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self._after_step()
        self.step += 1
        if self._densifying() and self.step >= c.densify_from and self.step % c.densify_every == 0:
            self.densify()
        if (c.opacity_reset_every and self.step < c.densify_until and self.step % c.opacity_reset_every == 0
                and not self.growth_frozen):
            density.reset_opacity(self.params, self.optimizer)
            self.reset_done = True
        if c.sh_policy == "schedule" and self.step % c.sh_every == 0 and self.sh_degree < c.sh_degree:
            self.sh_degree += 1
        return loss.item()

    def _prediction(self, rgb: torch.Tensor, index: int) -> torch.Tensor:
        """What the loss compares with the target (the joint baseline adds its caustic field)."""
        return rgb

    def _after_step(self) -> None:
        """Extra optimiser steps of subclasses."""

    def _densifying(self) -> bool:
        return self.step < self.cfg.densify_until and not self.growth_frozen

    def densify(self) -> dict:
        """Clone small and split large Gaussians with high screen gradient, within the budget;
        prune transparent, huge and never-visible ones."""
        c = self.cfg
        p = self.params
        n0 = p["means"].shape[0]
        grads = self.stats.mean().to(self.device)
        max_scale = p["log_scales"].detach().exp().max(1).values
        high = grads >= c.densify_grad_threshold
        clone = high & (max_scale <= density.PERCENT_DENSE * self.extent)
        split = high & ~clone
        room = (self.budget - n0) if self.budget is not None else n0 * 10
        if c.growth_rate > 0:
            room = min(room, max(1, int(c.growth_rate * n0)))
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
            children = density.split_values(p, torch.cat([split, torch.zeros(n_clone, dtype=torch.bool)]), self.gen)
            density.append(p, self.optimizer, children)
        n = p["means"].shape[0]
        opac = torch.sigmoid(p["logit_opacities"].detach())
        prune = opac < density.PRUNE_OPACITY
        prune[:n0] |= split  # split originals are replaced by their children
        if self.reset_done:
            radius = torch.cat([self.stats.max_radius, torch.zeros(n - n0, dtype=torch.int32)])
            big = p["log_scales"].detach().exp().max(1).values > density.PRUNE_WORLD_SCALE * self.extent
            prune |= (radius > density.PRUNE_SCREEN_RADIUS) | big
        if bool(prune.all()):
            prune[torch.argmax(opac)] = False  # never prune everything (the backward needs one)
        if prune.any():
            density.remove(p, self.optimizer, ~prune)
        self.stats = density.GradientStats.zeros(p["means"].shape[0])
        return {"cloned": n_clone, "split": n_split, "pruned": int(prune.sum())}

    # --- evaluation ---------------------------------------------------------------------
    @torch.no_grad()
    def render_view(self, index: int) -> torch.Tensor:
        """(H, W, 3) render of camera ``index`` at the training resolution (not clamped)."""
        cam, _ = self.data.view(index, 1)
        viewmat, K = _view_tensors(cam, self.device)
        p = self.params
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], self._sh(),
                     viewmat, K, cam.width, cam.height, sh_degree=self.sh_degree,
                     background=torch.tensor(self.cfg.background, dtype=torch.float32),
                     compiled=self.cfg.compiled)
        return out.rgb

    def _eval_reference(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        """What a held-out render is scored against for the run's own decisions: the held-out
        image (caustic modes compensate its caustics, see core/recgs.py)."""
        return self.data.view(index, 1)[1]

    def heldout_ids(self, ids: Optional[list[int]] = None) -> list[int]:
        """The held-out views a score is taken on (``ids``, default all, cut to ``eval_views``)."""
        ids = self.data.test_ids if ids is None else ids
        return ids[: self.cfg.eval_views] if self.cfg.eval_views else ids

    @torch.no_grad()
    def evaluate(self, ids: Optional[list[int]] = None) -> dict:
        """Mean PSNR (dB) and SSIM over held-out views at the training resolution: ``psnr`` /
        ``ssim`` against the held-out images (what the run decides on), and ``psnr_gt`` /
        ``ssim_gt`` against the ground truth where the survey has one."""
        ids = self.heldout_ids(ids)
        if not ids:
            return {}
        ps, ss, pg, sg = [], [], [], []
        for i in ids:
            rgb = self.render_view(i).clamp(0, 1)
            ref = self._eval_reference(i, rgb)
            ps.append(psnr(rgb, ref))
            ss.append(float(ssim(rgb, ref)))
            gt = self.data.gt_view(i)
            if gt is not None:
                pg.append(psnr(rgb, gt))
                sg.append(float(ssim(rgb, gt)))
        out = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}
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
                             **{k: metrics[k] for k in ("psnr_gt", "ssim_gt") if k in metrics},
                             "gaussians": int(self.params["means"].shape[0]), "sh_degree": self.sh_degree,
                             "elapsed": round(self.elapsed, 2), "phase": self._phase()})
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
        if c.sh_policy == "probation" and not self.sh_state["done"] and (self.growth_frozen or not self._densifying()):
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
                and (self.growth_frozen or not self._densifying()) and self.sh_state["done"]
                and self.sh_state["trial"] is None):
            self.done_reason = "held-out PSNR plateau"

    # --- the loop -----------------------------------------------------------------------
    def run(self, on_progress: Optional[Callable[[Progress], None]] = None,
            should_stop: Optional[Callable[[], bool]] = None,
            on_checkpoint: Optional[Callable[["Trainer"], None]] = None, checkpoint_every_s: float = 60.0) -> str:
        """Train until a limit, a plateau or ``should_stop()``. Returns the reason it stopped."""
        c = self.cfg
        t_start = time.perf_counter() - self.elapsed
        last_ckpt = time.perf_counter()
        losses = []
        while True:
            if self.step >= c.iterations:
                self.done_reason = self.done_reason or "iteration limit"
            if c.max_minutes is not None and self.elapsed >= 60 * c.max_minutes:
                self.done_reason = self.done_reason or "time limit"
            if self.done_reason:
                if not self._continue_after(self.done_reason):
                    break
                self.done_reason = None
            if should_stop is not None and should_stop():
                return "stopped"
            self._schedule()
            if self.done_reason:
                continue
            prev_level = self.level()
            losses.append(self.train_step())
            if self.level() != prev_level:
                self.data.drop_level(prev_level)
            self.elapsed = time.perf_counter() - t_start
            evaluated = {}
            if self.step % c.eval_every == 0 or self.step >= c.iterations:
                evaluated = self.evaluate()
                self._after_eval(evaluated)
                self.elapsed = time.perf_counter() - t_start
            if on_progress and (self.step % c.log_every == 0 or evaluated or self.done_reason):
                on_progress(self._progress(np.mean(losses[-c.log_every:]), evaluated))
            if on_checkpoint and time.perf_counter() - last_ckpt >= checkpoint_every_s:
                on_checkpoint(self)
                last_ckpt = time.perf_counter()
        if on_progress:
            on_progress(self._progress(np.mean(losses[-c.log_every:]) if losses else float("nan"), {}, "done"))
        return self.done_reason

    def _continue_after(self, reason: str) -> bool:
        """Whether to go on when the run would stop for ``reason`` (caustic modes go on to
        their recurrences after a plateau)."""
        return False

    def _schedule(self) -> None:
        """Work due before the next step (caustic re-estimation in core/recgs.py)."""

    def _phase(self) -> str:
        return "densify" if self._densifying() else "refine"

    def _progress_extra(self) -> dict:
        return {}

    def _progress(self, loss, metrics, phase=None) -> Progress:
        c = self.cfg
        eta = None
        if self.step:
            per = self.elapsed / self.step
            eta = per * (c.iterations - self.step)
            if c.max_minutes is not None:
                eta = min(eta, max(0.0, 60 * c.max_minutes - self.elapsed))
        phase = phase or self._phase()
        return Progress(phase, self.step, float(loss), int(self.params["means"].shape[0]), self.sh_degree,
                        round(self.elapsed, 2), None if eta is None else round(eta, 1),
                        metrics.get("psnr"), metrics.get("ssim"), metrics.get("psnr_gt"),
                        **self._progress_extra())

    # --- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "config": asdict(self.cfg), "step": self.step, "elapsed": self.elapsed,
            "params": {n: v.detach().cpu().clone() for n, v in self.params.items()},
            "optimizer": self.optimizer.state_dict(), "stats": self.stats.state_dict(),
            "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(),
            "np_rng": self.np_rng.bit_generator.state, "order": list(self.order),
            "history": self.history, "budget": self.budget, "growth_frozen": self.growth_frozen,
            "sh_degree": self.sh_degree, "sh_state": self.sh_state, "best_psnr": self.best_psnr,
            "since_best": self.since_best, "reset_done": self.reset_done, "done_reason": self.done_reason,
        }

    def load_state_dict(self, s: dict) -> None:
        self.step, self.elapsed = s["step"], s["elapsed"]
        self.params = {n: torch.nn.Parameter(v.to(self.device)) for n, v in s["params"].items()}
        self.optimizer = self._make_optimizer()
        fused = [g.get("fused") for g in self.optimizer.param_groups]
        self.optimizer.load_state_dict(s["optimizer"])
        for g, f in zip(self.optimizer.param_groups, fused):  # the saved flags are the old run's
            g["fused"] = f
            if f:
                g["foreach"] = None
        self.stats = density.GradientStats(**s["stats"])
        self.gen.set_state(s["gen"])
        torch.set_rng_state(s["torch_rng"])
        self.np_rng.bit_generator.state = s["np_rng"]
        self.order = list(s["order"])
        self.history = list(s["history"])
        self.budget, self.growth_frozen = s["budget"], s["growth_frozen"]
        self.sh_degree, self.sh_state = s["sh_degree"], s["sh_state"]
        self.best_psnr, self.since_best = s["best_psnr"], s["since_best"]
        self.reset_done = s["reset_done"]
        # limits are checked again against this run's settings (a resume may raise them)
        self.done_reason = None if s["done_reason"] in ("iteration limit", "time limit") else s["done_reason"]


def resolve_image_dir(scene_dir: Path, images) -> Path:
    """An image folder given absolute, relative to the working directory, or by its name
    inside the scene folder (``clean``)."""
    p = Path(images)
    if p.is_absolute() or (p.is_dir() and not (scene_dir / p).is_dir()):
        return p
    return scene_dir / p


def default_gt_dir(scene_dir: str | Path) -> Optional[Path]:
    """The survey's ground-truth folder (``clean/``, as tools/make_survey.py writes) if any."""
    d = Path(scene_dir) / "clean"
    return d if d.is_dir() else None


def make_trainer(scene_dir: str | Path, cfg: TrainConfig, images: Optional[str | Path] = None,
                 gaussians: Optional[GaussianSet] = None, gt_images: Optional[str | Path] = None) -> Trainer:
    """Load a survey and build the trainer of ``cfg.mode``; all input checks happen here,
    before any work. ``gt_images``: a folder of ground-truth images with the same names, for
    scoring (required by ``oracle``, which trains on them)."""
    cfg.validate()
    scene_dir = Path(scene_dir)
    image_dir = None
    if cfg.mode == "oracle":
        if gt_images is None:
            raise RecGSError(f"{scene_dir}: mode oracle trains on ground-truth images, but there is no "
                             "clean/ folder (pass --gt-images DIR)")
        images = gt_images
    if images is not None:
        image_dir = resolve_image_dir(scene_dir, images)
        if image_dir.is_dir() and not any(image_dir.iterdir()):
            raise RecGSError(f"{image_dir}: image folder is empty")
    elif (scene_dir / "images").is_dir() and not any((scene_dir / "images").iterdir()):
        raise RecGSError(f"{scene_dir / 'images'}: image folder is empty")
    scene = load_scene(scene_dir, image_dir=image_dir)
    gt_scene = load_scene(scene_dir, image_dir=resolve_image_dir(scene_dir, gt_images)) if gt_images is not None else None
    data = TrainData(scene, cfg.downscale, cfg.holdout_every, cfg.device, gt_scene=gt_scene)
    if cfg.mode in ("recgs", "filter2d", "joint"):
        from .recgs import CausticTrainer

        return CausticTrainer(data, cfg, gaussians)
    return Trainer(data, cfg, gaussians)
