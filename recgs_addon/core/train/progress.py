"""Progress reports and the run's clock: elapsed time as the time limit counts it, the
reserve kept for the renders after training, the schedule's time and the ETA.

:class:`ProgressMixin` is a part of :class:`~.trainer.Trainer` (its ``cfg``, ``elapsed``,
``step`` and ``label``)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Optional


#: The most of a time limit kept for what follows training.
FINISH_SHARE = 0.4
#: Near the end of a time limit (within this many reserves of it) a render timed this many
#: steps ago or more is timed again before the reserve decides: the model the run starts from
#: renders several times slower than the trained one (its Gaussians are large: 0.81 s against
#: 0.23-0.29 s a 1371x733 view of a pool, whose job ended 36 s early on a 180-s limit), and a
#: growing model slower.
RETIME_NEAR = 1.5
RETIME_STEPS = 20


@dataclass
class Progress:
    phase: str
    iteration: int
    loss: float
    gaussians: int
    sh_degree: int
    elapsed: float
    eta: Optional[float]
    #: share of the run done, 0..1: by the ETA once steps are timed, before that by the time limit
    fraction: float = 0.0
    psnr_test: Optional[float] = None
    ssim_test: Optional[float] = None
    psnr_test_gt: Optional[float] = None   # against the survey's ground truth, where it has one
    extra: dict = field(default_factory=dict)  # what a method driving the trainer adds (flat)


class ProgressMixin:
    """The trainer's clock and progress reports (see the module's docstring)."""

    @property
    def time_limit_s(self) -> Optional[float]:
        """The run's time limit in seconds (None: none): the one place the config's minutes
        are read."""
        return None if self.cfg.max_minutes is None else 60.0 * self.cfg.max_minutes

    def finishing_estimate(self) -> Optional[float]:
        """Seconds what follows training will take: ``finishing_renders()`` at the latest render
        time measured (the job times one before the first step; held-out evaluations follow it)
        and ``finishing_writes()`` output images at ``write_s`` each (the job measures it); None
        before a render was timed."""
        if self._render_s is None:
            return None
        return self.finishing_renders() * self._render_s + self.finishing_writes() * self.write_s

    def finishing_reserve(self) -> float:
        """Seconds the time limit keeps for what follows training (:meth:`finishing_estimate`),
        at most :data:`FINISH_SHARE` of the limit. The whole job then ends near its limit,
        finishing included (the plan says where the finishing needs more)."""
        est = self.finishing_estimate()
        if est is None or self.time_limit_s is None:
            return 0.0
        return min(est, FINISH_SHARE * self.time_limit_s)

    def time_is_up(self) -> bool:
        """Whether the time limit, less the finishing's reserve (:meth:`finishing_reserve`), is
        reached at ``elapsed``. Near it (:data:`RETIME_NEAR` reserves) a render timed
        :data:`RETIME_STEPS` steps ago or more is timed again first, on the model as it is now
        (one held-out view, the time it takes counted), so that the reserve follows the model."""
        limit = self.time_limit_s
        if limit is None:
            return False
        reserve = self.finishing_reserve()
        if self.elapsed < limit - RETIME_NEAR * reserve:
            return False
        if self._render_s is not None and self.step - self._render_step >= RETIME_STEPS:
            t = time.perf_counter()
            self._render_s = None            # the new time replaces the old one
            self.render_output((self.data.test_ids or self.data.train_ids)[0])
            self.elapsed += time.perf_counter() - t
            reserve = self.finishing_reserve()
        return self.elapsed >= limit - reserve

    def start_clock(self, origin: Optional[float] = None) -> None:
        """Count the run's time from ``origin`` (a ``time.perf_counter()`` reading, default now;
        a job passes the moment its command started), on top of what a resumed run had spent.
        From then on every second counts against the time limit: training, and the renders,
        estimates and scores between training segments."""
        self._clock = (time.perf_counter() if origin is None else origin) - self.elapsed

    def schedule_elapsed(self) -> float:
        """Seconds of training as the schedule counts them: wall clock less the compiler's
        start-up stall (a time limit itself stays wall clock)."""
        return max(0.0, self.elapsed - self.compile_stall)

    def finish(self, on_progress: Optional[Callable[[Progress], None]] = None, **extra) -> None:
        """The last progress report of a run (phase ``done``)."""
        if on_progress:
            on_progress(self.progress(self._last_loss, {}, "done", **extra))

    @property
    def phase(self) -> str:
        if self.label is not None:
            return self.label
        return "densify" if self.densifying() else "refine"

    def progress(self, loss, metrics, phase=None, **extra) -> Progress:
        c = self.cfg
        eta = None
        if self.step:
            per = self.elapsed / self.step
            eta = per * (c.iterations - self.step)
            if self.time_limit_s is not None:
                eta = min(eta, max(0.0, self.time_limit_s - self.elapsed))
        if eta is not None and self.elapsed + eta > 0:
            fraction = self.elapsed / (self.elapsed + eta)
        elif self.time_limit_s is not None:
            fraction = self.elapsed / self.time_limit_s
        else:
            fraction = 0.0
        phase = phase or self.phase
        return Progress(phase, self.step, float(loss), int(self.params["means"].shape[0]), self.sh_degree,
                        round(self.elapsed, 2), None if eta is None else round(eta, 1),
                        round(min(1.0, fraction), 4), metrics.get("psnr"), metrics.get("ssim"),
                        metrics.get("psnr_gt"), extra)
