"""The artist's workflow in the Blender layer: sidebar operators driving background jobs
(train, cancel, resume, edits, reconstruct from photos), operator errors, settings saved with
the .blend, the batch script and the panel snapshot tool."""
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import ROOT, write_rendered_scene
from test_ply import assert_same

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender

SAMPLE = ROOT / "data" / "sample"


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("wf") / "scene"
    write_rendered_scene(root, n_views=8, width=40, height=30, n_gauss=200)
    return root


@pytest.fixture
def session(bpy_session, tiny_scene, tmp_path):
    """The tiny scene imported; settings for short, eager 3DGS runs writing to tmp_path/out."""
    assert bpy.ops.recgs.import_colmap(directory=str(tiny_scene)) == {"FINISHED"}
    s = bpy.context.scene.recgs
    s.mode, s.eager, s.holdout_every, s.checkpoint_every = "3dgs", True, 4, 0.2
    s.iterations, s.max_minutes = 100000, 0.0
    s.out_dir = str(tmp_path / "out")
    yield bpy.context.scene, bpy.context.active_object.name, tmp_path / "out"
    from recgs_addon.blender import job_follow

    job_follow.stop_active(10)


def _follow():
    from recgs_addon.blender import job_follow

    return job_follow


def _pump_until(pred, timeout=60.0):
    follow = _follow()
    t0 = time.monotonic()
    while not pred():
        assert follow.pump() is not None, f"job ended early: {bpy.context.scene.recgs.message}"
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.05)


def _train_then_cancel(name):
    """Train from the operator, wait for a live update, cancel; returns the finished Job."""
    follow = _follow()
    assert bpy.ops.recgs.train() == {"FINISHED"}
    job = follow.active_job().job
    _pump_until(lambda: "recgs_synced" in bpy.data.objects[name])
    assert bpy.ops.recgs.cancel() == {"FINISHED"}
    assert follow.wait() == "CANCELLED"
    return job


def _object_gaussians(name, world=False):
    from recgs_addon.blender.gaussian_object import gaussians_from_object

    return gaussians_from_object(bpy.data.objects[name], world=world)


def test_train_cancel_resume(session):
    from recgs_addon.blender import jobs
    from recgs_addon.core.train.checkpoint import load_checkpoint
    from recgs_addon.core.io.ply import read_gaussian_ply

    scene, name, out = session
    s = scene.recgs
    follow = _follow()
    job = _train_then_cancel(name)
    assert job.proc.poll() == 0 and job.last["done"]["status"] == "cancelled"
    assert not follow.is_running()
    # the object holds the Gaussians of the last checkpoint (written on SIGTERM)
    ckpt = read_gaussian_ply(out / "point_cloud.ply")
    g = _object_gaussians(name)
    assert_same(ckpt, g)
    assert bpy.data.objects[name]["recgs_synced"] == jobs.gaussian_signature(g)
    assert load_checkpoint(out / "checkpoint.pt")["step"] == s.iteration == job.last["done"]["iteration"]
    assert bpy.data.objects[name]["recgs_out_dir"] == str(out)

    s.iterations = s.iteration + 10
    assert bpy.ops.recgs.resume() == {"FINISHED"}
    job = follow.active_job().job
    assert "--resume" in job.argv and "--init-ply" not in job.argv
    assert follow.wait() == "DONE", s.message
    assert job.last["start"]["resumed"] and job.last["done"]["iterations"] == s.iterations
    assert json.loads((out / "metrics.json").read_text())["iterations"] == s.iterations
    assert_same(read_gaussian_ply(out / "point_cloud.ply"), _object_gaussians(name))


def test_edited_object_is_what_resume_trains(session, tmp_path):
    """Delete half of the Gaussians in Edit Mode and move the object: Export PLY gives exactly
    the rest, and Resume starts a fresh job from them (world space, --init-ply)."""
    import bmesh

    from recgs_addon.core.io.ply import read_gaussian_ply

    scene, name, out = session
    s = scene.recgs
    follow = _follow()
    _train_then_cancel(name)
    before = _object_gaussians(name)
    n = len(before)
    obj = bpy.data.objects[name]
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[v for v in bm.verts if v.index % 2 == 0], context="VERTS")
    bmesh.update_edit_mesh(obj.data)
    keep = np.arange(n) % 2 == 1
    assert bpy.ops.recgs.export_ply(filepath=str(tmp_path / "edited.ply")) == {"FINISHED"}  # in Edit Mode
    assert_same(before.subset(keep), read_gaussian_ply(tmp_path / "edited.ply"))

    obj.location = (0.5, -0.25, 0.1)
    s.iterations = 15
    assert bpy.ops.recgs.resume() == {"FINISHED"}  # still in Edit Mode
    job = follow.active_job().job
    init = out / "edited_init.ply"
    assert "--resume" not in job.argv and job.argv[job.argv.index("--init-ply") + 1] == str(init)
    edited = read_gaussian_ply(init)
    assert len(edited) == int(keep.sum())
    expected = before.subset(keep)
    assert np.allclose(edited.means, expected.means + [0.5, -0.25, 0.1], atol=1e-6)
    assert np.array_equal(edited.sh, expected.sh) and np.array_equal(edited.logit_opacities, expected.logit_opacities)
    # the move is baked: identity transform, world-space Gaussians in the mesh
    assert np.array_equal(np.array(obj.matrix_world), np.eye(4))
    bpy.ops.object.mode_set(mode="OBJECT")
    assert_same(edited, _object_gaussians(name))
    assert follow.wait() == "DONE", s.message
    assert job.last["start"]["gaussians"] == len(edited) and not job.last["start"]["resumed"]
    assert_same(read_gaussian_ply(out / "point_cloud.ply"), _object_gaussians(name))


def test_caustic_mode_outputs(session, tmp_path):
    """A caustic-removal run from the panel: Export Caustic-Free Images copies OUT/decaustic,
    Open Report loads report.md into a text datablock."""
    scene, name, out = session
    s = scene.recgs
    s.mode, s.iterations = "recgs", 30
    assert bpy.ops.recgs.train() == {"FINISHED"}
    assert _follow().wait() == "DONE", s.message
    if (out / "decaustic").is_dir():   # light taken off: the export copies the caustic-free photos
        made = sorted(p.name for p in (out / "decaustic").iterdir())
        assert any(n.endswith(".png") for n in made)
        assert bpy.ops.recgs.export_images(directory=str(tmp_path / "clean photos")) == {"FINISHED"}
        assert sorted(p.name for p in (tmp_path / "clean photos").iterdir()) == made
    else:   # none taken off in 30 steps: the photos are caustic-free as they are, and it says so
        with pytest.raises(RuntimeError, match="caustic-free as they are"):
            bpy.ops.recgs.export_images(directory=str(tmp_path / "clean photos"))
    assert bpy.ops.recgs.open_report() == {"FINISHED"}
    assert bpy.data.texts["RecGS report"].as_string() == (out / "report.md").read_text()


def test_export_images_takes_the_true_colour_photos_too(session, tmp_path):
    """A job that modelled the water (here its outputs written by hand): Export Caustic-Free
    Images copies truecolour/ into the folder's truecolour/, with or without decaustic/."""
    scene, name, out = session
    (out / "truecolour").mkdir(parents=True)
    for n in ("a.png", "b.exr"):
        (out / "truecolour" / n).write_bytes(b"x")
    assert bpy.ops.recgs.export_images(directory=str(tmp_path / "export")) == {"FINISHED"}
    assert sorted(p.name for p in (tmp_path / "export" / "truecolour").iterdir()) == ["a.png", "b.exr"]


def test_export_images_of_a_job_that_found_no_caustics_says_so(session, tmp_path):
    """A caustic-removal job that took no light off wrote no caustic-free copies: the export
    says why (its photos are caustic-free as they are) instead of asking for a caustic mode."""
    import json

    scene, name, out = session
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps({"caustics_dropped": "light: no caustics found"}))
    with pytest.raises(RuntimeError, match=r"no caustics found\), so its photos are caustic-free as they are"):
        bpy.ops.recgs.export_images(directory=str(tmp_path / "export"))
    assert not (tmp_path / "export").exists()


def test_operator_errors_report_instead_of_raising(session, tmp_path, monkeypatch):
    from recgs_addon.blender import jobs
    from recgs_addon.core.io.ply import write_gaussian_ply
    from test_ply import random_gaussians

    scene, name, out = session
    s = scene.recgs
    follow = _follow()

    def refused(op, message, **kw):
        with pytest.raises(RuntimeError, match=message):
            op(**kw)
        assert not follow.is_running()

    refused(bpy.ops.recgs.resume, "no checkpoint to resume from")
    refused(bpy.ops.recgs.cancel, "No RecGS job is running")
    refused(bpy.ops.recgs.open_report, "Train first")
    refused(bpy.ops.recgs.export_images, "Train first", directory=str(tmp_path / "x"))
    refused(bpy.ops.recgs.reconstruct, "Set the Photo Folder")
    refused(bpy.ops.recgs.import_video, "Set the Video File")
    s.mode, s.caustic_k = "recgs", 8
    refused(bpy.ops.recgs.train, "Caustic Filter Size must be odd")
    s.mode = "3dgs"
    monkeypatch.setattr(jobs, "missing_modules", lambda names: list(names))
    refused(bpy.ops.recgs.train, r"needs the training engine: click Install Training Engine")
    # a package missing in the Python that runs jobs: the message names that Python, Blender's
    # own or the one chosen in the preferences
    (tmp_path / "photos").mkdir()
    s.photo_dir = str(tmp_path / "photos")
    refused(bpy.ops.recgs.reconstruct, r"pycolmap in Blender's Python \(" + re.escape(sys.executable))
    monkeypatch.setattr(jobs, "_worker_python", str(tmp_path / "other" / "python"))
    refused(bpy.ops.recgs.reconstruct, r"pycolmap in the Python chosen in the RecGS preferences \("
            + re.escape(str(tmp_path / "other" / "python")))
    s.photo_dir = ""
    monkeypatch.undo()
    # no Gaussian object selected
    bpy.ops.object.select_all(action="DESELECT")
    bpy.context.view_layer.objects.active = None
    refused(bpy.ops.recgs.train, "Select a Gaussian object")
    # a PLY-imported object and no scene folder
    write_gaussian_ply(tmp_path / "g.ply", random_gaussians(n=10, degree=0))
    bpy.ops.recgs.import_ply(filepath=str(tmp_path / "g.ply"))
    s.scene_dir = ""
    refused(bpy.ops.recgs.train, "Set the Scene Folder")
    s.scene_dir = str(tmp_path / "nowhere")
    refused(bpy.ops.recgs.train, "nowhere: scene folder is missing")
    # a job already running (a stand-in process)
    bpy.context.view_layer.objects.active = bpy.data.objects[name]
    s.scene_dir = ""
    dummy = jobs.Job("train", [sys.executable, "-c", "import time; time.sleep(60)"])
    follow._begin(dummy, scene, object_name=name)
    for op in (bpy.ops.recgs.train, bpy.ops.recgs.resume, bpy.ops.recgs.reconstruct, bpy.ops.recgs.import_video):
        with pytest.raises(RuntimeError, match="already running"):
            op()
    assert bpy.ops.recgs.cancel() == {"FINISHED"}
    assert follow.wait() == "CANCELLED" and dummy.proc.poll() is not None


def test_failed_jobs_are_reported(session):
    from recgs_addon.blender import jobs

    scene, name, out = session
    s = scene.recgs
    follow = _follow()
    # a crash without an error event: exit code and the last stderr lines
    code = "import sys\nfor i in range(100): print('line', i, file=sys.stderr)\nsys.exit(3)"
    follow._begin(jobs.Job("train", [sys.executable, "-c", code]), scene, object_name=name)
    assert follow.wait() == "FAILED"
    assert "exited with code 3" in s.message
    assert "line 99" in follow.last_failure and "line 10" not in follow.last_failure
    # the trainer's own error event (bad settings refused by the job)
    s.device = "cuda:7"
    assert bpy.ops.recgs.train() == {"FINISHED"}
    assert follow.wait() == "FAILED"
    assert "cuda" in s.message.lower(), s.message


def test_settings_survive_save_and_reload(session, tmp_path):
    scene, name, out = session
    s = scene.recgs
    s.mode, s.max_minutes, s.budget_auto, s.budget, s.downscale, s.caustic_k = "joint", 7.5, False, 1234, 3, 11
    s.preset, s.checkpoint_every, s.photo_dir = "vanilla", 42.0, "//photos"
    s.status = "RUNNING"  # as if saved while a job ran
    path = tmp_path / "saved.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.context.scene.recgs.mode == "recgs"
    bpy.ops.wm.open_mainfile(filepath=str(path))
    s = bpy.context.scene.recgs
    assert (s.mode, s.max_minutes, s.budget_auto, s.budget, s.downscale, s.caustic_k) == ("joint", 7.5, False, 1234, 3, 11)
    assert (s.preset, s.checkpoint_every, s.photo_dir, s.out_dir) == ("vanilla", 42.0, "//photos", str(out))
    assert s.status == "CANCELLED"  # load_post: no job survives a reload
    assert bpy.data.objects[name]["recgs_scene_dir"]


def test_reconstruct_from_photos_then_import(bpy_session, tmp_path):
    """The Reconstruct operator runs `sfm` as a job (photos copied to SCENE/images, model in
    SCENE/sparse/0) and imports the result."""
    from recgs_addon.blender.gaussian_object import is_gaussian_object

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(6):
        shutil.copy(SAMPLE / "images" / f"view_{i:03d}.png", photos)
    s = bpy.context.scene.recgs
    s.photo_dir = str(photos)
    assert bpy.ops.recgs.reconstruct() == {"FINISHED"}
    follow = _follow()
    job = follow.active_job().job
    assert follow.wait() == "DONE", s.message
    scene_dir = tmp_path / "photos_scene"
    assert s.scene_dir == str(scene_dir)
    assert sorted(p.name for p in (scene_dir / "images").iterdir()) == sorted(p.name for p in photos.iterdir())
    assert (scene_dir / "sparse/0/images.bin").is_file()
    phases = [e["phase"] for e in job.history if e["event"] == "progress"]
    assert phases[0] == "features" and phases[-1] == "mapping"
    registered = job.last["done"]["registered"]
    assert registered >= 3
    obj = bpy.context.active_object
    assert is_gaussian_object(obj) and len(obj.data.vertices) == job.last["done"]["points"]
    assert len([o for o in bpy.data.objects if o.type == "CAMERA"]) == registered
    with pytest.raises(RuntimeError, match="already has a COLMAP model"):
        bpy.ops.recgs.reconstruct()


def test_sfm_command_reports_bad_photo_folder(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "one.png").write_bytes(b"x")
    r = subprocess.run([sys.executable, "-m", "recgs_addon", "sfm", str(tmp_path / "p"), "--out", str(tmp_path / "s")],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    ev = json.loads(r.stdout.splitlines()[-1])
    assert ev["event"] == "error" and str(tmp_path / "p") in ev["message"] and "at least 2" in ev["message"]
    assert not (tmp_path / "s").exists()


def test_job_command_and_environment(tmp_path):
    from recgs_addon.blender import jobs

    argv = jobs.train_command("S", "O", {"mode": "3dgs", "max_minutes": None, "eager": True, "eager2": False,
                                         "caustic_k": 9}, init_ply="I.ply")
    assert argv[:3] == [sys.executable, "-m", "recgs_addon"]
    assert argv[3:] == ["train", "S", "--out", "O", "--mode", "3dgs", "--eager", "--caustic-k", "9", "--init-ply", "I.ply"]
    from recgs_addon import batch
    from recgs_addon.blender.properties import SETTINGS_OPTIONS

    parser = batch._parser()
    args = parser.parse_args(["S", "--out", "O", "--mode", "recgs", "--eager", "--caustic-k", "7",
                              "--warmup", "100", "--caustic-model", "additive"])
    assert batch.extra_train_args(parser, args, SETTINGS_OPTIONS) == ["--caustic-model", "additive", "--warmup", "100"]
    env = jobs.job_env()
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(ROOT)
    # runs from any working directory (as inside Blender) through PYTHONPATH alone
    job = jobs.Job("info", jobs.command("info", str(tmp_path / "missing.ply")), cwd=tmp_path)
    assert job.wait(60) == 1
    assert any("missing.ply" in line for line in job.stderr_tail)


def test_batch_trains_and_saves_a_blend(tiny_scene, tmp_path):
    out = tmp_path / "batch out"
    r = subprocess.run([sys.executable, str(ROOT / "recgs_addon/batch.py"), str(tiny_scene), "--out", str(out),
                        "--mode", "3dgs", "--iterations", "20", "--eager", "--holdout-every", "4"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[done] it 20" in r.stderr  # the job's progress lines are forwarded
    for name in ("scene.blend", "point_cloud.ply", "metrics.json", "train/checkpoint.pt"):
        assert (out / name).is_file(), name
    left = [p.name for p in out.rglob("*") if ".tmp" in p.name or p.name.endswith(("@", ".blend1"))]
    assert not left, left   # every file went through a temporary name and was renamed
    code = f"""
import json, sys
sys.path.insert(0, {str(ROOT)!r})
import bpy
from recgs_addon import blender as addon
from recgs_addon.blender.gaussian_object import gaussians_from_object, is_gaussian_object
from recgs_addon.core.io.ply import read_gaussian_ply
addon.register()
bpy.ops.wm.open_mainfile(filepath={str(out / 'scene.blend')!r})
objs = [o for o in bpy.data.objects if is_gaussian_object(o)]
g = gaussians_from_object(objs[0])
ply = read_gaussian_ply({str(out / 'point_cloud.ply')!r})
print("RESULT", json.dumps({{"gaussian_objects": len(objs), "n": len(g), "ply": len(ply),
    "same": bool((g.means == ply.means).all()),
    "cameras": len([o for o in bpy.data.objects if o.type == "CAMERA"]),
    "mode": bpy.context.scene.recgs.mode, "iterations": bpy.context.scene.recgs.iterations,
    "out_dir": objs[0]["recgs_out_dir"],
    "modifiers": [(m.type, m.node_group.name if m.type == "NODES" and m.node_group else None)
                  for m in objs[0].modifiers],
    "materials": sorted(m.name for m in bpy.data.materials if m.users)}}))
"""
    r2 = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r2.returncode == 0, r2.stderr[-3000:]
    res = json.loads(r2.stdout.split("RESULT ", 1)[1])
    assert res["gaussian_objects"] == 1 and res["n"] == res["ply"] > 0 and res["same"]
    assert res["cameras"] == 8 and res["mode"] == "3dgs" and res["iterations"] == 20
    assert res["out_dir"] == str(out / "train")
    assert [m for m in res["modifiers"] if m[0] == "NODES" and m[1]], res["modifiers"]  # the preview
    assert res["materials"], "the preview's material was not saved"


@pytest.mark.parametrize("case", ["missing", "no model"])
def test_batch_bad_folder_fails_clearly(tmp_path, case):
    scene = tmp_path / "relevé 2"
    if case == "no model":
        (scene / "images").mkdir(parents=True)
    r = subprocess.run([sys.executable, str(ROOT / "recgs_addon/batch.py"), "--", str(scene),
                        "--out", str(tmp_path / "o"), "--mode", "3dgs"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("batch: error:") and str(scene) in last, r.stderr[-2000:]
    assert not (tmp_path / "o" / "scene.blend").exists()


def _snapshot_module():
    spec = importlib.util.spec_from_file_location("panel_snapshot", ROOT / "tools/panel_snapshot.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_panel_draws_every_control(session):
    snap = _snapshot_module()
    scene, name, out = session
    idle = snap.snapshot(bpy.context, running=False)
    for text in ("== RecGS ==", "== Scene ==", "== Training ==", "== Advanced (closed) ==", "== Output ==",
                 "== Preview (closed) ==", "Scene Folder:", "(recgs.import_colmap)", "(recgs.reconstruct)",
                 "Video File:", "Max Frames: 300", "(recgs.import_video)", "Mode: 3DGS", "Time Limit (min):", "Budget:", "Downscale:", "Caustic Filter Size:",
                 "(recgs.train)", "(recgs.resume)", "(recgs.export_ply)", "(recgs.export_images)",
                 "(recgs.open_report)", f"{name}: 200 Gaussians"):
        assert text in idle, text
    assert "(recgs.cancel)" not in idle
    for k, v in snap.SAMPLE_RUNNING.items():
        setattr(scene.recgs, k, v)
    running = snap.snapshot(bpy.context, running=True)
    assert "(recgs.cancel)" in running and "(recgs.train)" not in running
    for text in ("Running: densify", "Iteration: 1,750", "Held-out PSNR: 21.74 dB", "Gaussians: 129,015",
                 "Elapsed: 1:39, remaining: 2:21"):
        assert text in running, text
    assert "Mode: 3DGS  (greyed out)" in running


def test_panel_settings_round_trip_through_the_train_command_line(bpy_session):
    """Settings -> the job's train command line -> parsed -> settings of a fresh scene: every
    setting the panel passes to a job comes back the same (the one SETTINGS table both ways)."""
    from recgs_addon.blender import jobs
    from recgs_addon.blender.properties import SETTINGS, apply_train_args, train_options
    from recgs_addon.cli import build_parser

    s = bpy.context.scene.recgs
    s.mode, s.max_minutes, s.iterations, s.budget_auto, s.budget = "recgs", 3.5, 700, False, 1234
    s.downscale, s.max_side, s.sh_degree, s.seed, s.holdout_every = 2, 800, 2, 7, 5
    s.checkpoint_every, s.eager, s.caustic_k, s.images, s.medium = 15, True, 9, "photos", "off"
    argv = jobs.train_command("S", "O", train_options(s))
    args = build_parser().parse_args(argv[3:])   # after [python, -m, recgs_addon]
    fresh = bpy.data.scenes.new("round trip").recgs
    apply_train_args(fresh, args)
    for key in SETTINGS:
        assert SETTINGS[key][0](fresh) == SETTINGS[key][0](s), key
    assert (fresh.budget_auto, fresh.budget, fresh.images, fresh.medium) == (False, 1234, "photos", "off")


def test_panel_progress_is_the_jobs_share_done(bpy_session):
    """The Training panel's bar shows the share done the job reports; the panel does not work
    it out again from its own time limit."""
    from types import SimpleNamespace

    from recgs_addon.blender import job_follow

    s = bpy.context.scene.recgs
    s.max_minutes = 1.0
    a = SimpleNamespace(job=SimpleNamespace(kind="train"), object_name="RecGS")
    job_follow._apply(a, s, {"event": "progress", "phase": "densify", "iteration": 3, "elapsed": 50.0,
                             "eta": None, "fraction": 0.1})
    assert s.progress == pytest.approx(0.1) and s.eta == -1.0
    job_follow._apply(a, s, {"event": "progress", "phase": "refine", "iteration": 9, "elapsed": 60.0,
                             "eta": 20.0, "fraction": 0.75})
    assert s.progress == pytest.approx(0.75) and s.eta == pytest.approx(20.0)
    # a job in blocks: its share done, and each block's step in the message
    job_follow._apply(a, s, {"event": "progress", "phase": "blocks 1/2 done", "iteration": 1500, "elapsed": 70.0,
                             "eta": 30.0, "fraction": 0.6, "loss": None, "psnr_test": None,
                             "blocks": [{"block": "block01", "iteration": 1000, "psnr_test": 27.5, "done": True},
                                        {"block": "block02", "iteration": 500, "psnr_test": None, "done": False}]})
    assert s.progress == pytest.approx(0.6) and s.phase == "blocks 1/2 done"
    assert s.message == "block01: done, 27.50 dB; block02: it 500"
