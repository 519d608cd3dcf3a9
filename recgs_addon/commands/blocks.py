"""``train --blocks N``: a survey split into blocks over the seabed, each trained by the same
trainer as a task on Ray, merged into one scene (core/blocks).

Ray does the scheduling, the transport and the retries: with no address a local Ray on this
machine (its workers share the cores), with ``--cluster ADDRESS`` (or ``RAY_ADDRESS``) an
existing cluster, whose workers must reach OUT (a shared folder) and hold this package's
dependencies. A block is a task that runs ``train`` on its part of the survey in
``OUT/blocks/NAME`` (events in ``events.jsonl``, its log in ``log.txt``); a task whose
worker dies is retried by Ray and resumes from the block's last checkpoint. This process
follows the blocks' events and speaks the ``train`` command's protocol: ``plan``,
``progress`` (with each block's figures), ``checkpoint`` (the blocks merged so far, for the
live preview) and ``done``. SIGTERM/SIGINT stop every block after its checkpoint; ``--resume``
goes on with the same blocks.
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

from ..core.errors import RecGSError
from ..core.options.train import AUTO_BLOCKS, TRAIN_OPTIONS
from .events import StopSignals, _finite_tree, _json_default, emit, fail
from .train import _parse_budget, add_train_arguments, run_train

#: Options a block's ``train`` is not given as the job was (each block has its own).
_OWN = {"scene_dir", "out", "blocks", "cluster", "block", "block_threads", "resume", "init_ply", "max_minutes"}
#: Ray retries a block whose worker died this many times (each resumes from its checkpoint).
RETRIES = 3
#: Seconds between looks at the blocks' events.
POLL_S = 0.5


def train_command(args) -> int:
    """The ``train`` command: one job, or with ``--blocks N`` (N >= 2) the survey in blocks;
    ``--blocks auto`` chooses (:func:`auto_count`)."""
    if args.block is None and args.blocks == AUTO_BLOCKS:
        if args.resume and (Path(args.out) / "blocks" / "plan.json").is_file():
            args.blocks = 2   # the split already made
        else:
            try:
                n, why = auto_count(args)
            except RecGSError as exc:
                return fail(str(exc))
            print(f"--blocks auto: {why}", file=sys.stderr, flush=True)
            args.blocks = n if n > 1 else 0
    if args.blocks and args.blocks > 1 and args.block is None:
        return run_blocks(args)
    return run_train(args)


def auto_count(args) -> tuple[int, str]:
    """``--blocks auto``: one job where its planned memory fits on this machine, else the
    fewest blocks whose share does (core/blocks/split.py ``auto_blocks``)."""
    from ..core.blocks.split import auto_blocks
    from ..core.train.config import preset
    from ..core.train.plan import USABLE_SHARE, available_bytes, survey_bytes
    from ..core.train.trainer import auto_budget

    data = _survey_data(args)
    cfg = preset(args.preset)
    budget = _parse_budget(args.budget)
    if budget is None:
        budget = auto_budget(data, cfg)
    avail = available_bytes(cfg.device)
    return auto_blocks(data.scene, [data.scene.cameras[i].name for i in data.test_ids],
                       survey_bytes(data, cfg.sh_degree, budget), None if avail is None else int(USABLE_SHARE * avail))


def block_argv(args) -> list[str]:
    """The ``train`` options the job was given that every block is given too."""
    argv = []
    for opt in TRAIN_OPTIONS:
        if opt.dest in _OWN or not opt.flag.startswith("--"):
            continue
        value = getattr(args, opt.dest, None)
        if value is None or value is False or value == opt.default:
            continue
        if opt.dest in ("images", "gt_images") and Path(value).exists() \
                and not (Path(args.scene_dir) / value).is_dir():
            value = Path(value).resolve()   # a folder named from here: a worker starts elsewhere
        argv += [opt.flag] if value is True else [opt.flag, str(value)]
    return argv


def _threads(args, n_blocks: int, cores: int) -> int:
    if args.block_threads:
        return args.block_threads
    return max(1, cores // max(1, min(n_blocks, cores)))


def run_blocks(args) -> int:
    t0 = time.perf_counter()
    try:
        import ray
    except ImportError:
        from ..engine_install import RAY_REQUIREMENT

        return fail(f"--blocks runs the blocks on Ray, which is not installed: pip install '{RAY_REQUIREMENT}' into "
                    "the training Python (scripts/setup.sh --ray does)")
    from ..core.blocks.split import BlockPlan, check_split, plan_blocks
    from ..core.io.ply import read_gaussian_ply, write_gaussian_ply

    out: Path = args.out
    bdir = out / "blocks"
    plan_path = bdir / "plan.json"
    try:
        if out.exists() and not out.is_dir():
            raise RecGSError(f"{out}: is a file, not a folder (choose another output folder)")
        if args.resume:
            if not plan_path.is_file():
                raise RecGSError(f"{plan_path}: no blocks to resume")
            plan = BlockPlan.load(plan_path)
        else:
            data = _survey_data(args)   # the cameras, and the survey's held-out photos
            test = [data.scene.cameras[i].name for i in data.test_ids]
            plan = plan_blocks(data.scene, args.blocks, test)
            check_split(data.scene, plan, test, cluster=bool(args.cluster or os.environ.get("RAY_ADDRESS")))
            bdir.mkdir(parents=True, exist_ok=True)
            plan.save(plan_path)
            init = read_gaussian_ply(args.init_ply) if args.init_ply else None
            for b in plan.blocks:
                d = bdir / b.name
                d.mkdir(exist_ok=True)
                for stale in ("checkpoint.pt", "metrics.json", "events.jsonl", "log.txt"):
                    (d / stale).unlink(missing_ok=True)   # a new split starts every block afresh
                (d / "block.json").write_text(json.dumps(b.config()))
                if init is not None:   # the artist's edits: each block starts from its part of them
                    write_gaussian_ply(d / "init.ply", init.subset(b.grown.contains(init.means)))
    except RecGSError as exc:
        return fail(str(exc))
    (bdir / "STOP").unlink(missing_ok=True)

    address = args.cluster or os.environ.get("RAY_ADDRESS") or None
    package = Path(__file__).resolve().parents[1]
    try:
        if address:
            ray.init(address=address, runtime_env={"py_modules": [str(package)]}, log_to_driver=False,
                     logging_level="WARNING")
        else:
            ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, log_to_driver=False,
                     logging_level="WARNING", runtime_env={"env_vars": {"PYTHONPATH": str(package.parent)}})
    except Exception as exc:   # noqa: BLE001 - Ray's errors name the address and the cause
        return fail(f"Ray did not start{f' at {address}' if address else ''}: {exc}")
    try:
        cores = int(ray.cluster_resources().get("CPU", 1))
        threads = _threads(args, len(plan.blocks), cores)
        workers = max(1, min(len(plan.blocks), cores // threads))
        minutes = None
        if args.max_minutes is not None:
            minutes = block_minutes(args.max_minutes, time.perf_counter() - t0, len(plan.blocks), workers)
        lines = plan.lines() + [f"blocks run on Ray ({address or 'local'}): {workers} at a time, {threads} "
                                f"thread(s) each" + (f", {minutes:.2f} min each" if minutes else "")]
        emit("plan", lines=lines, blocks=[b.name for b in plan.blocks], workers=workers, threads=threads)
        for line in lines:
            print(line, file=sys.stderr, flush=True)
        common = block_argv(args)
        # a fresh worker for every block (max_calls=1): a job keeps the memory it frees
        # (train.tune_allocator), so a worker reused for a second block would start it with the
        # first one's memory held, and its plan would see too little left
        task = ray.remote(num_cpus=threads, max_retries=RETRIES, max_calls=1)(train_block)
        refs = {}
        for b in plan.blocks:
            d = bdir / b.name
            argv = ["train", str(Path(args.scene_dir).resolve()), "--out", str(d.resolve()),
                    "--block", str((d / "block.json").resolve()), *common]
            if (d / "init.ply").is_file():
                argv += ["--init-ply", str((d / "init.ply").resolve())]
            if minutes is not None:
                argv += ["--max-minutes", f"{minutes:.4f}"]
            refs[task.remote(argv, str(d.resolve()), threads, str((bdir / "STOP").resolve()))] = b.name
        results, stopped = _follow(ray, refs, plan, bdir, out, args.checkpoint_every, t0)
    finally:
        ray.shutdown()
    failed = {n: r for n, r in results.items() if r.get("rc") not in (0, None) or r.get("error")}
    if failed:
        name, r = next(iter(failed.items()))
        return fail(f"{bdir / name}: block {name} failed ({r.get('error') or 'exit status ' + str(r.get('rc'))}); "
                    f"see {bdir / name / 'log.txt'}; the other blocks' checkpoints are kept (--resume goes on)")
    try:
        return _finish(args, plan, bdir, out, results, stopped, t0)
    except RecGSError as exc:
        return fail(str(exc), detail="the blocks' checkpoints are kept")


#: Share of a time limit kept for merging the blocks, scoring the scene and writing its outputs.
MERGE_SHARE = 0.05


def block_minutes(max_minutes: float, spent_s: float, n_blocks: int, workers: int) -> float:
    """Each block's time limit: what the job has left (its limit less the ``spent_s`` seconds
    the split and Ray's start took, and :data:`MERGE_SHARE` for the merge), over the rounds of
    ``workers`` blocks at once that ``n_blocks`` take (a last round with fewer blocks counts
    whole: 3 blocks on 2 workers are two rounds)."""
    rounds = -(-n_blocks // max(1, workers))
    left_s = max(60.0 * max_minutes * (1 - MERGE_SHARE) - spent_s, 0.0)
    return max(left_s / rounds / 60.0, 0.05)


def _survey_data(args, gt_images=None):
    """The whole survey as one job would see it (its photos read only when asked for): its
    cameras, held-out photos and training sizes."""
    from ..core.train.config import preset
    from ..core.train.trainer import load_data

    cfg = preset(args.preset, downscale=args.downscale, max_side=args.max_side, holdout_every=args.holdout_every)
    return load_data(args.scene_dir, cfg, images=args.images, gt_images=gt_images)


def train_block(argv: list[str], out_dir: str, threads: int, stop_file: str) -> dict:
    """One block: ``train`` in this (Ray worker's) process, its events to ``events.jsonl`` and
    its log to ``log.txt`` in ``out_dir``; resumed from the block's checkpoint where there is one
    (a retry after the worker died), skipped where the block is done."""
    import contextlib

    import torch

    def cli_main(argv: list[str]) -> int:   # ``train ARGS`` as the command line runs it
        import argparse

        parser = argparse.ArgumentParser(prog="python -m recgs_addon train")
        add_train_arguments(parser)
        return run_train(parser.parse_args(argv[1:]))

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = out / "metrics.json"
    if metrics.is_file():
        try:
            if json.loads(metrics.read_text()).get("status") == "done":
                return {"rc": 0, "skipped": True, "pid": os.getpid()}
        except ValueError:
            pass
    resumed = (out / "checkpoint.pt").is_file()
    if resumed:
        argv = [*argv, "--resume"]
    os.environ["RECGS_STOP_FILE"] = stop_file
    torch.set_num_threads(threads)
    (out / "worker.pid").write_text(str(os.getpid()))
    with open(out / "events.jsonl", "a") as ev, open(out / "log.txt", "a") as log, \
            contextlib.redirect_stdout(ev), contextlib.redirect_stderr(log):
        try:
            rc = cli_main(argv)
        except SystemExit as exc:    # argparse's refusals
            rc = exc.code if isinstance(exc.code, int) else 2
        except Exception as exc:   # noqa: BLE001 - the block's own error, for the job's message
            print(f"error: {exc!r}", file=sys.stderr)
            return {"rc": 1, "error": repr(exc), "pid": os.getpid(), "resumed": resumed}
    from ..core.train.plan import peak_resident_bytes
    return {"rc": rc, "pid": os.getpid(), "resumed": resumed, "peak_rss": peak_resident_bytes()}


class _BlockEvents:
    """What one block's ``events.jsonl`` says so far (read as it grows)."""

    def __init__(self, path: Path):
        self.path, self.offset = path, 0
        self.last: dict = {}
        self.starts = 0
        self.checkpoints = 0
        self.done: dict = {}

    def read(self) -> None:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except OSError:
            return
        end = data.rfind(b"\n") + 1   # a line still being written waits for the next look
        self.offset += end
        for line in data[:end].splitlines():
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            kind = ev.get("event")
            if kind == "progress":
                self.last = ev
            elif kind == "start":
                self.starts += 1
            elif kind == "checkpoint":
                self.checkpoints += 1
            elif kind == "done":
                self.done = ev


def _follow(ray, refs: dict, plan, bdir: Path, out: Path, checkpoint_every: float, t0: float):
    """Wait for the blocks, emitting their progress and, every ``checkpoint_every`` seconds when
    a block has checkpointed, the blocks merged so far (the live preview)."""
    stop = StopSignals().install()
    events = {b.name: _BlockEvents(bdir / b.name / "events.jsonl") for b in plan.blocks}
    results: dict = {}
    pending = list(refs)
    merged_at, seen_ckpts, said = time.perf_counter(), 0, 0.0
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=len(pending), timeout=POLL_S)
            for ref in ready:
                name = refs[ref]
                try:
                    results[name] = ray.get(ref)
                except Exception as exc:   # noqa: BLE001 - retries spent: the block failed
                    results[name] = {"rc": 1, "error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
            if stop() and not (bdir / "STOP").exists():
                (bdir / "STOP").write_text(str(stop.received))
            for e in events.values():
                e.read()
            now = time.perf_counter()
            ckpts = sum(e.checkpoints for e in events.values())
            if ckpts > seen_ckpts and now - merged_at >= checkpoint_every:
                seen_ckpts, merged_at = ckpts, now
                _preview(plan, bdir, out, sum(int(e.last.get("iteration") or 0) for e in events.values()))
            if now - said >= 1.0 or not pending:
                said = now
                _progress(plan, events, results, now - t0)
    finally:
        stop.restore()
    for name, e in events.items():
        e.read()
        results.setdefault(name, {})["starts"] = e.starts
        results[name]["done"] = e.done
        results[name]["iteration"] = int(e.last.get("iteration") or 0)
    return results, stop.received


def _progress(plan, events: dict, results: dict, elapsed: float) -> None:
    blocks = []
    for b in plan.blocks:
        p = events[b.name].last
        blocks.append({"block": b.name, "iteration": p.get("iteration", 0), "gaussians": p.get("gaussians"),
                       "psnr_test": p.get("psnr_test"), "eta": p.get("eta"), "done": b.name in results})
    etas = [x["eta"] for x in blocks if x["eta"] is not None and not x["done"]]
    done = sum(x["done"] for x in blocks)
    fraction = sum(1.0 if b.name in results else float(events[b.name].last.get("fraction") or 0.0)
                   for b in plan.blocks) / len(plan.blocks)
    emit("progress", phase=f"blocks {done}/{len(blocks)} done", iteration=sum(x["iteration"] for x in blocks),
         gaussians=sum(x["gaussians"] or 0 for x in blocks), elapsed=round(elapsed, 2),
         eta=max(etas) if etas else None, fraction=round(fraction, 4), loss=None, sh_degree=None, psnr_test=None,
         blocks=blocks)
    print(f"[blocks] {done}/{len(blocks)} done; " + ", ".join(
        f"{x['block']} it {x['iteration']}" for x in blocks) + f" {elapsed:.0f}s", file=sys.stderr, flush=True)


def _merged(plan, bdir: Path):
    """(the blocks' Gaussians merged, how many each kept, the blocks that had a model)."""
    from ..core.blocks.merge import merge_gaussians
    from ..core.io.ply import read_gaussian_ply

    parts, names = [], []
    for b in plan.blocks:
        ply = bdir / b.name / "point_cloud.ply"
        if ply.is_file():
            parts.append((read_gaussian_ply(ply), b.cell))
            names.append(b.name)
    g, kept = merge_gaussians(parts)
    return g, dict(zip(names, kept))


def _preview(plan, bdir: Path, out: Path, iteration: int) -> None:
    from ..core.io.ply import write_gaussian_ply

    try:
        g, _ = _merged(plan, bdir)
        write_gaussian_ply(out / "point_cloud.ply", g)
    except (RecGSError, OSError):   # a block's PLY between writes: the next look tries again
        return
    emit("checkpoint", ply=str(out / "point_cloud.ply"), gaussians=len(g), iteration=iteration)


def _finish(args, plan, bdir: Path, out: Path, results: dict, stopped, t0: float) -> int:
    from ..core.blocks.merge import score_views, summarise
    from ..core.io.atomic import atomic_path
    from ..core.io.ply import write_gaussian_ply
    from ..core.train.data import default_gt_dir

    g, kept = _merged(plan, bdir)
    write_gaussian_ply(out / "point_cloud.ply", g)
    emit("checkpoint", ply=str(out / "point_cloud.ply"), gaussians=len(g),
         iteration=sum(r.get("iteration", 0) for r in results.values()))
    if stopped:
        emit("done", status="cancelled", reason=f"received {stopped}", gaussians=len(g),
             checkpoint=str(bdir))
        print(f"stopped by {stopped}; every block's checkpoint saved (--resume goes on)", file=sys.stderr)
        return 0
    data = _survey_data(args, args.gt_images if args.gt_images is not None else default_gt_dir(args.scene_dir))
    seam_images: dict = {}
    scores = score_views(g, data, data.test_ids, set(plan.seam_views), keep=seam_images)
    summary = summarise(scores)
    figures = _seam_figures(out, scores, seam_images)
    blocks = []
    for b in plan.blocks:
        m = {}
        try:
            m = json.loads((bdir / b.name / "metrics.json").read_text())
        except (OSError, ValueError):
            pass
        r = results.get(b.name, {})
        blocks.append({"block": b.name, "photos": len(b.train), "held_out": len(b.test), "kept": kept.get(b.name, 0),
                       "gaussians": m.get("gaussians"), "iterations": m.get("iterations"),
                       "seconds": m.get("seconds"), "psnr_test": m.get("psnr_test"),
                       "psnr_test_gt": m.get("psnr_test_gt"), "water": bool((m.get("medium") or {}).get("kept")),
                       "attenuation": ((m.get("medium") or {}).get("coefficients") or {}).get("attenuation"),
                       "lamp": bool((m.get("lamp") or {}).get("kept")),
                       "caustics": (m.get("light") or {}).get("caustics"),
                       "peak_rss_mb": round(r["peak_rss"] / 2 ** 20) if r.get("peak_rss") else None,
                       "starts": r.get("starts"), "resumed": bool(r.get("starts", 0) > 1 or r.get("resumed"))})
    copied = _collect_images(plan, bdir, out)
    metrics = {"status": "done", "reason": "blocks done", "blocks": blocks, "grid": list(plan.grid),
               "margin": plan.margin, "gaussians": len(g), "sh_degree": g.sh_degree,
               "iterations": sum(b["iterations"] or 0 for b in blocks),
               "job_seconds": round(time.perf_counter() - t0, 2),
               "psnr_test": summary["psnr"], "psnr_test_gt": summary["psnr_gt"], "scores": summary,
               "views": [asdict(s) for s in scores], "images": copied, "seam_figures": figures,
               "test_views": [data.scene.cameras[i].name for i in data.test_ids]}
    with atomic_path(out / "metrics.json", "metrics") as tmp:
        tmp.write_text(json.dumps(_finite_tree(metrics), indent=2, allow_nan=False, default=_json_default))
    report = _report(out, plan, metrics)
    emit("done", report=str(report), **{k: v for k, v in metrics.items() if k not in ("views",)})
    return 0


#: Held-out photos crossing a seam shown in the report (the worst-scored first).
SEAM_FIGURES = 4


def _seam_figures(out: Path, scores, images: dict) -> list[str]:
    """The merged scene's render beside the photo for the seam-crossing held-out views that
    scored worst, as ``OUT/report/seam_NAME.png``; their paths relative to OUT."""
    from ..core.io.images import write_image

    worst = sorted((s for s in scores if s.name in images), key=lambda s: s.psnr)[:SEAM_FIGURES]
    paths = []
    for s in worst:
        rel = f"report/seam_{Path(s.name).stem}.png"
        (out / "report").mkdir(parents=True, exist_ok=True)
        write_image(out / rel, images[s.name])
        paths.append(rel)
    return paths


def _collect_images(plan, bdir: Path, out: Path) -> dict:
    """Each photo's caustic-free (and true-colour) image from the block whose cell holds its
    footprint's centre, into ``OUT/decaustic`` (``OUT/truecolour``)."""
    import shutil

    copied = {}
    for folder in ("decaustic", "truecolour"):
        n = 0
        for name, block in plan.owner.items():
            src_dir = bdir / block / folder
            if not src_dir.is_dir():
                continue
            for src in src_dir.glob(Path(name).stem + ".*"):
                (out / folder).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, out / folder / src.name)
                n += 1
        if n:
            copied[folder] = n
    return copied


def _yes(x) -> str:
    return "-" if x is None else ("yes" if x else "no")


def _water(b: dict) -> str:
    if not b["water"]:
        return "no"
    return "yes" + (" (" + " / ".join(f"{a:.2f}" for a in b["attenuation"]) + ")" if b["attenuation"] else "")


def _report(out: Path, plan, m: dict) -> Path:
    from ..core.io.atomic import atomic_path

    def f(x, fmt="{:.2f}"):
        return "-" if x is None else fmt.format(x)

    s = m["scores"]
    lines = ["# Training in blocks", "",
             f"{len(plan.blocks)} blocks ({plan.grid[0]} x {plan.grid[1]} over the seabed, margin {plan.margin:.3g}), "
             f"merged into {m['gaussians']:,} Gaussians in {m['job_seconds']:.0f} s.", "",
             "| | held-out views | PSNR vs photos (dB) | PSNR vs ground truth (dB) |", "|---|---|---|---|",
             f"| all | {s['views']} | {f(s['psnr'])} | {f(s['psnr_gt'])} |",
             f"| crossing a seam | {s['seam_views']} | {f(s['psnr_seam'])} | {f(s['psnr_gt_seam'])} |",
             f"| inside one block | {s['views'] - s['seam_views']} | {f(s['psnr_inner'])} | {f(s['psnr_gt_inner'])} |",
             "", "| block | photos | held out | steps | Gaussians kept / trained | its held-out PSNR (dB) | "
             "peak memory (MB) | starts | water (attenuation per m) | lamp | caustics found |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for b in m["blocks"]:
        lines.append(f"| {b['block']} | {b['photos']} | {b['held_out']} | {f(b['iterations'], '{}')} | "
                     f"{b['kept']:,} / {f(b['gaussians'], '{:,}')} | {f(b['psnr_test'])} | "
                     f"{f(b['peak_rss_mb'], '{}')} | {f(b['starts'], '{}')} | {_water(b)} | {_yes(b['lamp'])} | "
                     f"{_yes(b['caustics'])} |")
    att = [b["attenuation"] for b in m["blocks"] if b["water"] and b["attenuation"]]
    if len(att) > 1:
        import numpy as np

        spread = np.ptp(np.asarray(att), axis=0) / np.maximum(np.mean(att, axis=0), 1e-9)
        lines += ["", f"The blocks fitted the water each on their own photos: their attenuations differ by "
                      f"{', '.join(f'{100 * x:.0f} %' for x in spread)} (red, green, blue)."]
    if m.get("seam_figures"):
        lines += ["", "Held-out photos that cross a seam, the merged scene's render (left) beside the photo "
                      "(right), the lowest-scored first:", ""]
        lines += [f"![{Path(p).stem}]({p})" for p in m["seam_figures"]]
    lines += ["", "Each block's own report is in `blocks/NAME/report.md`. A block's held-out PSNR is that of its "
              "own model on the held-out photos in its cell, with its own water and lamp; the merged scene's is "
              "of the Gaussians as stored."]
    path = out / "report.md"
    with atomic_path(path, "report") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path
