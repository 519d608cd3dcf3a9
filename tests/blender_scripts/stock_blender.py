"""An artist's session in a stock Blender (the bpy module of a venv holding only bpy and the
numpy it brings), run by tests/test_blender_versions.py in a fresh user profile
(BLENDER_USER_RESOURCES):

    python stock_blender.py ZIP SCENE_DIR OUT_DIR [--render] [--engine ok|unavailable]
                            [--worker-python PYTHON] [--train-steps N]

Install the extension zip with Blender's own installer and enable it, import the COLMAP
survey, check the EEVEE preview (its geometry nodes instance every Gaussian; ``--render``
also renders a small EEVEE frame), delete a few Gaussians, export the PLY and check that it
holds exactly the Gaussians left, disable and re-enable twice. With ``--engine``: click
*Install Training Engine* (refused while online access is off, then with it on; the
operator's timer function is stepped by hand, the bpy module has no event loop) and, when
the engine is expected (``ok``), train N steps in the background following progress, then
start again and cancel. ``unavailable``: the install must fail with a clear message and
leave nothing behind. ``--worker-python``: instead of the engine, choose an existing Python
that holds torch in the add-on's preferences (*Python with torch*), then train and cancel the
same way; the job runs in that Python, Blender's own never imports torch.

Each step prints one line ``STEP {"step": ..., "seconds": ..., "detail": ...}``; the first
failure prints ``FAIL {...}`` with the traceback and exits 1. The last line is ``ALL-OK``.
"""
import json
import os
import sys
import time
import traceback

import bpy  # noqa: I001  (bpy first: it makes Blender's own modules importable)
import addon_utils

MODULE = "bl_ext.user_default.recgs"
OPERATORS = ("RECGS_OT_import_colmap", "RECGS_OT_export_ply", "RECGS_OT_import_ply", "RECGS_OT_install_engine")
DELETED = 10


def step(name, fn, *args):
    t0 = time.perf_counter()
    try:
        detail = fn(*args)
    except BaseException as exc:  # noqa: BLE001  (report any failure, then stop)
        print("FAIL " + json.dumps({"step": name, "seconds": round(time.perf_counter() - t0, 2),
                                    "error": f"{type(exc).__name__}: {exc}",
                                    "traceback": traceback.format_exc()[-3000:]}), flush=True)
        sys.exit(1)
    print("STEP " + json.dumps({"step": name, "seconds": round(time.perf_counter() - t0, 2),
                                "detail": detail if detail is not None else ""}), flush=True)
    return detail


def mod(name):
    return sys.modules[f"{MODULE}.recgs_addon.{name}"]


def find_spec(name):
    import importlib.util
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None


def stock():
    """Nothing the add-on needs beyond bpy and numpy is importable before the install."""
    found = [n for n in ("torch", "pycolmap", "scipy") if find_spec(n) is not None]
    assert not found, f"not a stock Blender Python: {found} importable"
    import numpy
    return (f"Blender {bpy.app.version_string}, Python {sys.version.split()[0]}, numpy {numpy.__version__}, "
            f"OpenImageIO {'bundled with Blender' if find_spec('OpenImageIO') else 'absent'}")


def install(zip_path):
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    assert MODULE in bpy.context.preferences.addons, sorted(bpy.context.preferences.addons.keys())
    missing = [c for c in OPERATORS if not hasattr(bpy.types, c)]
    assert not missing, f"not registered after install: {missing}"
    for name in ("pycolmap", "OpenImageIO"):
        assert find_spec(name) is not None, f"{name} not importable after the install (bundled wheels)"
    import pycolmap
    return f"pycolmap {pycolmap.__version__} from {os.path.dirname(os.path.dirname(pycolmap.__file__))}"


def import_survey(scene_dir):
    n_images = len(os.listdir(os.path.join(scene_dir, "images")))
    before = {o.name for o in bpy.data.objects if o.type == "CAMERA"}   # the startup scene's own
    bpy.ops.recgs.import_colmap(directory=scene_dir)
    obj = bpy.context.active_object
    assert obj is not None and "f_dc_0" in obj.data.attributes, obj
    cams = [o for o in bpy.data.objects if o.type == "CAMERA" and o.name not in before]
    assert len(cams) == n_images, (len(cams), n_images)
    assert any(m.startswith(MODULE + ".recgs_addon.core") for m in sys.modules), "core not from the extension"
    return f"{len(cams)} cameras, {len(obj.data.vertices)} Gaussians"


def instances_of(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    return sum(1 for inst in dg.object_instances
               if inst.is_instance and inst.parent is not None and inst.parent.original == obj)


def preview(out_dir, render):
    obj = bpy.context.active_object
    pv = mod("blender.preview")
    md = pv.preview_modifier(obj)
    assert md is not None and md.node_group is not None, "no preview modifier after the import"
    ratio = pv.get_input(obj, "Display Ratio", 1.0)
    n, shown = len(obj.data.vertices), instances_of(obj)
    assert shown > 0 and abs(shown - ratio * n) <= max(2, 0.05 * n), (shown, ratio, n)
    detail = f"{shown} instances of {n} Gaussians (display ratio {ratio:g})"
    if render:
        scene = bpy.context.scene
        scene.camera = next(o for o in bpy.data.objects if o.type == "CAMERA")
        try:
            scene.render.engine = "BLENDER_EEVEE"
        except TypeError:
            scene.render.engine = "BLENDER_EEVEE_NEXT"  # Blender 4.2-4.x
        scene.eevee.taa_render_samples = 1
        scene.render.resolution_percentage = 50
        scene.render.image_settings.file_format = "PNG"
        scene.render.filepath = os.path.join(out_dir, "eevee.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(scene.render.filepath)
        import numpy as np
        px = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(px)
        rgb = px.reshape(-1, 4)[:, :3]
        assert rgb.std() > 0.01, "the EEVEE frame is flat: no Gaussians drawn"
        detail += f"; EEVEE {img.size[0]}x{img.size[1]} in {time.perf_counter() - t0:.1f} s, std {rgb.std():.3f}"
    return detail


def delete_some():
    import bmesh
    obj = bpy.context.active_object
    n = len(obj.data.vertices)
    before = instances_of(obj)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="DESELECT")
    bm = bmesh.from_edit_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    for i in range(0, DELETED * 7, 7):
        bm.verts[i].select = True
    bm.select_flush(True)
    bmesh.update_edit_mesh(obj.data)
    bpy.ops.mesh.delete(type="VERT")
    bpy.ops.object.mode_set(mode="OBJECT")
    assert len(obj.data.vertices) == n - DELETED, (len(obj.data.vertices), n)
    after = instances_of(obj)
    assert after < before, (before, after)
    return f"{n} -> {len(obj.data.vertices)} Gaussians, preview {before} -> {after} instances"


def read_ply_xyz(path):
    import numpy as np
    with open(path, "rb") as f:
        header = b""
        while not header.endswith(b"end_header\n"):
            header += f.readline()
        lines = header.decode().splitlines()
        assert "format binary_little_endian 1.0" in lines, lines[:3]
        count = next(int(ln.split()[2]) for ln in lines if ln.startswith("element vertex"))
        props = [ln.split()[2] for ln in lines if ln.startswith("property float")]
        data = np.frombuffer(f.read(), np.float32, count * len(props)).reshape(count, len(props))
    return data[:, [props.index(k) for k in ("x", "y", "z")]]


def export(out_dir):
    import numpy as np
    obj = bpy.context.active_object
    path = os.path.join(out_dir, "edited.ply")
    bpy.ops.recgs.export_ply(filepath=path)
    xyz = read_ply_xyz(path)
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3) @ np.array(obj.matrix_world)[:3, :3].T.astype(np.float32) + np.array(obj.matrix_world)[:3, 3]
    assert len(xyz) == len(co), (len(xyz), len(co))
    assert np.allclose(xyz, co, atol=1e-5), "the PLY's means are not the edited object's"
    return f"{len(xyz)} Gaussians in {os.path.getsize(path)} bytes"


def disable_enable():
    for _ in range(2):
        addon_utils.disable(MODULE, default_set=True)
        left = [c for c in OPERATORS if hasattr(bpy.types, c)]
        assert not left, f"left after disable: {left}"
        assert not hasattr(bpy.types.Scene, "recgs"), "scene settings left after disable"
        addon_utils.enable(MODULE, default_set=True)
        missing = [c for c in OPERATORS if not hasattr(bpy.types, c)]
        assert not missing, f"missing after enable: {missing}"
    obj = bpy.context.active_object
    n = len(obj.data.vertices)
    path = os.path.join(os.path.dirname(bpy.context.scene.render.filepath) or ".", "again.ply")
    bpy.ops.recgs.export_ply(filepath=path)
    assert len(read_ply_xyz(path)) == n
    return "twice; export works after"


def engine_refused_offline():
    bpy.context.preferences.system.use_online_access = False
    assert not bpy.app.online_access
    try:
        bpy.ops.recgs.install_engine()
    except RuntimeError as exc:
        assert "Online access is off" in str(exc), exc
        eng = mod("blender.engine")
        assert eng._installer is None
        return "refused: " + str(exc).strip().splitlines()[0]
    raise AssertionError("the engine install started with online access off")


def engine_install(expect):
    eng, ei = mod("blender.engine"), mod("engine_install")
    bpy.context.preferences.system.use_online_access = True  # Preferences > System > Allow Online Access
    assert bpy.app.online_access
    bpy.ops.recgs.install_engine()
    assert eng._installer is not None
    inst, phases, texts = eng._installer, [], set()
    while eng._installer is not None:   # what bpy.app.timers does in a UI session
        texts.add(eng.status_text())
        if not phases or phases[-1] != inst.progress.phase:
            phases.append(inst.progress.phase)
        eng._step()
        time.sleep(0.2)
    site = ei.installed_engine(eng.engine_root())
    leftovers = sorted(os.listdir(os.path.dirname(str(ei.engine_site(eng.engine_root())))))
    if expect == "unavailable":
        assert inst.status == "failed", (inst.status, inst.message)
        assert "Installing the training engine failed" in inst.message or "network" in inst.message, inst.message
        assert site is None and leftovers == [], leftovers
        return f"failed as expected, nothing left: {inst.message}"
    assert inst.status == "done", f"{inst.status}: {inst.message}\n" + "\n".join(inst.progress.lines[-15:])
    assert site is not None and leftovers == ["site-packages"], leftovers
    assert mod("blender.jobs")._engine == site, "jobs do not see the engine"
    assert "torch" not in sys.modules, "Blender's own Python imported torch"
    assert "numba" not in sys.modules, "Blender's own Python imported numba"
    assert any(t.startswith("RecGS engine:") for t in texts), texts
    info = ei.engine_info(site)
    assert info.get("numba"), f"the engine holds no numba (training would run on eager torch): {info}"
    assert ei.update_reason(info) is None, ei.update_reason(info)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(site) for f in fs)
    return f"{inst.message}, {size / 2**20:.0f} MiB; progress phases {' > '.join(phases)}"


def worker_python(python):
    """Preferences > Add-ons > RecGS > Python with torch: an existing Python runs the jobs."""
    eng, jobs = mod("blender.engine"), mod("blender.jobs")
    assert not eng.engine_ready(), "a training engine is ready before any was chosen"
    prefs = bpy.context.preferences.addons[MODULE].preferences
    prefs.worker_python = python
    assert jobs.worker_python() == python, (jobs.worker_python(), python)
    assert eng.engine_ready(), "the chosen Python is not taken as the engine"
    assert not jobs.missing_modules(["torch"]), f"{python} has no torch (asked through the add-on)"
    assert "torch" not in sys.modules, "Blender's own Python imported torch"
    assert "numba" not in sys.modules, "Blender's own Python imported numba"
    assert jobs.command("train")[0] == python, jobs.command("train")
    path = jobs.job_env()["PYTHONPATH"].split(os.pathsep)
    profile = os.environ.get("BLENDER_USER_RESOURCES", "")
    assert profile and path[0] == str(jobs.PACKAGE_PARENT) and path[0].startswith(profile), \
        f"the job would not run the installed extension's package: {path}"
    blender_site = [p for p in path if p.startswith(profile) and "site-packages" in p]
    assert not blender_site, f"Blender's site-packages (its Python's wheels) on the worker's path: {blender_site}"
    return f"jobs run in {python} with the extension's package from {path[0]}"


def train(steps):
    training, follow = mod("blender.training"), mod("blender.job_follow")
    scene, obj = bpy.context.scene, bpy.context.active_object
    s = scene.recgs
    s.iterations, s.max_minutes, s.checkpoint_every = steps, 0.0, 5.0
    s.out_dir = os.path.join(os.path.dirname(bpy.context.scene.render.filepath) or ".", "train")
    training.start_training(scene, obj)
    seen = []
    while follow.pump() is not None:  # the timer function of the sidebar's Train button
        if s.iteration and (not seen or seen[-1] != s.iteration):
            seen.append(s.iteration)
        time.sleep(0.2)
    assert s.status == "DONE", f"{s.status}: {s.message} {follow.last_failure}"
    assert s.iteration == steps, (s.iteration, steps)
    assert seen, "no progress seen"
    assert os.path.isfile(os.path.join(s.out_dir, "point_cloud.ply"))
    # the worker imported numba (its kernels from the first step, or after their warm-up)
    with open(os.path.join(s.out_dir, "metrics.json")) as f:
        compile_state = json.load(f)["compile"]
    assert compile_state["numba"] in ("ready", "warming"), compile_state
    obj = bpy.data.objects[obj.name]
    assert "torch" not in sys.modules, "Blender's own Python imported torch"
    assert "numba" not in sys.modules, "Blender's own Python imported numba"
    return (f"{steps} steps, progress at iterations {seen}, {len(obj.data.vertices)} Gaussians, numba "
            f"{compile_state['numba']}; {s.message}")


def train_cancel():
    training, follow = mod("blender.training"), mod("blender.job_follow")
    scene, obj = bpy.context.scene, bpy.context.active_object
    s = scene.recgs
    s.iterations = 5000
    s.out_dir = s.out_dir + "_cancel"
    training.start_training(scene, obj)
    t0 = time.perf_counter()
    cancelled_at = None
    while follow.pump() is not None:
        if cancelled_at is None and s.iteration > 0:
            bpy.ops.recgs.cancel()
            cancelled_at = s.iteration
        assert time.perf_counter() - t0 < 600, "the cancelled job did not stop"
        time.sleep(0.2)
    assert cancelled_at is not None, "no progress before the job ended"
    assert s.status == "CANCELLED", f"{s.status}: {s.message}"
    assert os.path.isfile(os.path.join(s.out_dir, "checkpoint.pt")), "no checkpoint after cancel"
    assert "torch" not in sys.modules, "Blender's own Python imported torch"
    assert "numba" not in sys.modules, "Blender's own Python imported numba"
    return f"cancelled after iteration {cancelled_at}, stopped at {s.iteration}: {s.message}"


def main(argv):
    zip_path, scene_dir, out_dir = argv[:3]
    render = "--render" in argv
    expect = argv[argv.index("--engine") + 1] if "--engine" in argv else None
    worker = argv[argv.index("--worker-python") + 1] if "--worker-python" in argv else None
    steps = int(argv[argv.index("--train-steps") + 1]) if "--train-steps" in argv else 50
    os.makedirs(out_dir, exist_ok=True)
    bpy.context.scene.render.filepath = os.path.join(out_dir, "")
    step("stock", stock)
    step("install", install, zip_path)
    step("import", import_survey, scene_dir)
    step("preview", preview, out_dir, render)
    step("delete", delete_some)
    step("export", export, out_dir)
    step("disable_enable", disable_enable)
    if expect:
        step("engine_offline", engine_refused_offline)
        step("engine", engine_install, expect)
        if expect == "ok":
            step("train", train, steps)
            step("cancel", train_cancel)
    if worker:
        step("worker_python", worker_python, worker)
        step("train", train, steps)
        step("cancel", train_cancel)
    addon_utils.disable(MODULE, default_set=True)
    print("ALL-OK", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
