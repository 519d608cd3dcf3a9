"""The ``train`` command: the background job, ``python -m recgs_addon train ...`` (no Blender needed).

``train`` streams progress as JSON lines on stdout (one object per line, ``"event"`` first:
``start``, ``progress``, ``checkpoint``, ``done``, ``error``) and a human-readable line per
update on stderr, so the Blender add-on (or any program) can follow it. It writes, in OUT_DIR:

* ``checkpoint.pt``: the whole training state (model, Adam moments, random generators),
  written atomically every ``--checkpoint-every`` seconds, on SIGTERM/SIGINT and at the end;
* ``point_cloud.ply``: the current model in the INRIA layout, updated with each checkpoint
  (this is what a live preview reads);
* ``metrics.json``: held-out PSNR/SSIM, their history, time, Gaussian count, SH degree.

``--resume`` continues from ``checkpoint.pt``. A killed job loses at most the steps since the
last checkpoint; the files under their final names are always complete.
"""
from __future__ import annotations

import ctypes
import json
import math
import os
import sys
import time
from dataclasses import asdict, replace
from typing import Optional
from pathlib import Path

from ..core.caustics.config import CAUSTIC_MODES
from ..core.errors import RecGSError
from ..core.options.train import TRAIN_OPTIONS
from .events import StopSignals, _finite_tree, _json_default, emit, fail, finite


def add_train_arguments(p) -> None:
    """The ``train`` options, from their one declaration (core/options/train.py)."""
    TRAIN_OPTIONS.add_to(p)


def _peak_device_bytes(device) -> Optional[int]:
    """The most memory the run's GPU held (CUDA; None on the CPU and elsewhere)."""
    import torch

    if str(device).startswith("cuda") and torch.cuda.is_available():
        return int(torch.cuda.max_memory_allocated(device))
    return None


def _parse_budget(text: str):
    if text == "auto":
        return None
    try:
        return int(text)  # the range is checked by TrainConfig.validate
    except ValueError:
        raise RecGSError(f"--budget must be a number of Gaussians or 'auto', got {text!r}") from None


def _check_device(name: str) -> None:
    import torch

    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RecGSError(f"--device {name}: this torch has no CUDA device")
    if name == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise RecGSError("--device mps: this torch has no MPS device")


def _read_block(path):
    """``--block FILE``: one block of a split survey (commands/blocks.py writes it)."""
    if path is None:
        return None
    try:
        block = json.loads(Path(path).read_text())
        if not all(k in block for k in ("train", "test", "cell")):
            raise ValueError("it names no train, test and cell")
        return block
    except (OSError, ValueError) as exc:
        raise RecGSError(f"{path}: not a block of a split survey ({exc})") from None


def tune_allocator() -> str:
    """Keep freed memory in this process (glibc on Linux) instead of handing it back to the OS.

    A training step on a large model allocates and frees tensors of tens to hundreds of MB.
    glibc serves allocations above its mmap threshold (at most 32 MB) with fresh mappings and
    unmaps them on free, so every step faults in and zeroes new pages. On the vanilla run's
    1.56M-Gaussian model (benchmarks/bench_allocator.py, 2 threads): 76,844 page faults and
    0.648 s a step with glibc's defaults; with mmap off and trimming at 2 GB, 12,748 faults
    and 0.485 s (1.33x), peak memory 3142 MB instead of 3110, parameters identical. A job is
    a process of its own, so holding freed memory until it exits costs nothing else.
    ``RECGS_MALLOC=system`` keeps glibc's defaults. Returns what was done: ``"retained"`` or
    ``"system"``.
    """
    if os.environ.get("RECGS_MALLOC", "").lower() == "system" or not sys.platform.startswith("linux"):
        return "system"
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):   # not glibc (musl, ...): its defaults
        return "system"
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4
    ok = all([mallopt(M_MMAP_MAX, 0), mallopt(M_TRIM_THRESHOLD, 2 ** 31 - 1),
              mallopt(M_TOP_PAD, 256 << 20)])
    return "retained" if ok else "system"


def run_train(args) -> int:
    t_command = time.perf_counter()   # the time limit counts from here (Trainer.start_clock)
    import torch

    allocator = tune_allocator()

    from ..core.caustics.config import CausticConfig
    from ..core.io.ply import read_gaussian_ply
    from ..core.train.checkpoint import load_checkpoint
    from ..core.train.config import TrainConfig, preset
    from ..core.train.data import default_gt_dir

    torch.set_num_threads(max(1, torch.get_num_threads()))
    out: Path = args.out
    ckpt_path = out / "checkpoint.pt"
    try:
        if not 0 <= args.checkpoint_every < math.inf:   # NaN fails this too
            raise RecGSError(f"--checkpoint-every must be a number of seconds >= 0, got {args.checkpoint_every}")
        if out.exists() and not out.is_dir():
            raise RecGSError(f"{out}: is a file, not a folder (choose another output folder)")
        _check_device(args.device)
        state = None
        if args.resume:
            state = load_checkpoint(ckpt_path)
            cfg = TrainConfig.from_dict(state["config"])
            ccfg = CausticConfig.from_dict(state.get("caustic_config", state["config"]))
            if args.max_minutes is not None:
                cfg.max_minutes = args.max_minutes
            if args.iterations is not None:
                cfg.iterations = args.iterations
        else:
            cfg = preset(args.preset, iterations=args.iterations, max_minutes=args.max_minutes,
                         downscale=args.downscale, max_side=args.max_side, sh_degree=args.sh_degree, seed=args.seed,
                         device=args.device, holdout_every=args.holdout_every,
                         budget=_parse_budget(args.budget),
                         compiled=False if args.eager else (True if args.compile_first else None),
                         keep_best=False if args.keep_last else None,
                         strategy=args.density, prune_weight=args.prune_weight, medium=args.medium,
                         lamp=args.lamp, block=_read_block(args.block))
            caustic = dict(mode=args.mode, caustic_dc=None if args.caustic_dc is None else args.caustic_dc == "keep",
                           caustic_k=args.caustic_k, caustic_model=args.caustic_model, warmup=args.warmup,
                           recurrence_steps=args.recurrence_steps, max_recurrences=args.max_recurrences,
                           recurrence_tol=args.recurrence_tol, robust_k=args.robust_k,
                           estimator=args.estimator, caustics=args.caustics, fit_loss=args.fit_loss,
                           pass_statistic=args.pass_statistic, pass_min=args.pass_min, looks=args.looks,
                           gain_restore=None if args.gain_restore is None else args.gain_restore == "on")
            ccfg = CausticConfig(**{k: v for k, v in caustic.items() if v is not None})
        init = read_gaussian_ply(args.init_ply) if args.init_ply and not args.resume else None
        gt = args.gt_images if args.gt_images is not None else default_gt_dir(args.scene_dir)
        method, trainer = _build(args, cfg, ccfg, init, gt, state)
        fitted = _fitting_side(trainer) if state is None else None
        if fitted is not None:   # trained smaller, so that the outputs and scores fit the time limit
            trainer.compiler.close()
            cfg = replace(cfg, max_side=fitted["side"])
            method, trainer = _build(args, cfg, ccfg, init, gt, state)
            fitted["to"] = list(trainer.data.sizes[trainer.data.train_ids[0]])
        plan = _plan(args, method, trainer, fitted)
        trainer.start_clock(t_command)
    except RecGSError as exc:
        return fail(str(exc))

    from ..core.io.lock import folder_lock
    try:
        lock = folder_lock(out)
        lock.__enter__()
    except RecGSError as exc:
        trainer.compiler.close()
        return fail(str(exc))
    try:
        return _train_locked(args, out, ckpt_path, method, trainer, cfg, ccfg, state, allocator, plan, t_command)
    finally:
        lock.__exit__(None, None, None)


def _build(args, cfg, ccfg, init, gt, state):
    """The run's method and trainer at ``cfg``'s size, every image read, and what the finishing
    renders and writes counted for the time limit's reserve."""
    from ..core.caustics.build import make_method
    from ..core.train.water import DECIDE_VIEWS

    method = make_method(args.scene_dir, cfg, ccfg, images=args.images, gaussians=init, gt_images=gt)
    trainer = method.trainer
    if state is not None:
        method.load_state_dict(state)
    # every image the run uses is read now, so a file that does not decode stops the job
    # before it writes anything (training would read them all anyway; they stay cached)
    trainer.data.load_all(trainer.level(), on_image=_reading_progress(time.perf_counter()))
    # what _finish renders, in renders of a view at the training size: the held-out views
    # (outputs, final scores, once more to spare), every training view at most 400 px twice
    # (views per Gaussian: a render and its backward) and once more (coverage), with water or a
    # lamp every training view's range (its true-colour photo), and with water a few to decide on it
    n_train, n_test = len(trainer.data.train_ids), len(trainer.data.test_ids)
    small = small_render_share(trainer.data.sizes)
    trainer.finishing_renders = lambda: (3 * n_test + 3 * n_train * small + method.finishing_renders()
                                         + (n_train if trainer.forms_image else 0)
                                         + (DECIDE_VIEWS if trainer.medium is not None else 0))
    # and the images it writes: held-out renders, the method's, the true-colour photos
    trainer.finishing_writes = lambda: (2 * n_test + method.finishing_images()
                                        + (2 * n_train if trainer.forms_image else 0))
    return method, trainer


#: A render at most 400 px on the long side (the views per Gaussian, the coverage) costs at least
#: this share of one at the training size: what a render does per Gaussian does not shrink with
#: the pixels (measured on 30k Gaussians: 0.2 of a 1371x733 render at 400x214, 0.33 of a 686x367 one).
SMALL_RENDER_FLOOR = 0.2


def small_render_share(sizes) -> float:
    """What a render of the finishing's diagnostics (``COVERAGE_SIDE`` px at most) costs against
    one at the training size (the largest of ``sizes``): its share of the pixels, at least
    :data:`SMALL_RENDER_FLOOR`."""
    from ..core.train.coverage import COVERAGE_SIDE

    side = max(max(wh) for wh in sizes)
    level = max(1, -(-side // COVERAGE_SIDE))
    return min(1.0, max(1.0 / level ** 2, SMALL_RENDER_FLOOR))


#: Where the outputs and scores alone would take more than ``FINISH_SHARE`` of the time limit at
#: the training size, the job trains at a half or a quarter of its long side instead ...
FIT_FACTORS = (2, 4)
#: ... but no smaller than this (pixels, long side).
MIN_FIT_SIDE = 320


def _fitting_side(trainer) -> Optional[dict]:
    """The long side (``side``) to train at so that the finishing (its renders, timed on one view
    now; a render's time goes with its pixels) fits ``FINISH_SHARE`` of the time limit, and what
    it was fitted from; None where it fits as it is, there is no limit, or no smaller size helps.
    A job that trained its 42 steps at full size and ended 20 % late on a 3-minute limit trains
    its hundreds at half the size and ends on time: the finishing's renders and writes go with
    the pixels, and so do the steps."""
    from ..core.train.progress import FINISH_SHARE

    limit = trainer.time_limit_s
    if limit is None:
        return None
    trainer.render_output((trainer.data.test_ids or trainer.data.train_ids)[0])
    finish = trainer.finishing_estimate()
    if finish is None or finish <= FINISH_SHARE * limit:
        return None
    width, height = trainer.data.sizes[trainer.data.train_ids[0]]
    side = max(max(wh) for wh in trainer.data.sizes)
    factor = None
    for f in FIT_FACTORS:
        if side / f < MIN_FIT_SIDE:
            break
        factor = f
        if finish / f ** 2 <= FINISH_SHARE * limit:
            break
    if factor is None:
        return None
    return {"side": int(round(side / factor)), "from": [width, height], "finishing_seconds": round(finish, 1),
            "limit_seconds": limit}


def _write_seconds(out: Path, trainer) -> float:
    """Seconds one output image takes to write here: a training photo written as PNG and as
    EXR into ``out`` (then removed), the mean of the two, each timed at its second write (the
    first loads the format's libraries, once a process: on a fresh install it took long enough
    to reserve the limit's largest share). Writing is what the finishing does most of after
    rendering (five files a training view with the water and caustics)."""
    from ..core.io.images import write_image

    if not trainer.data.train_ids:
        return 0.0
    image = trainer.data.view(trainer.data.train_ids[0], 1)[1].cpu().numpy()
    spent = 0.0
    for ext in ("png", "exr"):
        probe = out / f".write-probe.{ext}"
        try:
            write_image(probe, image)
            t = time.perf_counter()
            write_image(probe, image)
            spent += time.perf_counter() - t
        finally:
            probe.unlink(missing_ok=True)
    return spent / 2


def _reading_progress(t0: float):
    """``on_image`` for ``TrainData.load_all``: a ``reading`` event every 5 % of the images, a
    line on stderr every 10 seconds and at the end."""
    said = [t0]

    def on_image(done: int, total: int) -> None:
        now = time.perf_counter()
        if done == total or done % max(1, total // 20) == 0:
            emit("reading", done=done, total=total, elapsed=round(now - t0, 2))
        if done == total or now - said[0] >= 10:
            said[0] = now
            print(f"read {done}/{total} images in {now - t0:.0f}s", file=sys.stderr, flush=True)
    return on_image


def _plan(args, method, trainer, fitted: Optional[dict] = None):
    """The run's plan (``core/train/plan.py``): emitted as a ``plan`` event and printed before
    any training; a run that cannot fit in memory is refused here (RecGSError). ``fitted``: the
    training size was lowered to fit the time limit (:func:`_fitting_side`), said first."""
    from ..core.train.plan import plan_run

    limit = None if args.max_memory is None else int(args.max_memory * 2 ** 30)
    if limit is not None and not limit > 0:
        raise RecGSError(f"--max-memory must be a number of gigabytes above 0, got {args.max_memory}")
    plan = plan_run(trainer, method.state_bytes(), limit,
                    caustics=method.ccfg.mode in CAUSTIC_MODES and not getattr(method, "dropped", False),
                    work=method.planned_work())
    # the caustic work within its share of the time limit and the memory training leaves
    room = None if plan.available_bytes is None else plan.available_bytes - (plan.start_bytes or plan.peak_bytes)
    plan.keep_work(method.fit_work(trainer.time_limit_s, room), method.planned_work(),
                   getattr(method, "pass_scale", 1))
    # one render timed now, so that the time limit keeps room for the finishing renders from the
    # first step (before, the first held-out evaluation measured it: a slow step's run went
    # without a reserve until then)
    if trainer.finishing_estimate() is None:   # no render timed yet (_fitting_side times one)
        trainer.render_output((trainer.data.test_ids or trainer.data.train_ids)[0])
    finish = trainer.finishing_estimate()
    limit_s = trainer.time_limit_s
    if fitted is not None:
        (w, h), (w2, h2) = fitted["from"], fitted["to"]
        plan.fitted = fitted
        plan.notes.append(f"size: at {w}x{h} the outputs and scores alone would take about "
                          f"{fitted['finishing_seconds']:.0f} s of the {fitted['limit_seconds']:.0f}-s limit: training "
                          f"at {w2}x{h2} instead, where they fit (a longer limit or fewer photos trains at {w}x{h})")
    if finish is not None and limit_s is not None:
        from ..core.train.progress import FINISH_SHARE
        line = f"finishing: about {finish:.0f} s of renders for the outputs and scores"
        if finish > FINISH_SHARE * limit_s:
            line += (f", more than {100 * FINISH_SHARE:.0f} % of the {limit_s:.0f}-s limit: the job will end about "
                     f"{finish - FINISH_SHARE * limit_s:.0f} s late; a limit of {finish / FINISH_SHARE / 60:.1f} minutes "
                     "or a lower resolution fits it")
        plan.notes.append(line)
    lines = plan.lines()
    if trainer.cfg.medium != "off":
        lines.append(f"water: {'modelled' if trainer.medium is not None else 'not modelled'} "
                     f"({trainer.medium_info['reason']})")
    overlay = trainer.data.overlay()
    if overlay.mask is not None:
        lines.append(f"overlay: {overlay.reason}")
    light = getattr(method, "light", None)
    if light is not None:
        lines.append(f"light: {light['reason']}" + ("" if light["caustics"] else "; training as plain 3DGS"))
    if trainer.cfg.lamp != "off":
        lines.append(f"lamp: {'modelled' if trainer.lamp is not None else 'not modelled'} "
                     f"({trainer.lamp_info['reason']})")
    if getattr(method, "estimator_why", None) and not getattr(method, "dropped", False):
        lines.append(f"caustic estimator: {method.ccfg.estimator} ({method.estimator_why})")
    emit("plan", lines=lines, **plan.summary())
    for line in lines:
        print(line, file=sys.stderr, flush=True)
    return plan


def _train_locked(args, out, ckpt_path, method, trainer, cfg, ccfg, state, allocator, plan, t_command) -> int:
    import torch

    from ..core.io.ply import write_gaussian_ply
    from ..core.train.checkpoint import save_checkpoint

    stop = StopSignals().install()
    trainer.write_s = _write_seconds(out, trainer)

    def checkpoint(tr) -> None:
        save_checkpoint(ckpt_path, method.state_dict())
        write_gaussian_ply(out / "point_cloud.ply", tr.gaussians())
        emit("checkpoint", path=str(ckpt_path), ply=str(out / "point_cloud.ply"), iteration=tr.step,
             gaussians=int(tr.params["means"].shape[0]))

    def on_progress(p) -> None:
        d = {k: finite(v) for k, v in {**asdict(p), **p.extra}.items() if k != "extra"}
        emit("progress", **d)
        msg = (f"[{p.phase}] it {p.iteration} loss {p.loss:.4f} gaussians {p.gaussians} "
               f"sh {p.sh_degree} {p.elapsed:.0f}s")
        if p.eta is not None:
            msg += f" (~{p.eta:.0f}s left)"
        if p.psnr_test is not None:
            msg += f" held-out PSNR {p.psnr_test:.2f} dB"
        print(msg, file=sys.stderr, flush=True)

    def on_compile(message: str) -> None:
        emit("compile", message=message, iteration=trainer.step)
        print(message, file=sys.stderr, flush=True)

    emit("start", scene=str(args.scene_dir), out=str(out), resumed=bool(state), iteration=trainer.step,
         train_views=len(trainer.data.train_ids), test_views=len(trainer.data.test_ids),
         gaussians=int(trainer.params["means"].shape[0]), allocator=allocator,
         threads={"torch": torch.get_num_threads(), "wait": os.environ.get("OMP_WAIT_POLICY", "")},
         config={**asdict(cfg), **asdict(ccfg)},
         plan=plan.summary())
    for message in trainer.compiler.messages:
        on_compile(message)
    trainer.compiler.log = on_compile
    try:
        reason = method.run(on_progress=on_progress, should_stop=stop,
                             on_checkpoint=checkpoint, checkpoint_every_s=args.checkpoint_every)
    except RecGSError as exc:  # bad input found during training (an image that does not decode)
        return fail(str(exc), detail=f"training stopped at iteration {trainer.step}; the last checkpoint is kept")
    except Exception as exc:  # keep the last checkpoint; report the error as an event too
        emit("error", message=f"training failed at iteration {trainer.step}: {exc!r}")
        raise
    finally:
        trainer.compiler.close()
        stop.restore()
    try:
        return _finish(args, out, ckpt_path, method, trainer, ccfg, reason, stop, checkpoint, plan, t_command)
    except RecGSError as exc:   # a full disk or an unwritable folder at the end: one line, the last checkpoint kept
        return fail(str(exc), detail=f"training ended at iteration {trainer.step}; the last checkpoint is kept")


def _finish(args, out, ckpt_path, method, trainer, ccfg, reason, stop, checkpoint, plan, t_command) -> int:
    """The end of a run: the last checkpoint, the output images, metrics and report."""
    from ..core.outputs.diagnostics import support_summary, view_support
    from ..core.train.coverage import COVERAGE_VIEWS, LIGHT_SECONDS, spread, surface_coverage
    from ..core.outputs.exports import write_outputs
    from ..core.outputs.report import write_run_report
    from ..core.train.plan import peak_resident_bytes

    t = [time.perf_counter()]
    parts: dict = {}

    def took(name: str) -> None:   # the finishing's parts, timed (metrics.json: finish_seconds)
        now = time.perf_counter()
        parts[name] = round(now - t[0], 2)
        t[0] = now
    if reason != "stopped":
        trainer.decide_medium()   # auto: the water is kept where it changes the photos measurably
    checkpoint(trainer)
    took("checkpoint")
    outputs = write_outputs(method, out)
    took("outputs")
    if reason == "stopped":
        emit("done", status="cancelled", reason=f"received {stop.received}", iteration=trainer.step,
             checkpoint=str(ckpt_path))
        print(f"stopped by {stop.received} at iteration {trainer.step}; checkpoint saved", file=sys.stderr)
        return 0
    final = trainer.evaluate()
    took("evaluation")
    support = support_summary(view_support(trainer))
    took("view_support")
    light_s = (getattr(method, "pass_info", None) or {}).get("light_seconds") or LIGHT_SECONDS   # measured, where it was
    coverage = surface_coverage(trainer, source_ids=spread(trainer.data.train_ids, COVERAGE_VIEWS),
                                light_seconds=light_s).summary()
    took("coverage")
    metrics = {
        "status": "done", "reason": reason, "iterations": trainer.step,
        "seconds": round(trainer.elapsed, 2), "job_seconds": round(time.perf_counter() - t_command, 2),
        "peak_resident_bytes": peak_resident_bytes(), "peak_device_bytes": _peak_device_bytes(trainer.device),
        "finish_seconds": parts,
        "reserve_seconds": round(trainer.finishing_reserve(), 2), "reserve_writes": trainer.finishing_writes(),
        "gaussians": int(trainer.params["means"].shape[0]),
        "sh_degree": trainer.sh_degree,
        "test_views": [trainer.data.scene.cameras[i].name for i in trainer.data.test_ids],
        "psnr_test": final.get("psnr"), "ssim_test": final.get("ssim"),
        "psnr_test_gt": final.get("psnr_gt"), "ssim_test_gt": final.get("ssim_gt"),
        "psnr_test_captured": final.get("psnr_captured"), "view_support": support, "coverage": coverage,
        "medium": trainer.medium_summary(), "lamp": trainer.lamp_summary(), "overlay": trainer.data.overlay().summary(),
        "coverage_sparse": {"median_views": plan.views_per_point, "median_passes": plan.passes_per_point},
        "plan": plan.summary(), **outputs,
        "compile": trainer.compiler.summary(), "skipped_steps": trainer.skipped_steps,
        "density": dict(trainer.density_totals),
        "history": trainer.history, "recurrences": [], "light": trainer.light, **method.summary(),
        "config": {**asdict(trainer.cfg), **asdict(ccfg)},
    }
    from ..core.io.atomic import atomic_path
    with atomic_path(out / "metrics.json", "metrics") as tmp:
        tmp.write_text(json.dumps(_finite_tree(metrics), indent=2, allow_nan=False, default=_json_default))
    report = write_run_report(out, metrics, method)
    emit("done", report=str(report),
         **{k: v for k, v in metrics.items() if k not in ("history", "config", "recurrences")})
    return 0
