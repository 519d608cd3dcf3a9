"""Command line: ``python -m recgs_addon COMMAND ...``.

Commands
--------
``import SCENE_DIR --out OUT_DIR``
    Imports a COLMAP survey into a new .blend (cameras + initial Gaussians) with the add-on's
    own operators (needs the ``bpy`` module), exports the Gaussians as a 3DGS PLY, and writes
    a report of the time taken and of the camera conversion error (sparse points projected
    through the Blender cameras versus the COLMAP cameras).
``info FILE.ply``
    Prints what a Gaussian PLY holds (count, SH degree, bounds). No Blender needed.
``train SCENE_DIR --out OUT_DIR [options]``
    Trains 3D Gaussian Splatting (see ``recgs_addon.runner``); progress as JSON lines.
``render MODEL.ply SCENE_DIR --out DIR [--names a.png,b.png]``
    Renders a model from the survey's cameras (PNG and float EXR) and reports PSNR.
``sfm PHOTO_DIR --out SCENE_DIR [--link] [--overwrite]``
    Structure from motion with pycolmap (``recgs_addon.core.capture.sfm``): copies (or links) the
    photos to SCENE_DIR/images and writes the COLMAP model to SCENE_DIR/sparse/0, ready for
    ``import`` and ``train``. Progress as JSON lines, like ``train``.
``video CLIP --out SURVEY [--frames N | --every S] [--max-side PX] [--format jpg|png] [--overwrite]``
    A video clip into a survey (``recgs_addon.core.capture.video``): the sharpest frame of each
    window of time, near-duplicates and dark frames left out, written to SURVEY/images with
    their time stamps in SURVEY/frames.json; then SfM with sequential matching and one shared
    camera into SURVEY/sparse/0. Progress as JSON lines (phases ``frames``, ``features``,
    ``matching``, ``mapping``); SIGTERM/SIGINT stop it cleanly, and running it again on the
    same SURVEY continues where it stopped.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
import warnings
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    """The whole command line: one subparser per command (also read by tools/make_reference.py)."""
    p = argparse.ArgumentParser(prog="python -m recgs_addon", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    imp = sub.add_parser("import", help="COLMAP survey -> scene.blend + point_cloud.ply + report",
                         description="Import a COLMAP survey into a new .blend (a camera per photo and the "
                                     "initial Gaussians) with the add-on's own operators, export the Gaussians "
                                     "as a 3DGS PLY, and report the time taken and how far the Blender "
                                     "cameras' projections are from COLMAP's. Needs the bpy module.")
    imp.add_argument("scene_dir", type=Path, help="survey folder holding images/ and a COLMAP model in sparse/0")
    imp.add_argument("--out", type=Path, required=True,
                     help="output folder (scene.blend, point_cloud.ply, report.md, report.json)")
    imp.add_argument("--images", default="images", help="image folder inside the scene (default: images)")
    imp.add_argument("--sh-degree", type=int, default=0, choices=range(4),
                     help="spherical-harmonic degree of the initial Gaussians (training raises it where it helps)")
    info = sub.add_parser("info", help="describe a 3DGS PLY file",
                          description="Print what a Gaussian PLY holds (count, SH degree, bounds, mean opacity) "
                                      "as JSON. No Blender needed.")
    info.add_argument("ply", type=Path, help="a 3DGS PLY (INRIA layout)")
    from .runner import add_render_arguments, add_train_arguments

    add_train_arguments(sub.add_parser(
        "train", help="train Gaussians on a survey (JSON-lines progress)",
        description="Train 3D Gaussian Splatting on a survey, with or without caustic removal. Progress as JSON "
                    "lines on stdout and a readable line on stderr; writes checkpoint.pt, point_cloud.ply and "
                    "metrics.json to OUT. SIGTERM/SIGINT stop it after a checkpoint; --resume continues."))
    add_render_arguments(sub.add_parser(
        "render", help="render a PLY from a survey's cameras",
        description="Render a model from the survey's cameras (a PNG and a float EXR per view, in OUT) and "
                    "report each view's PSNR against its photo."))
    sfm = sub.add_parser("sfm", help="photos -> COLMAP model with pycolmap (JSON-lines progress)",
                         description="Structure from motion with pycolmap: copies (or links) the photos to "
                                     "OUT/images and writes the COLMAP model to OUT/sparse/0, ready for import "
                                     "and train. Progress as JSON lines; SIGTERM/SIGINT stop it, and running "
                                     "it again continues where it stopped.")
    sfm.add_argument("photo_dir", type=Path, help="folder of overlapping photos")
    sfm.add_argument("--out", type=Path, required=True, help="scene folder to write (images/, sparse/0)")
    sfm.add_argument("--link", action="store_true", help="symlink the photos instead of copying them")
    sfm.add_argument("--overwrite", action="store_true", help="replace an existing sparse/0")
    sfm.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model (one camera shared)")
    sfm.add_argument("--threads", type=int, default=2, help="CPU threads for SfM (features, matching, mapping)")
    add_video_arguments(sub.add_parser(
        "video", help="video clip -> frames + COLMAP model (JSON-lines progress)",
        description="A video clip into a survey: the sharpest frame of each window of time (near-duplicates and "
                    "dark frames left out) into OUT/images with their time stamps in OUT/frames.json, then SfM "
                    "with sequential matching and one shared camera into OUT/sparse/0. Progress as JSON lines; "
                    "SIGTERM/SIGINT stop it, and running it again continues where it stopped."))
    return p


def add_video_arguments(p: argparse.ArgumentParser) -> None:
    from .core.capture.frame_choice import DEFAULT_FRAMES
    from .core.capture.video import DEFAULT_MAX_SIDE, IMAGE_FORMATS, JPEG_QUALITY

    p.add_argument("clip", type=Path, help="video file (MP4, MOV, MKV, ...)")
    p.add_argument("--out", type=Path, required=True, help="survey folder to write (images/, frames.json, sparse/0)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                   help=f"about this many frames, at most 4 a second of clip (default {DEFAULT_FRAMES})")
    g.add_argument("--every", type=float, default=None, metavar="SECONDS",
                   help="one frame every SECONDS instead of a count")
    p.add_argument("--max-side", type=int, default=DEFAULT_MAX_SIDE,
                   help=f"long side of the written frames at most this many px (0: the clip's size; default {DEFAULT_MAX_SIDE})")
    p.add_argument("--format", choices=IMAGE_FORMATS, default="jpg", help="image format of the frames (default jpg)")
    p.add_argument("--quality", type=int, default=JPEG_QUALITY, help=f"JPEG quality (default {JPEG_QUALITY})")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model (one camera for the clip)")
    p.add_argument("--overlap", type=int, default=10, help="match each frame with the next N frames (default 10)")
    p.add_argument("--loop-detection", type=Path, default=None, metavar="VOCAB_TREE",
                   help="also match frames that look alike anywhere in the clip, with this COLMAP "
                        "vocabulary tree file (off by default)")
    p.add_argument("--min-registered", type=float, default=0.5, metavar="SHARE",
                   help="fail unless SfM registers at least this share of the frames (default 0.5)")
    p.add_argument("--threads", type=int, default=2, help="CPU threads for decoding and SfM")
    p.add_argument("--overwrite", action="store_true",
                   help="start again: replace the folder's frames, database and model")
    p.add_argument("--verbose", action="store_true", help="keep COLMAP's own log lines on stderr")


def _blender_projection_error(bpy, cam_objs, points) -> dict:
    """Project the sparse points with each Blender camera's own matrices (as Blender renders)
    and with the core pinhole camera; return the largest and mean difference in pixels."""
    import numpy as np

    from .blender.cameras import apply_render_settings, camera_from_object

    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    pts = np.c_[points.astype(np.float64), np.ones(len(points))]
    worst, total, count = 0.0, 0.0, 0
    for obj in cam_objs:
        cam = camera_from_object(obj)
        apply_render_settings(scene, obj)
        r = scene.render
        P = np.array(obj.calc_matrix_camera(depsgraph, x=r.resolution_x, y=r.resolution_y,
                                            scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
        V = np.array(obj.matrix_world.inverted())
        clip = pts @ (P @ V).T
        ndc = clip[:, :2] / clip[:, 3:4]
        uv_b = np.c_[(ndc[:, 0] + 1) / 2 * cam.width, (1 - ndc[:, 1]) / 2 * cam.height]
        uv_c, z = cam.project(points)
        ok = (z > 0) & (uv_c[:, 0] >= 0) & (uv_c[:, 0] < cam.width) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < cam.height)
        if ok.any():
            d = np.abs(uv_b[ok] - uv_c[ok]).max(axis=1)
            worst = max(worst, float(d.max()))
            total += float(d.sum())
            count += int(ok.sum())
    return {"max_px": worst, "mean_px": total / max(count, 1), "projections": count}


def cmd_import(args) -> int:
    try:
        import bpy
    except ImportError:
        print("error: the 'import' command needs the bpy module (pip install bpy==5.0.1) "
              "or running inside Blender", file=sys.stderr)
        return 2
    from . import blender as addon
    from .core.errors import RecGSError

    out = args.out
    if out.exists() and not out.is_dir():
        print(f"error: {out}: is a file, not a folder (choose another output folder)", file=sys.stderr)
        return 1
    t_start = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        try:  # the operator checks all input before it makes anything
            res = bpy.ops.recgs.import_colmap(directory=str(args.scene_dir), images=args.images,
                                              sh_degree=args.sh_degree)
        except RuntimeError as exc:
            print(f"error: {str(exc).removeprefix('Error: ').strip()}", file=sys.stderr)
            return 1
        t_import = time.perf_counter() - t_start
        if res != {"FINISHED"}:
            print(f"error: import failed: {res}", file=sys.stderr)
            return 1
        try:
            lines = _write_import_outputs(bpy, args, out, t_start, t_import)
        except RuntimeError as exc:   # an operator's error report (the export's full disk, ...)
            print(f"error: {str(exc).removeprefix('Error: ').strip()}", file=sys.stderr)
            return 1
        except RecGSError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    finally:
        addon.unregister()
    print("\n".join(lines))
    return 0


def _write_import_outputs(bpy, args, out: Path, t_start: float, t_import: float) -> list[str]:
    """point_cloud.ply, scene.blend and the report of an import, each written whole or not at
    all (core/io/atomic.py); returns the report's lines."""
    from .blender.blendfile import save_blend
    from .blender.gaussian_object import read_mesh
    from .core.io.atomic import atomic_path, make_folder
    from .core.io.ply import read_gaussian_ply

    make_folder(out)
    obj = bpy.context.active_object
    cam_objs = sorted((o for o in bpy.data.objects if o.type == "CAMERA"), key=lambda o: o.name)
    proj = _blender_projection_error(bpy, cam_objs, read_mesh(obj.data).means)
    undistorted = "recgs_undistorted_dir" in obj
    t0 = time.perf_counter()
    ply_path = out / "point_cloud.ply"
    bpy.ops.recgs.export_ply(filepath=str(ply_path))
    t_export = time.perf_counter() - t0
    bpy.context.scene.camera = cam_objs[0]
    blend_path = out / "scene.blend"
    t0 = time.perf_counter()
    save_blend(blend_path)
    t_save = time.perf_counter() - t0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = read_gaussian_ply(ply_path)
    report = {
        "scene_dir": str(args.scene_dir), "images": len(cam_objs), "gaussians": len(g),
        "sh_degree": g.sh_degree, "undistorted": undistorted,
        "seconds": {"import_operator": round(t_import, 3),
                    "export_ply": round(t_export, 3), "save_blend": round(t_save, 3),
                    "total": round(time.perf_counter() - t_start, 3)},
        "camera_projection_error_px": proj,
        "outputs": {"blend": str(blend_path), "ply": str(ply_path)},
    }
    with atomic_path(out / "report.json", "report") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    lines = [
        f"# RecGS import report: {args.scene_dir}", "",
        f"- {len(cam_objs)} cameras, {len(g)} initial Gaussians (SH degree {g.sh_degree})",
        f"- time: import operator {t_import:.2f} s (reading, checking, building), PLY export "
        f"{t_export:.2f} s, .blend save {t_save:.2f} s",
        f"- Blender cameras vs COLMAP cameras over {proj['projections']} point projections: "
        f"max {proj['max_px']:.2e} px, mean {proj['mean_px']:.2e} px",
        f"- wrote {blend_path} and {ply_path}", "",
        "Training, caustic removal and caustic-free images are not part of this command yet.",
    ]
    with atomic_path(out / "report.md", "report") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return lines


def cmd_info(args) -> int:
    from .core.errors import RecGSError
    from .core.io.ply import read_gaussian_ply

    try:
        g = read_gaussian_ply(args.ply)
    except RecGSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    import numpy as np

    lo, hi = (g.means.min(0), g.means.max(0)) if len(g) else (np.zeros(3), np.zeros(3))
    print(json.dumps({"file": str(args.ply), "gaussians": len(g), "sh_degree": g.sh_degree,
                      "bounds_min": lo.tolist(), "bounds_max": hi.tolist(),
                      "mean_opacity": float(g.opacities.mean()) if len(g) else None}, indent=2))
    return 0


def _emit(event: str, **fields) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


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
    from .core.errors import RecGSError

    t0 = time.perf_counter()
    scene: Path = args.out
    image_dir = scene / "images"
    model_dir = scene / "sparse" / "0"
    try:
        from .core.capture.sfm import SfmOptions, list_images, reconstruct

        names = list_images(args.photo_dir)
        if model_dir.exists() and not args.overwrite:
            raise RecGSError(f"{model_dir}: a COLMAP model is already there (import it, or pass --overwrite)")
        import pycolmap  # noqa: F401  (fail before copying anything)
    except ImportError as exc:
        msg = f"sfm needs the Python package '{exc.name}' (pip install pycolmap)"
        _emit("error", message=msg)
        print(f"error: {msg}", file=sys.stderr)
        return 1
    except RecGSError as exc:
        _emit("error", message=str(exc))
        print(f"error: {exc}", file=sys.stderr)
        return 1
    _emit("start", photos=str(args.photo_dir), scene=str(scene), images=len(names))
    same = image_dir.exists() and image_dir.resolve() == args.photo_dir.resolve()
    if not same:
        _stage_photos(args.photo_dir, image_dir, names, args.link)

    def on_progress(phase: str, done: int, total: int) -> None:
        _emit("progress", phase=phase, done=done, total=total, elapsed=round(time.perf_counter() - t0, 2))
        print(f"[{phase}] {done}/{total}", file=sys.stderr, flush=True)

    import signal

    from .core.errors import Cancelled

    stop = {"signal": None}

    def on_signal(signum, _frame):
        stop["signal"] = signal.Signals(signum).name

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        result = reconstruct(image_dir, model_dir, scene / "database.db",
                             SfmOptions(camera_model=args.camera_model, threads=args.threads), on_progress,
                             resume=True, should_stop=lambda: stop["signal"] is not None)
    except Cancelled:
        _emit("done", status="cancelled", reason=f"received {stop['signal']}", scene=str(scene))
        print(f"stopped by {stop['signal']}; run the same command again to continue", file=sys.stderr)
        return 0
    except RecGSError as exc:
        _emit("error", message=str(exc))
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    _emit("done", status="done", scene=str(scene), **result.summary())
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


def _fail(message: str) -> int:
    _emit("error", message=message)
    print(f"error: {message}", file=sys.stderr)
    return 1


def cmd_video(args) -> int:
    import signal

    from .core.errors import Cancelled, RecGSError, SceneError

    t0 = time.perf_counter()
    survey: Path = args.out
    model_dir = survey / "sparse" / "0"
    try:
        import av  # noqa: F401
        import pycolmap
    except ImportError as exc:
        return _fail(f"the video command needs the Python package '{exc.name}' "
                     + ("(PyAV: install the training engine, or pip install av==18.1.0)" if exc.name == "av"
                        else "(pip install pycolmap)"))
    from .core.capture.sfm import SfmOptions, reconstruct
    from .core.capture.video import VideoOptions, existing_frames, import_frames, plan_windows, probe

    if args.every is None and args.frames < 1:
        return _fail(f"--frames must be at least 1, got {args.frames}")
    if args.every is not None and not (math.isfinite(args.every) and args.every > 0):
        return _fail(f"--every must be a positive number of seconds, got {args.every}")
    if not 0.0 <= args.min_registered <= 1.0:
        return _fail(f"--min-registered is a share of the frames, 0 to 1, got {args.min_registered}")
    for name, value, low, high in (("--quality", args.quality, 1, 100), ("--overlap", args.overlap, 1, 10 ** 6),
                                   ("--threads", args.threads, 1, 1024), ("--max-side", args.max_side, 0, 10 ** 6)):
        if not low <= value <= high:
            return _fail(f"{name} must be {low} to {high}, got {value}")
    options = VideoOptions(frames=args.frames, every_s=args.every, max_side=args.max_side,
                           image_format=args.format, jpeg_quality=args.quality, threads=args.threads)
    stop = {"signal": None}

    def on_signal(signum, _frame):
        stop["signal"] = signal.Signals(signum).name

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    if not args.verbose:
        pycolmap.logging.minloglevel = 3   # COLMAP's INFO to ERROR lines: ours say the same, briefly

    def progress(phase: str, done: int, total: int, **extra) -> None:
        _emit("progress", phase=phase, done=done, total=total, elapsed=round(time.perf_counter() - t0, 2), **extra)
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
        elif model_dir.exists():
            raise RecGSError(f"{model_dir}: the survey is already made (import it, or pass --overwrite "
                             "to import the clip again)")
        record = existing_frames(survey, args.clip, options)
        _emit("start", clip=str(args.clip), survey=str(survey), codec=info.codec, width=info.width,
              height=info.height, fps=round(info.fps, 4), duration_s=round(info.duration_s, 3),
              frames_in_clip=info.frames, resumed=record is not None)
        print(f"{args.clip}: {info.codec} {info.width}x{info.height}, {info.fps:.2f} fps, "
              f"{info.duration_s:.1f} s, ~{info.frames} frames", file=sys.stderr, flush=True)
        t_frames = time.perf_counter()
        if record is None:
            record = import_frames(args.clip, survey, options,
                                   lambda done, total, kept: progress("frames", done, total, chosen=kept),
                                   lambda: stop["signal"] is not None)
            t_frames = time.perf_counter() - t_frames
        else:
            t_frames = 0.0
            print(f"reusing the {len(record['frames'])} frames chosen before ({survey / 'frames.json'})",
                  file=sys.stderr, flush=True)
        chosen = len(record["frames"])
        progress("frames", record["frame_count"], record["frame_count"], chosen=chosen)
        sfm_options = SfmOptions(camera_model=args.camera_model, threads=args.threads, matching="sequential",
                                 overlap=args.overlap, vocab_tree=str(args.loop_detection) if args.loop_detection else None,
                                 max_image_size=VIDEO_SIFT_MAX_SIDE, max_num_features=VIDEO_SIFT_FEATURES,
                                 first_octave=0 if max(record["size"]) >= VIDEO_SIFT_FULL_SIZE else None,
                                 min_registered=max(2, math.ceil(args.min_registered * chosen)))
        try:
            result = reconstruct(survey / "images", model_dir, survey / "database.db", sfm_options, progress,
                                 resume=True, should_stop=lambda: stop["signal"] is not None)
        except SceneError as exc:
            raise SceneError(f"{args.clip}: {exc}. Choose more frames (--frames, or a shorter --every), match "
                             "more neighbours (--overlap), or film slower with more overlap") from exc
    except Cancelled:
        _emit("done", status="cancelled", reason=f"received {stop['signal']}", survey=str(survey))
        print(f"stopped by {stop['signal']}; run the same command again to continue", file=sys.stderr)
        return 0
    except RecGSError as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"{exc.filename or survey}: {exc.strerror or exc}")
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    seconds = {"frames": round(t_frames, 2), **result.summary()["step_seconds"]}
    _emit("done", status="done", survey=str(survey), chosen=chosen, frame_count=record["frame_count"],
          **{**result.summary(), "step_seconds": seconds, "seconds": round(time.perf_counter() - t0, 2)})
    print(f"{chosen} frames of {record['frame_count']} chosen, {result.registered} registered, "
          f"{result.points} points; survey in {survey}", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "sfm":
        return cmd_sfm(args)
    if args.command == "video":
        return cmd_video(args)
    from .runner import run_render, run_train

    return {"import": cmd_import, "info": cmd_info, "train": run_train, "render": run_render}[args.command](args)
