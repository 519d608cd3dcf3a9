"""The training-engine installer without Blender and without the network: pip is replaced by
small scripts that fail, hang or write a fake torch."""
import os
import subprocess
import sys
import time

import pytest

from recgs_addon import engine_install as ei

FAKE_TORCH = ("import os, sys; d = sys.argv[1]; os.makedirs(os.path.join(d, 'torch'));"
              "open(os.path.join(d, 'torch', '__init__.py'), 'w').write(\"__version__ = %r\")")


def _run(inst, timeout=60):
    t0 = time.monotonic()
    while inst.poll() is None:
        assert time.monotonic() - t0 < timeout, inst.progress.lines
        time.sleep(0.05)
    return inst.status


def _fake_install(root, version="9.9"):
    return ei.Installer(root, command=[sys.executable, "-c", FAKE_TORCH % version, "{target}"])


def test_success_swaps_in_and_the_worker_sees_it(tmp_path):
    assert ei.installed_engine(tmp_path) is None
    inst = _fake_install(tmp_path)
    assert _run(inst) == "done", inst.message
    site = ei.installed_engine(tmp_path)
    assert site == ei.engine_site(tmp_path) and not inst.tmp.exists()
    assert ei.engine_info(site)["torch"] == "9.9"
    env = ei.worker_env(tmp_path / "pkg", site, base={"PYTHONPATH": "/elsewhere"})
    assert env["PYTHONPATH"].split(os.pathsep)[:2] == [str(tmp_path / "pkg"), str(site)]
    assert env["PYTHONPATH"].endswith("/elsewhere") and env["PYTHONNOUSERSITE"] == "1"
    r = subprocess.run([sys.executable, "-c", "import torch; print(torch.__version__)"], env=env,
                       capture_output=True, text=True)
    assert r.stdout.strip() == "9.9", r.stderr
    assert _run(_fake_install(tmp_path, "10.0")) == "done"           # a reinstall replaces it
    assert ei.engine_info(site)["torch"] == "10.0"
    assert sorted(p.name for p in site.parent.iterdir()) == ["site-packages"]


@pytest.mark.parametrize("output, words", [
    ("ERROR: Could not find a version that satisfies the requirement torch==2.13.0", "Could not find"),
    ("WARNING: Retrying ... NewConnectionError: Failed to establish a new connection\n"
     "ERROR: Could not find a version", "network failed"),
    ("Installing collected packages: numba, torch\n"
     "ERROR: Could not install packages due to an OSError: [Errno 28] No space left on device",
     "GB free on the disk"),
])
def test_pip_failure_leaves_nothing(tmp_path, output, words):
    code = f"import sys; print('Collecting torch==2.13.0'); print({output!r}); sys.exit(1)"
    inst = ei.Installer(tmp_path, command=[sys.executable, "-c", code])
    assert _run(inst) == "failed" and words in inst.message
    assert not inst.tmp.exists() and ei.installed_engine(tmp_path) is None


def test_installed_but_not_importable_is_refused(tmp_path):
    inst = ei.Installer(tmp_path, command=[sys.executable, "-c", "pass"])   # pip "succeeds", no torch
    assert _run(inst) == "failed" and "holds no torch" in inst.message
    assert not inst.tmp.exists() and ei.installed_engine(tmp_path) is None


def test_cancel_and_leftovers(tmp_path):
    assert _run(_fake_install(tmp_path)) == "done"
    inst = ei.Installer(tmp_path, command=[sys.executable, "-c", "import time; time.sleep(60)"])
    assert inst.tmp.is_dir()
    inst.cancel()
    assert inst.status == "cancelled" and not inst.tmp.exists()
    assert ei.engine_info(ei.installed_engine(tmp_path))["torch"] == "9.9"   # the old engine stays
    inst.tmp.mkdir(parents=True)                                    # a crashed attempt's folder
    (inst.tmp / "junk").write_text("x")
    assert _run(_fake_install(tmp_path, "11")) == "done" and not inst.tmp.exists()


def test_progress_lines():
    p = ei.Progress()
    ei.parse_line("Collecting torch==2.13.0", p)
    assert (p.phase, p.package) == ("resolving", "torch==2.13.0")
    ei.parse_line("  Downloading https://x/torch-2.13.0%2Bcpu-cp311-cp311-linux_x86_64.whl (191.8 MB)", p)
    assert p.phase == "downloading" and p.package.startswith("torch-2.13.0")
    ei.parse_line("Progress 50 of 200", p)
    assert p.fraction == 0.25
    ei.parse_line("Installing collected packages: torch", p)
    assert p.phase == "installing"


def test_pip_command(monkeypatch):
    monkeypatch.delenv(ei.PIP_ARGS_ENV, raising=False)
    cmd = ei.pip_command("/t", platform="linux", requirements=ei.engine_requirements("1.26.4"))
    assert cmd[-4:] == ["torch==2.13.0", "av==18.1.0", "numba==0.61.2", "numpy==1.26.4"]
    assert cmd[cmd.index("--target") + 1] == "/t"
    assert cmd[cmd.index("--extra-index-url") + 1] == ei.TORCH_CPU_INDEX
    assert "--extra-index-url" not in ei.pip_command("/t", platform="win32")
    monkeypatch.setenv(ei.PIP_ARGS_ENV, "--index-url http://mirror/simple")
    cmd = ei.pip_command("/t", platform="linux")
    assert "http://mirror/simple" in cmd and ei.TORCH_CPU_INDEX not in cmd


def test_engine_requirements_pin_numba_to_blenders_numpy():
    """numba comes with the numpy of the Python that installs (pip --target puts a copy in the
    engine, ahead of Blender's on the worker's path: the same version is harmless); without a
    numpy in numba's range the engine is torch alone (training on eager torch)."""
    assert ei.engine_requirements("1.26.4") == ("torch==2.13.0", ei.PYAV_REQUIREMENT, ei.NUMBA_REQUIREMENT,
                                                "numpy==1.26.4")
    assert ei.engine_requirements("2.2.6")[-1] == "numpy==2.2.6"
    for v in ("1.23.5", "2.3.0", None, "garbage"):
        assert ei.engine_requirements(v) == ei.ENGINE_REQUIREMENTS == ("torch==2.13.0", "av==18.1.0"), v
    assert ei.pip_command("/t")[-1] == ei.engine_requirements()[-1]    # the default: this Python's numpy


def test_engine_dir_env(monkeypatch, tmp_path):
    monkeypatch.setenv(ei.ENGINE_DIR_ENV, str(tmp_path))
    assert ei.installed_engine(None) == tmp_path


def test_batch_mode_finds_the_engine_the_addon_installed(tmp_path, monkeypatch):
    """``blender -b --python batch.py`` trains with the engine in the user's extension folder."""
    from recgs_addon import batch

    class FakeUtils:
        @staticmethod
        def user_resource(kind):
            assert kind == "EXTENSIONS"
            return str(tmp_path / "extensions")

    class FakeBpy:
        utils = FakeUtils

    monkeypatch.delenv(ei.ENGINE_DIR_ENV, raising=False)
    assert batch.use_installed_engine(FakeBpy) is None          # nothing installed yet
    root = tmp_path / "extensions" / ".user" / "user_default" / "recgs"
    site = ei.engine_site(root)
    site.mkdir(parents=True)
    assert batch.use_installed_engine(FakeBpy) is None          # half an install does not count
    (site / ei.MARKER).write_text("{}")
    assert batch.use_installed_engine(FakeBpy) == str(site)
    assert os.environ[ei.ENGINE_DIR_ENV] == str(site)           # what the add-on's jobs read
    monkeypatch.setenv(ei.ENGINE_DIR_ENV, "/chosen")
    assert batch.use_installed_engine(FakeBpy) == "/chosen"     # an explicit choice wins


def test_an_engine_without_numba_or_with_another_torch_asks_for_an_update(tmp_path):
    """An engine installed before numba was part of it (its marker has no numba) trains on
    eager torch: the panel offers *Update Training Engine*; likewise for another torch. An
    engine without numba where numba cannot come (numpy outside its range) is up to date."""
    wanted = ("torch==2.13.0", "numba==0.61.2", "numpy==1.26.4")
    assert "no numba" in ei.update_reason({"torch": "2.13.0+cpu"}, wanted)
    assert "no numba" in ei.update_reason({"torch": "2.13.0", "numba": None}, wanted)
    assert ei.update_reason({"torch": "2.13.0+cpu", "numba": "0.61.2"}, wanted) is None
    assert "torch 2.12.1" in ei.update_reason({"torch": "2.12.1+cpu", "numba": "0.61.2"}, wanted)
    assert ei.update_reason({"torch": "2.13.0"}, ("torch==2.13.0",)) is None
    # the marker an install writes is what the check reads (numba: whatever the fresh Python
    # that checks the install imports, here this one's if it has numba)
    assert _run(_fake_install(tmp_path, "2.13.0")) == "done"
    info = ei.engine_info(ei.installed_engine(tmp_path))
    assert (ei.update_reason(info, wanted) is None) == bool(info.get("numba"))
    assert "no numba" in ei.update_reason({**info, "numba": None}, wanted)


def test_an_engine_without_pyav_asks_for_an_update():
    """An engine installed before Import Video has torch and numba but no PyAV: the panel offers
    *Update Training Engine*; the marker records the PyAV the install holds."""
    wanted = ("torch==2.13.0", "av==18.1.0", "numba==0.61.2", "numpy==1.26.4")
    assert "no PyAV" in ei.update_reason({"torch": "2.13.0+cpu", "numba": "0.61.2"}, wanted)
    assert ei.update_reason({"torch": "2.13.0+cpu", "numba": "0.61.2", "av": "18.1.0"}, wanted) is None
