"""What a run will need, said before it starts: :func:`plan_run` measures a short warm-up
(forward and backward passes at the training resolution that change nothing) and estimates
the run's peak memory from what is loaded now and what grows with the model, so a job can
print its resolution, image count, memory and time per 1,000 steps, and refuse a run that
would not fit instead of being killed by the system halfway.

The estimate (bytes)::

    peak = now + PIXEL_BYTES * largest training image + method state
           + GAUSSIAN_BYTES_PER_FLOAT * floats per Gaussian * (budget - Gaussians now)

``now`` is the process's resident memory once every image is decoded (the photos kept
compact, the model at its start); the constants were measured on the numba path (CPU, resident
memory around training steps at 1280x960 and 1600x1200, 20k to 600k Gaussians; each constant
says what it came to), and benchmarks/bench_survey_size.py prints the plan's estimate beside
the measured peak of whole runs.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Optional

import torch

from ..errors import RecGSError
from ..model.gaussians import num_sh_coeffs
from .coverage import sparse_coverage

#: Working memory of one training step per pixel of its image (the rasterizer's per-pixel
#: buffers, the loss and SSIM maps, their gradients): 290-300 B measured at 1280x960 and
#: 1600x1200 with 20k Gaussians; rounded up.
PIXEL_BYTES = 320
#: Memory per float of a Gaussian's parameters over a run: the parameter, its gradient, Adam's
#: two moments, the kept best model, the step's gathered rows and projection: 31 B measured
#: (1.83 KB a Gaussian at SH degree 3, 20k to 600k Gaussians at 1600x1200); rounded up.
GAUSSIAN_BYTES_PER_FLOAT = 34
#: Share of the available memory a run may plan to use (the rest: the system, the viewer,
#: allocator slack).
USABLE_SHARE = 0.85


def floats_per_gaussian(sh_degree: int) -> int:
    """Parameters of one Gaussian: mean 3, log-scale 3, rotation 4, opacity 1, SH 3 per coefficient."""
    return 11 + 3 * num_sh_coeffs(sh_degree)


def gaussian_bytes(sh_degree: int) -> int:
    return GAUSSIAN_BYTES_PER_FLOAT * floats_per_gaussian(sh_degree)


def resident_bytes() -> Optional[int]:
    """This process's resident memory now, where the platform says (Linux), else None."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def peak_resident_bytes() -> Optional[int]:
    """The most resident memory this process has held so far, where the platform says (Linux,
    macOS), else None."""
    try:
        import resource
    except ImportError:   # Windows
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)


def available_bytes(device: str = "cpu") -> Optional[int]:
    """Memory a run can still take: on a CUDA device its free memory; on the CPU the system's
    available memory (``MemAvailable``), within a container's limit (cgroup v2 or v1) where
    one is set. None where the platform does not say."""
    if str(device).startswith("cuda") and torch.cuda.is_available():
        free, _total = torch.cuda.mem_get_info(torch.device(device))
        return int(free)
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None and sys.platform == "darwin":
        try:
            avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            avail = None
    if avail is None and sys.platform == "win32":
        avail = _windows_available()
    limit = _cgroup_room()
    if limit is not None:
        avail = limit if avail is None else min(avail, limit)
    return avail


def _cgroup_room() -> Optional[int]:
    """A container's memory limit less what it uses now (cgroup v2, then v1), or None."""
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(limit_file) as f:
                text = f.read().strip()
            if text == "max":
                return None
            limit = int(text)
            if limit >= 1 << 60:   # v1's "no limit"
                return None
            with open(usage_file) as f:
                return max(0, limit - int(f.read().strip()))
        except (OSError, ValueError):
            continue
    return None


def _windows_available() -> Optional[int]:  # pragma: no cover - Windows only
    import ctypes

    class MemoryStatus(ctypes.Structure):
        _fields_ = [("dwLength", ctypes.c_ulong), ("dwMemoryLoad", ctypes.c_ulong),
                    ("ullTotalPhys", ctypes.c_ulonglong), ("ullAvailPhys", ctypes.c_ulonglong),
                    ("ullTotalPageFile", ctypes.c_ulonglong), ("ullAvailPageFile", ctypes.c_ulonglong),
                    ("ullTotalVirtual", ctypes.c_ulonglong), ("ullAvailVirtual", ctypes.c_ulonglong),
                    ("ullAvailExtendedVirtual", ctypes.c_ulonglong)]

    st = MemoryStatus()
    st.dwLength = ctypes.sizeof(MemoryStatus)
    if not ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(st)):
        return None
    return int(st.ullAvailPhys)


@dataclass
class RunPlan:
    """What a run will take, before it starts (every size in bytes)."""

    width: int                      # the largest training image
    height: int
    photo_width: int                # its photo's own size
    photo_height: int
    train_views: int
    test_views: int
    gaussians: int                  # now
    budget: Optional[int]           # the most the model may grow to (None: no bound)
    image_bytes: int                # decoded images, as kept
    method_bytes: int               # a caustic method's per-view state at its largest
    peak_bytes: int                 # the estimate, with the model at its budget
    available_bytes: Optional[int]  # memory a run may take (None: unknown)
    seconds_per_1000: Optional[float]   # measured at the start's model size
    path: str = "eager"             # the rasterizer path the warm-up ran on
    budget_capped_from: Optional[int] = None   # the budget memory allowed, if lower than asked
    views_per_point: Optional[float] = None    # median training views per sparse point (coverage.py)
    passes_per_point: Optional[float] = None   # ... and independent passes (frames close in time: one)
    looks_per_point: Optional[float] = None    # ... and independent looks at the light (coverage.looks_of)
    notes: list = field(default_factory=list)
    start_bytes: Optional[int] = None   # the estimate with the model at its size now
    work_seconds: Optional[float] = None   # a caustic method's work besides training (its estimate)
    work_bytes: Optional[int] = None       # ... and its peak memory beside the model at its start
    work_megapixels: Optional[float] = None   # ... over this many megapixels of frames
    work_looks: int = 0                    # ... of which look frames (a video's frames between the keyframes)
    work_given_up: Optional[str] = None    # why that work will not be done (it does not fit)
    work_scale: int = 1                    # ... done on frames of 1 / this of the training size
    fitted: Optional[dict] = None          # the training size lowered to fit the time limit (from what, why)

    def summary(self) -> dict:
        return asdict(self)

    def keep_work(self, given_up: Optional[str], work=None, scale: int = 1) -> None:
        """The caustic work the plan holds is done (``given_up`` None: its memory, beside the
        model at its start, counts in the peak: it runs early in the run), as ``work`` (its
        cost as the method will do it, on frames of 1 / ``scale`` the training size), or not
        (why)."""
        if given_up is not None:
            self.work_given_up = given_up
            return
        if work is not None:
            self.work_seconds, self.work_bytes, self.work_megapixels = work.seconds, work.bytes, work.megapixels
            self.work_looks = getattr(work, "looks", 0)
            self.work_scale = scale
        if self.work_bytes is not None:
            self.peak_bytes = max(self.peak_bytes, (self.start_bytes or 0) + self.work_bytes)

    def lines(self) -> list[str]:
        """The plan in words, for the job's log and the panel."""
        gb = lambda b: f"{b / 2 ** 30:.1f} GB"  # noqa: E731
        res = f"{self.width}x{self.height}"
        if (self.photo_width, self.photo_height) != (self.width, self.height):
            res += f" (photos {self.photo_width}x{self.photo_height})"
        out = [f"training at {res}: {self.train_views} training and {self.test_views} held-out views, "
               f"images {gb(self.image_bytes)} in memory"]
        if self.start_bytes is not None and self.budget is not None and self.budget > self.gaussians:
            mem = (f"memory: about {gb(self.start_bytes)} to start, at most {gb(self.peak_bytes)} if the model "
                   f"grows to {self.budget:,} Gaussians")
        else:
            mem = f"memory: about {gb(self.peak_bytes)} at the peak"
        if self.available_bytes is not None:
            mem += f" ({gb(self.available_bytes)} available)"
        out.append(mem)
        if self.views_per_point is not None:
            out.append(f"coverage: each seabed point in a median of {self.views_per_point:g} training views "
                       f"({self.passes_per_point:g} passes"
                       + (f", {self.looks_per_point:.1f} independent looks at the light)" if self.looks_per_point else ")"))
        if self.seconds_per_1000 is not None:
            out.append(f"time: about {self.seconds_per_1000:.0f} s per 1,000 steps now ({self.gaussians:,} "
                       f"Gaussians, {self.path} path); steps slow down as the model grows")
        if self.work_given_up is not None:
            out.append(f"caustic work: not done: {self.work_given_up}")
        elif self.work_seconds is not None:
            out.append(f"caustic work: about {self.work_seconds:.0f} s and {gb(self.work_bytes)} of memory "
                       f"({self.work_megapixels:.1f} megapixels of frames"
                       + (f", {self.work_looks} of them look frames" if self.work_looks else "")
                       + (f", at 1/{self.work_scale} of the training size to fit the time limit)" if self.work_scale > 1
                          else ")"))
        out.extend(self.notes)
        return out


def estimate_peak(now: int, pixels: int, method_bytes: int, sh_degree: int, gaussians: int,
                  budget: Optional[int]) -> int:
    """The peak estimate of the module docstring (bytes)."""
    model = gaussian_bytes(sh_degree) * max(budget or gaussians, gaussians)
    held = 4 * floats_per_gaussian(sh_degree) * gaussians   # the parameters, already in ``now``
    return int(now + PIXEL_BYTES * pixels + method_bytes + model - held)


def survey_bytes(data, sh_degree: int, budget: Optional[int]) -> int:
    """What one job on ``data`` would hold at its largest, before its photos are read: the
    photos kept as 8-bit at the training size (3 bytes a pixel, a quarter more for the coarse
    level), one step's buffers at the largest view and the model at ``budget`` Gaussians (what
    ``--blocks auto`` weighs against the memory there is)."""
    ids = data.train_ids + data.test_ids
    pixels = data.training_pixels(ids)
    largest = max((data.sizes[i][0] * data.sizes[i][1] for i in ids), default=0)
    return int(3 * 1.25 * pixels + PIXEL_BYTES * largest + gaussian_bytes(sh_degree) * (budget or 0))


def plan_run(trainer, method_bytes: int = 0, limit_bytes: Optional[int] = None, warmup_steps: int = 3,
             caustics: bool = False, work=None) -> RunPlan:
    """Measure and estimate what ``trainer``'s run needs (its images loaded), cap an automatic
    budget to the memory there is, and refuse (:class:`RecGSError`) a run that cannot fit.

    ``limit_bytes``: memory the run may take (default: what :func:`available_bytes` finds
    plus what this process holds already, times :data:`USABLE_SHARE`). ``method_bytes``: a
    caustic method's per-view state at its largest. ``warmup_steps``: forward and backward
    passes timed on training views at the training resolution (the model does not change).
    ``caustics``: the run removes caustics (the plan then says where the survey's coverage is
    short of what that needs). ``work``: a caustic method's work besides training, with its
    ``seconds``, ``bytes`` and ``megapixels`` (``core/caustics/cost.py``): shown; whether it fits
    is the method's to decide (``Method.fit_work``), and :meth:`RunPlan.keep_work` counts it in
    the peak."""
    data, cfg = trainer.data, trainer.cfg
    big = max(data.train_ids + data.test_ids, key=lambda i: data.sizes[i][0] * data.sizes[i][1])
    w, h = data.sizes[big]
    cam = data.scene.cameras[big]
    n = int(trainer.params["means"].shape[0])
    held = resident_bytes() or 0
    if limit_bytes is None:
        avail = available_bytes(cfg.device)
        if avail is not None:
            on_gpu = str(cfg.device).startswith("cuda")
            limit_bytes = int(USABLE_SHARE * (avail + (0 if on_gpu else held)))
    now = held if not str(cfg.device).startswith("cuda") else int(torch.cuda.memory_allocated(cfg.device))
    degree = cfg.sh_degree
    peak = estimate_peak(now, w * h, method_bytes, degree, n, trainer.budget)
    fixed = estimate_peak(now, w * h, method_bytes, degree, n, n)   # the model as it is now
    plan = RunPlan(w, h, cam.width, cam.height, len(data.train_ids), len(data.test_ids), n, trainer.budget,
                   data.image_bytes(), method_bytes, peak, limit_bytes, None, start_bytes=fixed)
    if work is not None:
        plan.work_seconds, plan.work_bytes, plan.work_megapixels = work.seconds, work.bytes, work.megapixels
    if limit_bytes is not None and peak > limit_bytes:
        room = int((limit_bytes - fixed) / gaussian_bytes(degree))
        gb = lambda b: f"{b / 2 ** 30:.1f} GB"  # noqa: E731
        if cfg.budget is None and room >= max(n, 1):
            # an automatic budget: grow only as far as memory allows
            plan.budget_capped_from = trainer.budget
            trainer.budget = room
            plan.budget = room
            plan.peak_bytes = estimate_peak(now, w * h, method_bytes, degree, n, room)
            plan.notes.append(f"the model is capped at {room:,} Gaussians to fit in memory "
                              f"(the automatic budget was {plan.budget_capped_from:,})")
        elif room >= max(n, 1):   # the model the user asked for does not fit; a smaller one would
            raise RecGSError(
                f"{data.scene.image_dir}: a model of {cfg.budget:,} Gaussians needs about {gb(peak)} of memory here "
                f"and {gb(limit_bytes)} is available; ask for at most {room:,} (--budget) or train at a lower "
                f"resolution (--max-side, now {cfg.max_side or 'off'})")
        else:
            raise RecGSError(
                f"{data.scene.image_dir}: {len(data.train_ids) + len(data.test_ids)} images at {w}x{h} need about "
                f"{gb(fixed)} of memory before the model grows and {gb(limit_bytes)} is available; train at a "
                f"lower resolution (--max-side, now {cfg.max_side or 'off'}) or on fewer photos")
    cov = sparse_coverage(data)
    if cov.points:
        plan.views_per_point, plan.passes_per_point = cov.median_views, cov.median_passes
        plan.looks_per_point = cov.median_looks
        if caustics and cov.median_looks < MIN_PASSES:
            plan.notes.append(coverage_advice(cov.median_views, cov.median_looks))
    plan.seconds_per_1000, plan.path = time_steps(trainer, warmup_steps)
    return plan


#: Independent views of a seabed point below which caustic removal cannot tell the light from
#: the seabed well (benchmarks/RESULTS.md#caustics-pointwise-bound: with 3 views the best
#: per-point estimate keeps half of one photo's light error, with 8 a seventh).
MIN_PASSES = 6


def coverage_advice(views: float, looks: float) -> str:
    """What to tell a user whose survey sees each point too few times for caustic removal."""
    return (f"caustic removal needs each seabed point in about {MIN_PASSES} or more independent looks at the "
            f"light (photos, or video frames whose light had time to change); this survey has a median of {looks:.1f} "
            f"({views:g} views). Photograph with more overlap (80 % forward, 60 % side) or keep more frames "
            "of a video; expect caustics to stay partly in the model")


#: The plan's step timing stops once the timed passes add up to this many seconds.
TIMING_SECONDS = 2.0


def time_steps(trainer, steps: int) -> tuple[Optional[float], str]:
    """Seconds per 1,000 training steps at the training resolution with the model as it is,
    timed over ``steps`` forward and backward passes (fewer once they add up to
    :data:`TIMING_SECONDS`) after one untimed pass (gradients dropped, so nothing changes), and
    the path they ran on."""
    from .trainer import PARAM_NAMES

    if steps < 1:
        return None, str(trainer.compiler.compiled())
    ids = trainer.data.train_ids
    times = []
    path = "eager"
    for k in range(steps + 1):
        t0 = time.perf_counter()
        path = trainer.dry_step(ids[k % len(ids)])
        if k:
            times.append(time.perf_counter() - t0)
            if sum(times) >= TIMING_SECONDS:   # slow steps: one or two tell enough
                break
    for name in PARAM_NAMES:
        trainer.params[name].grad = None
    return 1000 * float(sorted(times)[len(times) // 2]), "numba" if path == "numba" else (
        "compiled" if path is True else "eager")
