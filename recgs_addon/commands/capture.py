"""The capture commands: ``sfm`` (photos into a COLMAP model with pycolmap) and ``video`` (a
clip's sharpest frames, then SfM, into a survey); progress as JSON lines."""
from __future__ import annotations

import argparse
import math
import shutil
import sys
import time
from pathlib import Path

from ..core.options.capture import SFM_OPTIONS, VIDEO_OPTIONS
from .events import StopSignals, emit, fail


def add_sfm_arguments(p: argparse.ArgumentParser) -> None:
    """The ``sfm`` options, from their one declaration (core/options/capture.py)."""
    SFM_OPTIONS.add_to(p)


def add_video_arguments(p: argparse.ArgumentParser) -> None:
    """The ``video`` options, from their one declaration (core/options/capture.py)."""
    VIDEO_OPTIONS.add_to(p)


def _stage_photos(photo_dir: Path, image_dir: Path, names: list[str], link: bool) -> None:
    """Copy (or symlink) the photos into the scene's image folder; leaves other files alone."""
    import os
    import shutil

    image_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        src, dst = photo_dir / name, image_dir / name
        if dst.is_symlink() or dst.exists():
            dst.unlink()
        if link:
            os.symlink(src.resolve(), dst)
        else:
            shutil.copy2(src, dst)


def cmd_sfm(args) -> int:
    from ..core.errors import RecGSError

    t0 = time.perf_counter()
    scene: Path = args.out
    image_dir = scene / "images"
    model_dir = scene / "sparse" / "0"
    try:
        from ..core.capture.sfm import SfmOptions, list_images, reconstruct

        names = list_images(args.photo_dir)
        if model_dir.exists() and not args.overwrite:
            raise RecGSError(f"{model_dir}: a COLMAP model is already there (import it, or pass --overwrite)")
        import pycolmap  # noqa: F401  (fail before copying anything)
    except ImportError as exc:
        return fail(f"sfm needs the Python package '{exc.name}' (pip install pycolmap)")
    except RecGSError as exc:
        return fail(str(exc))
    emit("start", photos=str(args.photo_dir), scene=str(scene), images=len(names))
    same = image_dir.exists() and image_dir.resolve() == args.photo_dir.resolve()
    if not same:
        _stage_photos(args.photo_dir, image_dir, names, args.link)

    def on_progress(phase: str, done: int, total: int) -> None:
        emit("progress", phase=phase, done=done, total=total, elapsed=round(time.perf_counter() - t0, 2))
        print(f"[{phase}] {done}/{total}", file=sys.stderr, flush=True)

    from ..core.errors import Cancelled

    stop = StopSignals().install()
    try:
        result = reconstruct(image_dir, model_dir, scene / "database.db",
                             SfmOptions(camera_model=args.camera_model, threads=args.threads), on_progress,
                             resume=True, should_stop=stop)
    except Cancelled:
        emit("done", status="cancelled", reason=f"received {stop.received}", scene=str(scene))
        print(f"stopped by {stop.received}; run the same command again to continue", file=sys.stderr)
        return 0
    except RecGSError as exc:
        return fail(str(exc))
    finally:
        stop.restore()
    emit("done", status="done", scene=str(scene), **result.summary())
    print(f"registered {result.registered}/{result.images} photos, {result.points} points, "
          f"model in {model_dir}", file=sys.stderr)
    return 0


#: Files and folders of a survey that ``video --overwrite`` replaces.
VIDEO_OUTPUTS = ("images", "frames.json", "database.db", "database.db-wal", "database.db-shm", "database.steps.json",
                 "sparse/0")
#: SfM settings for video frames (see SfmOptions), for a few hundred frames in minutes on 2
#: cores. SIFT on frames downscaled to a long side of 1280 px, at most 2048 features a frame,
#: and, on frames of at least VIDEO_SIFT_FULL_SIZE px, from the image itself rather than from
#: it upsampled twice. Measured on 30 frames of 1920 x 1080 of a generated seabed, matched with
#: 10 neighbours (2 shared cores, 2026-11-26): features at 1600 px 3.2 s a frame upsampled,
#: 1.35 s not, at 1280 px 0.85 s; matching with COLMAP's 8192 features (~11k a frame with their
#: second orientations) 0.57 s a pair, 4096 0.20 s, 2048 0.067 s: a 180-frame clip would need
#: ~17 minutes to match with the first, ~2 with the last. All 30 frames registered in each case
#: (reprojection error 0.30-0.31 px). Smaller frames keep the upsampled octave (256 x 192 frames
#: give ~250 features a frame without it, too few to register).
VIDEO_SIFT_MAX_SIDE = 1280
VIDEO_SIFT_FEATURES = 2048
VIDEO_SIFT_FULL_SIZE = 1280


def cmd_video(args) -> int:
    from ..core.errors import Cancelled, RecGSError, SceneError

    t0 = time.perf_counter()
    survey: Path = args.out
    model_dir = survey / "sparse" / "0"
    try:
        import av  # noqa: F401
        import pycolmap
    except ImportError as exc:
        return fail(f"the video command needs the Python package '{exc.name}' "
                    + ("(PyAV: install the training engine, or pip install av==18.1.0)" if exc.name == "av"
                       else "(pip install pycolmap)"))
    from ..core.capture.look_poses import register_looks
    from ..core.io.looks import placing_finished
    from ..core.capture.sfm import SfmOptions, reconstruct
    from ..core.capture.video import (VideoOptions, describe_ranges, existing_frames, import_frames, lost_ranges,
                                      plan_windows, probe)

    if args.frames < 1:
        return fail(f"--frames must be at least 1, got {args.frames}")
    if args.every is not None and not (math.isfinite(args.every) and args.every > 0):
        return fail(f"--every must be a positive number of seconds, got {args.every}")
    if not (math.isfinite(args.step) and 0 < args.step < 1):
        return fail(f"--step is a share of the image, between 0 and 1, got {args.step}")
    if not 0.0 <= args.min_registered <= 1.0:
        return fail(f"--min-registered is a share of the frames, 0 to 1, got {args.min_registered}")
    for name, value, low, high in (("--quality", args.quality, 1, 100), ("--overlap", args.overlap, 1, 10 ** 6),
                                   ("--threads", args.threads, 1, 1024), ("--max-side", args.max_side, 0, 10 ** 6)):
        if not low <= value <= high:
            return fail(f"{name} must be {low} to {high}, got {value}")
    if not 0.0 <= args.look_every < math.inf:
        return fail(f"--look-every is seconds between look frames, 0 or more, got {args.look_every}")
    options = VideoOptions(frames=args.frames, every_s=args.every, step=args.step, max_side=args.max_side,
                           image_format=args.format, jpeg_quality=args.quality, threads=args.threads,
                           looks_every_s=args.look_every)
    stop = StopSignals().install()
    if not args.verbose:
        pycolmap.logging.minloglevel = 3   # COLMAP's INFO to ERROR lines: ours say the same, briefly

    def progress(phase: str, done: int, total: int, **extra) -> None:
        emit("progress", phase=phase, done=done, total=total, elapsed=round(time.perf_counter() - t0, 2), **extra)
        more = "".join(f", {k} {v}" for k, v in extra.items())
        print(f"[{phase}] {done}/{total}{more}", file=sys.stderr, flush=True)

    try:
        if survey.exists() and not survey.is_dir():
            raise RecGSError(f"{survey}: is a file, not a folder (choose another survey folder)")
        info = probe(args.clip)
        plan_windows(info, options)      # a clip too short is refused before anything is replaced
        if args.overwrite:
            for name in VIDEO_OUTPUTS:
                path = survey / name
                if path.is_dir():
                    shutil.rmtree(path)
                elif path.exists():
                    path.unlink()
            if (survey / "sparse").is_dir() and not any((survey / "sparse").iterdir()):
                (survey / "sparse").rmdir()
        elif model_dir.exists() and placing_finished(survey, model_dir):
            raise RecGSError(f"{model_dir}: the survey is already made (import it, or pass --overwrite "
                             "to import the clip again)")
        record = existing_frames(survey, args.clip, options)
        emit("start", clip=str(args.clip), survey=str(survey), codec=info.codec, width=info.width,
             height=info.height, fps=round(info.fps, 4), duration_s=round(info.duration_s, 3),
             frames_in_clip=info.frames, resumed=record is not None)
        print(f"{args.clip}: {info.codec} {info.width}x{info.height}, {info.fps:.2f} fps, "
              f"{info.duration_s:.1f} s, ~{info.frames} frames", file=sys.stderr, flush=True)
        t_frames = time.perf_counter()
        if record is None:
            record = import_frames(args.clip, survey, options,
                                   lambda done, total, kept: progress("frames", done, total, chosen=kept),
                                   stop)
            t_frames = time.perf_counter() - t_frames
        else:
            t_frames = 0.0
            print(f"reusing the {len(record['frames'])} frames chosen before ({survey / 'frames.json'})",
                  file=sys.stderr, flush=True)
        chosen = len(record["frames"])
        progress("frames", record["frame_count"], record["frame_count"], chosen=chosen)
        short = record["stats"].get("short_clip")
        if short and t_frames:
            first, last = short[0], short[-1]
            print(f"a short clip: a step of {first['step']:.3g} of the image gave {first['frames']} frames, so "
                  f"{last['frames']} were taken at a step of {last['step']:.3g} (the view moved about "
                  f"{record['stats']['moved']:.2f} of the image in {record['duration_s']:.1f} s)",
                  file=sys.stderr, flush=True)
        sfm_options = SfmOptions(camera_model=args.camera_model, threads=args.threads, matching="sequential",
                                 overlap=args.overlap,
                                 vocab_tree=str(args.loop_detection) if args.loop_detection else None,
                                 max_image_size=VIDEO_SIFT_MAX_SIDE, max_num_features=VIDEO_SIFT_FEATURES,
                                 first_octave=0 if max(record["size"]) >= VIDEO_SIFT_FULL_SIZE else None,
                                 min_registered=max(2, math.ceil(args.min_registered * chosen)))
        try:
            result = reconstruct(survey / "images", model_dir, survey / "database.db", sfm_options, progress,
                                 resume=True, should_stop=stop)
        except SceneError as exc:
            raise SceneError(f"{args.clip}: {exc}. Choose frames closer together (a smaller --step, or a "
                             "shorter --every), match more neighbours (--overlap), or film slower with more "
                             "overlap") from exc
        looks = register_looks(survey, model_dir, survey / "database.db",
                               lambda done, total: progress("looks", done, total), stop)
    except Cancelled:
        emit("done", status="cancelled", reason=f"received {stop.received}", survey=str(survey))
        print(f"stopped by {stop.received}; run the same command again to continue", file=sys.stderr)
        return 0
    except RecGSError as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"{exc.filename or survey}: {exc.strerror or exc}")
    finally:
        stop.restore()
    seconds = {"frames": round(t_frames, 2), **result.summary()["step_seconds"]}
    if looks:
        seconds["looks"] = looks["seconds"]
    registered = {im.name for im in result.reconstruction.images.values() if im.has_pose}
    lost = lost_ranges(record, registered)
    emit("done", status="done", survey=str(survey), chosen=chosen, frame_count=record["frame_count"],
         lost=lost, looks={k: looks[k] for k in ("registered", "unregistered") if k in looks},
         **{**result.summary(), "step_seconds": seconds, "seconds": round(time.perf_counter() - t0, 2)})
    print(f"{chosen} frames of {record['frame_count']} chosen, {result.registered} registered, "
          f"{result.points} points; survey in {survey}", file=sys.stderr)
    if looks:
        print(f"look frames: {looks['registered']} of {looks['registered'] + looks['unregistered']} placed by their "
              "features against the keyframes' points (the rest are placed between their keyframes in time)"
              + (f"; {looks['reused']} of them were placed by an earlier run" if looks.get("reused") else ""),
              file=sys.stderr)
    if lost:
        print(f"not registered: {describe_ranges(lost)} of the clip ({chosen - result.registered} frames): the "
              "survey lacks the seabed seen only there. Import again with --overwrite and frames closer "
              "together (a smaller --step) or more neighbours matched (--overlap), or film that part "
              "again more slowly", file=sys.stderr)
    return 0
