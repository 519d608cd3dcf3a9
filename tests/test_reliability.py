"""Outputs appear whole or not at all; a full disk says so and keeps what was there."""
import builtins
import errno
import io
import os

import numpy as np
import pytest
import torch

from recgs_addon.core.errors import RecGSError
from recgs_addon.core.io.atomic import OutputError, atomic_path
from recgs_addon.core.io.images import read_image, write_image
from recgs_addon.core.io.ply import read_gaussian_ply, write_gaussian_ply
from recgs_addon.core.model.gaussians import GaussianSet
from recgs_addon.core.train.checkpoint import load_checkpoint, save_checkpoint


def gaussians(n, seed=0):
    rng = np.random.default_rng(seed)
    return GaussianSet(means=rng.normal(size=(n, 3)).astype(np.float32),
                       log_scales=np.full((n, 3), -2.0, np.float32),
                       quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                       logit_opacities=np.zeros(n, np.float32),
                       sh=rng.normal(size=(n, 1, 3)).astype(np.float32))


class DiskFullAfter:
    """``open`` whose files (opened for writing under ``folder``) raise ENOSPC once more than
    ``limit`` bytes went into them: a disk that fills up in the middle of a write."""

    def __init__(self, folder, limit):
        self.folder, self.limit, self.real = str(folder), limit, builtins.open

    def __call__(self, file, mode="r", *args, **kw):
        f = self.real(file, mode, *args, **kw)
        if "w" not in mode or not str(file).startswith(self.folder):
            return f
        limit, write = self.limit, f.write
        written = [0]

        def full_write(data):
            written[0] += len(data)
            if written[0] > limit:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return write(data)

        f.write = full_write
        return f


def leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


def test_ply_export_on_a_full_disk_keeps_the_previous_one(tmp_path, monkeypatch):
    path = tmp_path / "point_cloud.ply"
    write_gaussian_ply(path, gaussians(50))
    before = path.read_bytes()
    monkeypatch.setattr(builtins, "open", DiskFullAfter(tmp_path, 1000))
    with pytest.raises(OutputError, match="point_cloud.ply.*disk is full.*previous one is kept"):
        write_gaussian_ply(path, gaussians(5000, seed=1))
    monkeypatch.undo()
    assert path.read_bytes() == before and len(read_gaussian_ply(path)) == 50
    assert leftovers(tmp_path) == []


def test_checkpoint_on_a_full_disk_keeps_the_previous_one(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"step": 100, "params": {"means": torch.zeros(10, 3)}})
    monkeypatch.setattr(builtins, "open", DiskFullAfter(tmp_path, 500))
    with pytest.raises(RecGSError, match="checkpoint.pt.*checkpoint.*disk is full"):
        save_checkpoint(path, {"step": 200, "params": {"means": torch.zeros(100_000, 3)}})
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 100
    assert leftovers(tmp_path) == []


def test_first_write_on_a_full_disk_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(builtins, "open", DiskFullAfter(tmp_path, 10))
    with pytest.raises(OutputError, match="disk is full") as info:
        write_gaussian_ply(tmp_path / "new.ply", gaussians(100))
    assert "previous one" not in str(info.value)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_image_write_failure_keeps_the_previous_image(tmp_path, monkeypatch):
    path = tmp_path / "view.png"
    write_image(path, np.full((8, 8, 3), 0.5, np.float32))
    real_replace = os.replace

    def failing_replace(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OutputError, match="view.png.*image.*disk is full"):
        write_image(path, np.zeros((8, 8, 3), np.float32))
    monkeypatch.setattr(os, "replace", real_replace)
    assert np.allclose(read_image(path), 128 / 255, atol=1 / 255)
    assert leftovers(tmp_path) == []


def test_atomic_path_leaves_the_old_file_when_the_writer_raises(tmp_path):
    path = tmp_path / "report.md"
    path.write_text("old")
    with pytest.raises(ValueError):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise ValueError("writer bug")
    assert path.read_text() == "old" and leftovers(tmp_path) == []


# ------------------------------------------------------------------ one job per output folder

import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from recgs_addon.core.io.lock import FolderBusyError, folder_lock  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def hold_lock(folder):
    """A process that holds ``folder``'s lock until killed; returns once it holds it."""
    code = ("import sys, time; sys.path.insert(0, sys.argv[2])\n"
            "from recgs_addon.core.io.lock import folder_lock\n"
            "with folder_lock(sys.argv[1]):\n    print('held', flush=True); time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder), str(ROOT)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_second_job_on_a_busy_folder_refuses_and_a_killed_job_frees_it(tmp_path):
    holder = hold_lock(tmp_path)
    try:
        with pytest.raises(FolderBusyError, match=f"{tmp_path}.*another training job.*pid {holder.pid}"):
            with folder_lock(tmp_path):
                pass
        res = subprocess.run([sys.executable, "-m", "recgs_addon", "train", str(ROOT / "data" / "sample"),
                              "--out", str(tmp_path), "--iterations", "5", "--eager"],
                             cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert res.returncode == 1
        assert "another training job is writing to this folder" in res.stderr
        assert "Traceback" not in res.stderr
        assert not (tmp_path / "checkpoint.pt").exists()      # the refused job wrote nothing
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with folder_lock(tmp_path):                              # the kill left no stale lock
        pass


# ------------------------------------------------------------------ settings no run can use

@pytest.mark.parametrize("argv,msg", [
    (["--iterations", "-5"], "iterations must be at least 1, got -5"),
    (["--iterations", "0"], "iterations must be at least 1, got 0"),
    (["--max-minutes", "nan"], "the time limit must be a number of minutes above 0, got nan"),
    (["--max-minutes", "-1"], "the time limit must be a number of minutes above 0, got -1.0"),
    (["--holdout-every", "-1"], "holdout every must be 0 (hold out none) or a positive number, got -1"),
    (["--seed", "-1"], "seed must be a whole number from 0 to 2^64 - 1, got -1"),
    (["--seed", "100000000000000000000000"], "seed must be a whole number from 0 to 2^64 - 1"),
    (["--checkpoint-every", "nan"], "--checkpoint-every must be a number of seconds >= 0, got nan"),
    (["--checkpoint-every", "-5"], "--checkpoint-every must be a number of seconds >= 0, got -5.0"),
    (["--mode", "recgs", "--warmup", "-1"], "warmup must be 0 or more steps, got -1"),
    (["--mode", "recgs", "--max-recurrences", "-1"], "max recurrences must be 0 or more, got -1"),
    (["--mode", "recgs", "--recurrence-tol", "nan"], "recurrence tolerance must be a number >= 0, got nan"),
    (["--mode", "recgs", "--robust-k", "nan"], "robust trimming k must be a number >= 0 (0 = off), got nan"),
    (["--mode", "recgs", "--pass-min", "0"], "the passes a pixel needs must be at least 1, got 0"),
])
def test_train_refuses_settings_no_run_can_use(tmp_path, capsys, argv, msg):
    """Regression (outside trial): these were accepted: a NaN time limit or tolerance ran on
    with the limit ignored, a negative iteration count 'finished' at step 0, a negative seed
    or one above 2^64 ended in a traceback from numpy or torch. Each is now one error line,
    before any data is read or any folder made."""
    from recgs_addon.cli import main
    code = main(["train", str(ROOT / "data" / "sample"), "--out", str(tmp_path / "out"), "--eager", *argv])
    err = capsys.readouterr().err
    assert code == 1 and f"error: {msg}" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["train", "render"])
def test_an_output_folder_that_is_a_file_or_cannot_be_made(tmp_path, capsys, command):
    """Regression (outside trial): ``--out`` naming a file, or a folder that cannot be created,
    ended in a FileExistsError / FileNotFoundError traceback; now one line naming it."""
    from recgs_addon.cli import main
    from recgs_addon.core.io.ply import write_gaussian_ply
    sample = ROOT / "data" / "sample"
    model = tmp_path / "m.ply"
    write_gaussian_ply(model, gaussians(20))
    head = ["train", str(sample)] if command == "train" else ["render", str(model), str(sample)]
    tail = ["--eager", "--iterations", "1"] if command == "train" else ["--eager", "--names", "view_001.png"]
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    for out, msg in ((afile, f"{afile}: is a file, not a folder"),
                     (afile / "out", f"{afile / 'out'}: cannot create the output folder: Not a directory")):
        code = main(head + ["--out", str(out)] + tail)
        err = capsys.readouterr().err
        assert code == 1 and f"error: {msg}" in err and "Traceback" not in err, err
    assert afile.read_text() == "mine"


def test_render_refuses_downscale_zero(tmp_path, capsys):
    """Regression (outside trial): ``render --downscale 0`` ended in a traceback."""
    from recgs_addon.cli import main
    from recgs_addon.core.io.ply import write_gaussian_ply
    write_gaussian_ply(tmp_path / "m.ply", gaussians(20))
    code = main(["render", str(tmp_path / "m.ply"), str(ROOT / "data" / "sample"), "--out", str(tmp_path / "r"),
                 "--downscale", "0"])
    err = capsys.readouterr().err
    assert code == 1 and "error: --downscale must be an integer >= 1, got 0" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_copied_outputs_on_a_full_disk_keep_the_previous_copy(tmp_path, monkeypatch):
    """Batch mode copies the job's report and caustic-free images, and Export Caustic-Free
    Images copies the images, through core/io/atomic.copy_file: a disk that fills during the
    copy leaves the previous copy (or none) and no partial file."""
    import shutil

    from recgs_addon.core.io.atomic import copy_file, copy_tree
    src = tmp_path / "job"
    (src / "decaustic").mkdir(parents=True)
    for i in range(3):
        write_image(src / "decaustic" / f"v{i}.png", np.full((8, 8, 3), 0.1 * i, np.float32))
    out = tmp_path / "out"
    copy_tree(src / "decaustic", out / "decaustic")
    before = {p.name: p.read_bytes() for p in (out / "decaustic").iterdir()}
    write_image(src / "decaustic" / "v1.png", np.ones((8, 8, 3), np.float32))

    def full_disk(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "sendfile", full_disk)          # shutil's fast copy on Linux
    monkeypatch.setattr(shutil, "copyfileobj", full_disk)  # ... and its fallback
    with pytest.raises(OutputError, match=r"v0.png: could not write the image: the disk is full \(the previous one is kept\)"):
        copy_tree(src / "decaustic", out / "decaustic", "image")
    with pytest.raises(OutputError, match=r"new.md: could not write the report: the disk is full$"):
        copy_file(src / "decaustic" / "v1.png", out / "new.md", "report")
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in (out / "decaustic").iterdir()} == before
    assert leftovers(out / "decaustic") == [] and sorted(p.name for p in out.iterdir()) == ["decaustic"]


def test_import_command_refuses_an_output_folder_that_is_a_file(tmp_path):
    """Regression (outside trial): ``import SCENE --out FILE`` ended in a FileExistsError traceback."""
    pytest.importorskip("bpy")
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    r = subprocess.run([sys.executable, "-m", "recgs_addon", "import", str(ROOT / "data" / "sample"), "--out", str(afile)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert f"error: {afile}: is a file, not a folder" in r.stderr and afile.read_text() == "mine"


def test_import_command_writes_whole_files_and_no_backups(tmp_path):
    """import writes scene.blend (through a temporary, saved as a copy: no .blend1 backup when
    it replaces an earlier one), point_cloud.ply and the report, and no temporaries."""
    pytest.importorskip("bpy")
    out = tmp_path / "imported"
    for _ in range(2):
        r = subprocess.run([sys.executable, "-m", "recgs_addon", "import", str(ROOT / "data" / "sample"),
                            "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["point_cloud.ply", "report.json", "report.md", "scene.blend"]
    assert len(read_gaussian_ply(out / "point_cloud.ply")) == 5000


# ------------------------------------------------------------------ a full disk inside a job and an operator

@pytest.fixture(scope="module")
def small_survey(tmp_path_factory):
    from conftest import write_rendered_scene
    root = tmp_path_factory.mktemp("rel") / "scene"
    write_rendered_scene(root, n_views=8, width=40, height=30, n_gauss=200)
    return root


def test_a_job_whose_disk_fills_during_a_checkpoint_keeps_the_previous_one(small_survey, tmp_path, capsys, monkeypatch):
    """The disk fills in the middle of the job's second checkpoint (it checkpoints every step
    here): the job stops with one error line saying so, exit code 1, and the first checkpoint
    (and the PLY written with it) still load; no temporary is left."""
    from recgs_addon.cli import main
    from recgs_addon.core.train import checkpoint as ckpt_mod
    out = tmp_path / "out"
    real, calls = ckpt_mod.save_checkpoint, []

    def second_fills_the_disk(path, state):
        calls.append(state["step"])
        if len(calls) < 2:
            return real(path, state)
        disk = DiskFullAfter(out, 2000)
        monkeypatch.setattr(builtins, "open", disk)
        try:
            return real(path, state)
        finally:
            monkeypatch.setattr(builtins, "open", disk.real)
    monkeypatch.setattr(ckpt_mod, "save_checkpoint", second_fills_the_disk)
    code = main(["train", str(small_survey), "--out", str(out), "--eager", "--iterations", "20",
                 "--checkpoint-every", "0", "--holdout-every", "4"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert code == 1 and err == [f"error: {out / 'checkpoint.pt'}: could not write the checkpoint: the disk is full "
                                 "(the previous one is kept)"], err
    assert load_checkpoint(out / "checkpoint.pt")["step"] == calls[0] == 1 and calls[1] == 2
    assert len(read_gaussian_ply(out / "point_cloud.ply")) > 0
    assert leftovers(out) == []
