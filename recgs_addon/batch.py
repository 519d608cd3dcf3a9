"""Batch mode: import a survey, train, save the .blend and the outputs, without a UI.

    blender -b --python recgs_addon/batch.py -- SCENE_DIR --out OUT_DIR [trainer options]
    python recgs_addon/batch.py SCENE_DIR --out OUT_DIR [trainer options]     (bpy module)

Trainer options are those of ``python -m recgs_addon train`` (``--mode``, ``--max-minutes``,
``--iterations``, ``--budget``, ``--downscale``, ...); they become the scene's RecGS settings,
so the saved .blend remembers them. The job runs in ``OUT_DIR/train`` through the same code
as the sidebar's Train button (``blender.training``), followed from a loop on the main thread
with its progress lines forwarded to stderr. Writes:

* ``OUT_DIR/scene.blend``: cameras and the trained Gaussian object (Resume works from it);
* ``OUT_DIR/point_cloud.ply``: the object exported as a 3DGS PLY;
* ``OUT_DIR/decaustic/``: the caustic-free photos, when the mode removes caustics;
* ``OUT_DIR/report.md`` and ``metrics.json`` when the job wrote them.

Exits 0 on success, 1 with a message naming the problem otherwise (2 for bad options).
Ctrl-C cancels the job cleanly (checkpoint written) and still saves what there is.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

if not __package__:  # run as a script: make the package importable (it is this file's folder)
    _here = Path(__file__).resolve().parent
    if str(_here.parent) not in sys.path:
        sys.path.insert(0, str(_here.parent))
    # Run as a script (python recgs_addon/batch.py, blender -b --python), this file has no
    # package, so relative imports would fail. Naming its package here (PEP 366) makes the
    # plain relative imports below, and those in the functions, resolve in it. The folder's own
    # name, not "recgs_addon": an installed extension is imported under another name, hence
    # relative imports only (tests/test_architecture.py).
    __package__ = _here.name

from . import engine_install as ei  # noqa: E402  (after the package is made importable)
from .commands.train import add_train_arguments  # noqa: E402
from .core.errors import RecGSError  # noqa: E402
from .core.io import atomic  # noqa: E402


def use_installed_engine(bpy) -> "str | None":
    """Batch mode trains with the engine the add-on's *Install Training Engine* put in this
    user's extension folder (``<user>/extensions/.user/<repo>/recgs/engine/...``), unless
    ``RECGS_ENGINE_DIR`` names one or a Python with torch runs this. Returns the folder used."""
    if os.environ.get(ei.ENGINE_DIR_ENV):
        return os.environ[ei.ENGINE_DIR_ENV]
    try:
        base = Path(bpy.utils.user_resource("EXTENSIONS"))
    except (TypeError, ValueError):   # a Blender before 4.2 has no extensions
        return None
    for root in sorted(base.glob(".user/*/recgs")):
        site = ei.installed_engine(root)
        if site is not None:
            os.environ[ei.ENGINE_DIR_ENV] = str(site)   # what the add-on's jobs read
            return str(site)
    return None


def _argv(argv):
    if argv is not None:
        return list(argv)
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]


def _parser():
    import argparse

    p = argparse.ArgumentParser(prog="recgs_addon/batch.py", description=__doc__.split("\n\n")[0])
    add_train_arguments(p)
    return p


def extra_train_args(parser, args, handled) -> list[str]:
    """The options given that the RecGS settings do not hold, as command-line words."""
    skip = set(handled) | {"scene_dir", "out", "resume", "init_ply", "help"}
    words = []
    for action in parser._actions:
        if not action.option_strings or action.dest in skip:
            continue
        value = getattr(args, action.dest, None)
        if value == action.default:
            continue
        flag = max(action.option_strings, key=len)
        words += [flag] if action.nargs == 0 else [flag, str(value)]
    return words


def log(msg: str) -> None:
    print(f"batch: {msg}", file=sys.stderr, flush=True)


def fail(msg: str) -> int:
    print(f"batch: error: {msg}", file=sys.stderr, flush=True)
    return 1


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(_argv(argv))
    if args.resume or args.init_ply:
        return fail("--resume and --init-ply are not batch options (open scene.blend and use Resume)")
    try:
        import bpy
    except ImportError:
        return fail("needs Blender (blender -b --python recgs_addon/batch.py -- ...) or the bpy module")
    scene_dir: Path = args.scene_dir.resolve()
    out: Path = args.out.resolve()
    if not scene_dir.is_dir():
        return fail(f"{scene_dir}: scene folder is missing")
    t0 = time.perf_counter()
    engine = use_installed_engine(bpy)
    if engine:
        log(f"training engine: {engine}")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from . import blender as addon   # the Blender layer: only once bpy imports
    from .blender import job_follow, properties, training

    addon.register()
    try:
        extra = extra_train_args(parser, args, properties.SETTINGS_OPTIONS)
        return _run(bpy, training, job_follow, properties, args, extra, scene_dir, out, t0)
    finally:
        addon.unregister()


def _run(bpy, training, job_follow, properties, args, extra: list[str], scene_dir: Path, out: Path, t0: float) -> int:
    scene = bpy.context.scene
    s = scene.recgs
    try:
        properties.apply_train_args(s, args)
    except (ValueError, TypeError) as exc:
        return fail(str(exc))
    s.out_dir = str(out / "train")
    images = args.images or "images"
    try:
        res = bpy.ops.recgs.import_colmap(directory=str(scene_dir), images=images)
    except RuntimeError as exc:
        return fail(str(exc).removeprefix("Error: ").strip())
    if res != {"FINISHED"}:
        return fail(f"{scene_dir}: import failed")
    obj = bpy.context.active_object
    log(f"imported {scene_dir}: {len(obj.data.vertices)} initial Gaussians")
    try:
        log(training.start_training(scene, obj, echo_stderr=True, extra_args=extra))
        log("job: " + " ".join(job_follow.active_job().job.argv))
    except (RecGSError, OSError, ValueError) as exc:  # WorkflowError included
        return fail(str(exc))
    try:
        status = job_follow.wait()
    except KeyboardInterrupt:
        log("interrupted: stopping the job (it writes its checkpoint)")
        job_follow.cancel()
        status = job_follow.wait()
    if status == "FAILED":
        return fail(f"training failed: {job_follow.last_failure or s.message}")
    obj = bpy.data.objects[obj.name]
    try:
        copied = _save_outputs(bpy, obj, out)
    except RuntimeError as exc:   # the export operator's error report
        return fail(str(exc).removeprefix("Error: ").strip())
    except (RecGSError, OSError) as exc:
        return fail(str(exc))
    log(f"{status.lower()}: {s.message}; wrote {out / 'scene.blend'}, {out / 'point_cloud.ply'}"
        + (f", {', '.join(copied)}" if copied else "") + f" in {time.perf_counter() - t0:.1f} s")
    return 0 if status == "DONE" else 1


def _save_outputs(bpy, obj, out: Path) -> list[str]:
    """scene.blend, point_cloud.ply and the job's report and caustic-free images, each file
    written whole or not at all (core/io/atomic.py). Returns what was copied from the job."""
    from .blender.blendfile import save_blend

    atomic.make_folder(out)
    bpy.context.scene.camera = bpy.context.scene.camera or next(
        (o for o in bpy.data.objects if o.type == "CAMERA"), None)
    save_blend(out / "scene.blend")
    bpy.context.view_layer.objects.active = obj
    bpy.ops.recgs.export_ply(filepath=str(out / "point_cloud.ply"))
    job_out = out / "train"
    copied = []
    for name in ("decaustic", "report"):  # report/ holds report.md's figures
        if (job_out / name).is_dir():
            atomic.copy_tree(job_out / name, out / name)
            copied.append(f"{name}/")
    for name in ("report.md", "metrics.json"):
        if (job_out / name).is_file():
            atomic.copy_file(job_out / name, out / name, "report")
            copied.append(name)
    return copied


if __name__ == "__main__":
    sys.exit(main())
