"""The compile switch: eager at once on a cold cache or without a compiler, compiled once warm."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from recgs_addon.core.train import compiling
from recgs_addon.core.train.compiling import CompileSwitch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RECGS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "elsewhere"))  # restored after
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache" / "numba"))
    monkeypatch.delenv("RECGS_NUMBA", raising=False)
    monkeypatch.setattr(compiling, "numba_importable", lambda: False)   # a machine without numba
    monkeypatch.setattr(compiling, "_numba_ready", lambda: False)
    return tmp_path / "cache"


@pytest.fixture
def numba_machine(cache, monkeypatch, tmp_path):
    """numba installed (its kernels load instantly here); the warm marker in a temp folder."""
    monkeypatch.setattr(compiling, "numba_importable", lambda: True)
    monkeypatch.setattr(compiling, "_numba_ready", lambda: True)
    m = tmp_path / "numba-warm"
    monkeypatch.setattr(compiling, "numba_marker", lambda: m)
    return m


def _no_compiler(monkeypatch, tmp_path):
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))     # nothing on it
    assert compiling.find_compiler() is None


def test_no_compiler_means_eager(cache, monkeypatch, tmp_path):
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))     # nothing on it
    assert compiling.find_compiler() is None
    sw = CompileSwitch(None)
    assert sw.state == "unavailable" and not sw.compiled()
    assert "no C++ compiler" in sw.summary()["reason"] and sw.proc is None


def test_no_compiler_warm_numba_from_the_first_step(numba_machine, monkeypatch, tmp_path):
    _no_compiler(monkeypatch, tmp_path)
    numba_machine.write_text("warm")
    sw = CompileSwitch(None)
    assert sw.compiled() == "numba" and sw.proc is None and sw.switched_at is None
    assert "numba" in sw.messages[0] and sw.summary()["numba"] == "ready"
    assert CompileSwitch(False).compiled() is False      # --eager: the torch oracle, always
    monkeypatch.setenv("RECGS_NUMBA", "0")
    assert CompileSwitch(None).compiled() is False       # numba refused


def _fake_numba_start(code):
    """A numba warm-up that runs ``code`` (MARKER bound to the warm marker's path)."""
    def start(self, cmd, extra_env, nice=True):
        assert "--numba" in cmd
        m = compiling.numba_marker()
        self.proc = subprocess.Popen([sys.executable, "-c", f"MARKER = {str(m)!r}\n{code}"],
                                     stderr=subprocess.PIPE)
    return start


def test_no_compiler_cold_numba_trains_eager_then_switches(numba_machine, monkeypatch, tmp_path):
    _no_compiler(monkeypatch, tmp_path)
    monkeypatch.setattr(CompileSwitch, "_start", _fake_numba_start(
        "import pathlib, time; time.sleep(0.3); pathlib.Path(MARKER).write_text('ok')"))
    heard = []
    sw = CompileSwitch(None, log=heard.append)
    assert sw.numba == "warming" and sw.compiled() is False    # the first step does not wait
    sw.note_step(5)
    sw.proc.wait()
    assert sw.compiled() == "numba" and sw.switched_at == 5
    assert any("cold" in m for m in heard) and any("from step 5" in m for m in heard)
    assert CompileSwitch(None).compiled() == "numba"          # the next run: warm from the start


def test_no_compiler_failed_numba_warm_up_stays_eager(numba_machine, monkeypatch, tmp_path):
    _no_compiler(monkeypatch, tmp_path)
    monkeypatch.setattr(CompileSwitch, "_start", _fake_numba_start(
        "import sys; sys.stderr.write('LoweringError: boom\\n'); sys.exit(1)"))
    sw = CompileSwitch(None)
    sw.proc.wait()
    assert sw.compiled() is False and sw.numba == "failed"
    assert "LoweringError: boom" in sw.summary()["reason"] and not numba_machine.exists()


def test_numba_that_fails_to_load_means_eager(numba_machine, monkeypatch, tmp_path):
    _no_compiler(monkeypatch, tmp_path)
    numba_machine.write_text("warm")
    monkeypatch.setattr(compiling, "_numba_ready", lambda: False)
    sw = CompileSwitch(None)
    assert sw.compiled() is False and sw.numba == "failed" and "eager" in sw.messages[0]


def test_numba_on_request_even_with_a_compiler(numba_machine, monkeypatch):
    numba_machine.write_text("warm")
    monkeypatch.setenv("RECGS_NUMBA", "1")
    monkeypatch.setattr(compiling, "find_compiler", lambda: "/usr/bin/c++")
    sw = CompileSwitch(None)
    assert sw.compiled() == "numba" and sw.proc is None       # no torch.compile warm-up


def test_numba_first_even_with_a_compiler(numba_machine, monkeypatch):
    """numba is the default wherever it is installed (the fastest path measured): warm, from
    the first step with no torch.compile warm-up; cold, eager while its own warm-up runs."""
    monkeypatch.setattr(compiling, "find_compiler", lambda: "/usr/bin/c++")
    # the fake asserts that the warm-up started is numba's (--numba), not inductor's
    monkeypatch.setattr(CompileSwitch, "_start", _fake_numba_start("import time; time.sleep(30)"))
    sw = CompileSwitch(None)                                   # cold numba cache
    assert sw.numba == "warming" and sw.compiled() is False and sw.proc is not None
    sw.close()
    numba_machine.write_text("warm")
    sw = CompileSwitch(None)
    assert sw.compiled() == "numba" and sw.proc is None        # no warm-up of either kind


def test_torch_compile_when_numba_fails_or_is_refused(numba_machine, monkeypatch):
    numba_machine.write_text("warm")
    monkeypatch.setattr(compiling, "find_compiler", lambda: "/usr/bin/c++")
    monkeypatch.setattr(CompileSwitch, "_start", _fake_start(
        "import pathlib, time; time.sleep(0.3); p = pathlib.Path(MARKER); "
        "p.parent.mkdir(parents=True, exist_ok=True); p.write_text('ok')"))
    monkeypatch.setattr(compiling, "_numba_ready", lambda: False)   # numba's kernels fail to load
    sw = CompileSwitch(None)
    assert sw.numba == "failed" and sw.state == "warming" and sw.compiled() is False
    sw.proc.wait()
    assert sw.compiled() is True
    monkeypatch.setattr(compiling, "_numba_ready", lambda: True)
    monkeypatch.setenv("RECGS_NUMBA", "0")
    assert CompileSwitch(None).compiled() is True             # refused: torch.compile (warm now)


def test_explicit_choices_are_kept(cache):
    assert CompileSwitch(False).compiled() is False
    assert CompileSwitch(True).compiled() is True


def test_cache_goes_to_the_user_folder(cache):
    d = compiling.use_user_cache()
    assert d.parent == cache and d.name.startswith("inductor-torch")
    import os
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(d)


def test_warm_key_follows_threads_and_sources(cache):
    assert compiling.warm_key(1) != compiling.warm_key(2)
    assert compiling.warm_key(2) == compiling.warm_key(2)


def _fake_start(code):
    """A warm-up that runs ``code`` (with MARKER bound to the marker path) instead of compiling."""
    def start(self, cmd, extra_env, nice=True):
        m = compiling.marker()
        self.proc = subprocess.Popen([sys.executable, "-c", f"MARKER = {str(m)!r}\n{code}"],
                                     stderr=subprocess.PIPE)
    return start


def test_cold_cache_trains_eager_then_switches(cache, monkeypatch):
    if compiling.find_compiler() is None:
        pytest.skip("no C++ compiler here")
    monkeypatch.setattr(CompileSwitch, "_start", _fake_start(
        "import pathlib, time; time.sleep(0.3); p = pathlib.Path(MARKER); "
        "p.parent.mkdir(parents=True, exist_ok=True); p.write_text('ok')"))
    heard = []
    sw = CompileSwitch(None, log=heard.append)
    assert sw.state == "warming" and sw.compiled() is False   # the first step does not wait
    sw.note_step(7)
    sw.proc.wait()
    assert sw.compiled() is True and sw.switched_at == 7
    assert any("cold" in m for m in heard) and any("from step 7" in m for m in heard)
    # the next run finds the cache warm and compiles from its first step
    assert CompileSwitch(None).state == "compiled"


def test_failed_warm_up_stays_eager(cache, monkeypatch):
    if compiling.find_compiler() is None:
        pytest.skip("no C++ compiler here")
    monkeypatch.setattr(CompileSwitch, "_start", _fake_start(
        "import sys; sys.stderr.write('CppCompileError: boom\\n'); sys.exit(1)"))
    sw = CompileSwitch(None)
    sw.proc.wait()
    assert sw.compiled() is False and sw.state == "unavailable"
    assert "CppCompileError: boom" in sw.summary()["reason"]
    assert not compiling.is_warm()


def test_close_stops_a_running_warm_up(cache, monkeypatch):
    if compiling.find_compiler() is None:
        pytest.skip("no C++ compiler here")
    monkeypatch.setattr(CompileSwitch, "_start", _fake_start("import time; time.sleep(60)"))
    sw = CompileSwitch(None)
    proc = sw.proc
    sw.close()
    assert proc.poll() is not None and sw.proc is None


@pytest.mark.slow
def test_real_warm_up_covers_a_training_run(tmp_path):
    """The warm-up subprocess fills a fresh cache; a run after it compiles from its first step
    and finds every graph of its training steps and evaluations in the cache (at most a few
    small graphs of its own: under the default clone/split, two at step 11 and one when the SH
    degree rises, on the sample; none under MCMC)."""
    if compiling.find_compiler() is None:
        pytest.skip("no C++ compiler here")
    env = {"RECGS_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT),
           "RECGS_NUMBA": "0"}   # torch.compile's path (numba is the default where installed)
    import os
    env = {**os.environ, **env}
    subprocess.run([sys.executable, "-m", "recgs_addon.core.train.compiling", "--max-degree", "1",
                    "--threads", str(torch.get_num_threads())], env=env, check=True, cwd=ROOT)
    probe = (
        "import json, sys, torch, torch._dynamo.utils as u\n"
        "from recgs_addon.core.train.config import preset\n"
        "from recgs_addon.core.train.trainer import make_trainer\n"
        f"tr = make_trainer({str(ROOT / 'data' / 'sample')!r}, preset('default', iterations=30, sh_degree=1, holdout_every=8))\n"
        "state = tr.compiler.state\n"
        "for _ in range(20): tr.train_step()\n"
        "tr.sh_degree = 1\n"
        "for _ in range(10): tr.train_step()\n"
        "tr.evaluate()\n"
        "print(json.dumps({'state': state, 'miss': u.counters['inductor']['fxgraph_cache_miss'],"
        " 'hit': u.counters['inductor']['fxgraph_cache_hit']}))\n")
    out = subprocess.run([sys.executable, "-c", probe], env=env, check=True, cwd=ROOT,
                         capture_output=True, text=True).stdout.strip().splitlines()[-1]
    got = json.loads(out)
    assert got["state"] == "compiled"
    assert got["hit"] >= 10 and got["miss"] <= 3, got


def test_warm_up_borrows_a_core_when_none_is_spare(cache, monkeypatch):
    """On a machine whose cores all train, the warm-up gets one of them until it is done, and
    the trainer gets it back before its first compiled step (the cache is keyed on threads)."""
    if compiling.find_compiler() is None:
        pytest.skip("no C++ compiler here")
    real_popen = subprocess.Popen
    seen = {}

    def fake_popen(cmd, env=None, **kw):
        seen["cmd"], seen["env"] = cmd, env
        m = compiling.marker(int(cmd[cmd.index("--threads") + 1]))
        code = f"import pathlib; p = pathlib.Path({str(m)!r}); p.parent.mkdir(parents=True, exist_ok=True); p.write_text('ok')"
        return real_popen([sys.executable, "-c", code], stderr=subprocess.PIPE)

    monkeypatch.setattr(compiling.subprocess, "Popen", fake_popen)
    monkeypatch.setattr(compiling.os, "cpu_count", lambda: 2)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        sw = CompileSwitch(None)
        assert sw.state == "warming" and torch.get_num_threads() == 1
        assert seen["cmd"][seen["cmd"].index("--threads") + 1] == "2"
        assert seen["env"]["TORCHINDUCTOR_COMPILE_THREADS"] == "1"
        sw.proc.wait()
        assert sw.compiled() is True and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.slow
def test_real_numba_warm_up_fills_the_user_cache(tmp_path):
    """The numba warm-up subprocess compiles into RecGS's per-user cache and leaves the marker
    (the rasterizer's kernels and the loss's SSIM); a run without a compiler then takes numba's
    path from its first step, loading (not compiling) the kernels."""
    import os
    env = {**os.environ, "RECGS_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("RECGS_NUMBA", None)
    subprocess.run([sys.executable, "-m", "recgs_addon.core.train.compiling", "--numba"], env=env,
                   check=True, cwd=ROOT)
    numba_dir = tmp_path / "cache" / "numba"
    assert list(numba_dir.glob("recgs-warm-*")) and list(numba_dir.rglob("*.nbi"))
    assert {p.name.split(".")[1].split("-")[0] for p in numba_dir.rglob("_numba_ssim.*.nbi")} >= {
        "forward_rows", "forward_cols", "backward_rows", "backward_cols"}
    (tmp_path / "bin").mkdir()
    probe = ("import json, time\n"
             "from recgs_addon.core.train.compiling import CompileSwitch\n"
             "t = time.perf_counter(); sw = CompileSwitch(None)\n"
             "print(json.dumps({'path': sw.compiled(), 's': time.perf_counter() - t}))\n")
    out = subprocess.run([sys.executable, "-c", probe], env={**env, "PATH": str(tmp_path / "bin")},
                         check=True, cwd=ROOT, capture_output=True, text=True).stdout.strip().splitlines()[-1]
    assert json.loads(out)["path"] == "numba"
