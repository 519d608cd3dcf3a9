"""The fast rasterizer paths without waiting for a compiler.

Two paths are faster than eager torch: ``torch.compile`` (needs a C++ compiler at run time,
which most Windows and macOS machines lack; a cold cache costs one to four minutes of C++
compilation) and numba's kernels (LLVM ships inside numba's wheels: no compiler needed; a cold
cache costs ~15 s of one core; core/render/numba_kernels.py). :class:`CompileSwitch` decides,
step by step, which path the trainer takes:

- no compiler on ``PATH``: numba's path where numba is installed (else eager torch, said once,
  ``state == "unavailable"``). With numba's cache warm (a marker this module writes once a
  warm-up has compiled every kernel) from the first step; cold, the eager path at once while a
  background process (``python -m recgs_addon.core.train.compiling --numba``, lowered
  priority) fills the cache, then numba from the next step (loading the cached kernels takes
  about a second); if that fails, training stays eager.
- a compiler: numba's path all the same where numba is installed (it was the fastest path
  measured, and it never waits minutes for a compiler; :meth:`CompileSwitch._automatic`).
  Without numba (or if its kernels fail to load), torch.compile. A warm cache (a marker this
  module writes once a warm-up has compiled every graph a training step and an evaluation
  use): compiled from the first step (tracing the graphs again costs about ten seconds; the
  C++ compiler does not run). A cold cache: the eager path at once, while a background process
  (``python -m recgs_addon.core.train.compiling``) fills the cache with a small synthetic
  render at every SH degree; when it has finished, the next step switches to the compiled
  path. If it fails, training stays on the path it is on.
- ``RECGS_NUMBA=0``: never numba (torch.compile where a compiler is); ``RECGS_NUMBA=1``: the
  default, said explicitly.

All paths give the same numbers to float32 rounding (tests/test_rasterizer.py), so a switch
mid-run changes nothing but speed.

Both caches go to a per-user folder that survives reboots (:func:`user_cache_dir`), not
torch's default under ``/tmp`` or numba's beside the sources.
"""
from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional

import torch

#: Sources whose change invalidates the warm marker (what the compiled graphs are made of).
_SOURCES = ("render/projection.py", "render/rasterizer.py", "render/chunks.py", "render/kernels.py",
            "render/tiles.py", "render/composite.py", "render/numba_path.py", "render/rowgrads.py",
            "model/sh.py", "train/compiling.py")
_CORE = Path(__file__).resolve().parents[1]


def user_cache_dir() -> Path:
    """RecGS's per-user cache: ``RECGS_CACHE_DIR``, else the platform's cache folder."""
    if os.environ.get("RECGS_CACHE_DIR"):
        return Path(os.environ["RECGS_CACHE_DIR"])
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "recgs"


def inductor_dir() -> Path:
    """Where torch.compile's caches go: per user, beside RecGS's other caches. (Not
    ``TORCHINDUCTOR_CACHE_DIR``: torch sets that variable itself to its ``/tmp`` default the
    first time it looks, so it cannot tell a user's choice; move the cache with
    ``RECGS_CACHE_DIR``.)"""
    return user_cache_dir() / f"inductor-torch{torch.__version__}"


def use_user_cache() -> Path:
    """Point torch.compile's caches at :func:`inductor_dir` (before anything compiles)."""
    d = inductor_dir()
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(d)
    return d


def find_compiler() -> Optional[str]:
    """The C++ compiler torch.compile would call on the CPU, or None if there is none."""
    candidates = [os.environ.get("CXX")] if os.environ.get("CXX") else []
    candidates += ["cl"] if sys.platform == "win32" else ["c++", "g++", "clang++"]
    for name in candidates:
        path = shutil.which(name)
        if path:
            return path
    return None


def warm_key(threads: Optional[int] = None) -> str:
    """What a warm cache is valid for: torch, Python, machine, thread count, sources."""
    h = hashlib.sha256()
    threads = torch.get_num_threads() if threads is None else threads
    h.update(f"{torch.__version__}|{sys.version_info[:2]}|{platform.machine()}|{threads}".encode())
    for rel in _SOURCES:
        h.update((_CORE / rel).read_bytes())
    return h.hexdigest()[:16]


def marker(threads: Optional[int] = None) -> Path:
    return inductor_dir() / f"recgs-warm-{warm_key(threads)}"


def is_warm(threads: Optional[int] = None) -> bool:
    return marker(threads).exists()


def warm_up(max_degree: int = 3) -> None:
    """Compile every graph a training step and an evaluation use (once per SH degree up to
    ``max_degree``), on a small synthetic view, then write the warm marker."""
    from ..render.rasterizer import get_kernels, render
    from ..render.rowgrads import RowGrads
    from ..model.sh import num_sh_coeffs

    get_kernels(True)    # the kernels and their smoke renders (raises if the compiler fails)
    gen = torch.Generator().manual_seed(0)
    n, w, h = 400, 64, 48
    K = torch.tensor([[60.0, 0.0, w / 2], [0.0, 60.0, h / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    base = {"means": (torch.rand(n, 3, generator=gen) - 0.5) * torch.tensor([1.6, 1.2, 0.5]) + torch.tensor([0, 0, 2.0]),
            "log_scales": torch.full((n, 3), -3.0) + torch.rand(n, 3, generator=gen),
            "quats": torch.randn(n, 4, generator=gen),
            "logit_opacities": torch.randn(n, generator=gen),
            "sh_dc": torch.rand(n, 1, 3, generator=gen)}
    rg = RowGrads()
    for degree in range(max_degree + 1):
        k = num_sh_coeffs(degree)
        params = {name: torch.nn.Parameter(v.clone()) for name, v in base.items()}
        params["sh_rest"] = torch.nn.Parameter(torch.rand(n, 15, 3, generator=gen) * 0.1)
        # as Trainer.train_step: rows gathered through RowGrads, then backward
        p = {name: rg.track(name, v, cols=k - 1 if name == "sh_rest" else None) for name, v in params.items()}
        out = render(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], (p["sh_dc"], p["sh_rest"]),
                     viewmat, K, w, h, sh_degree=degree, background=torch.zeros(3), compiled=True, gather=rg)
        (out.rgb.square().mean() + out.means2d.sum() * 0).backward()
        rg.write()
        # as Trainer.render_output under no_grad (evaluations, caustic estimates)
        with torch.no_grad():
            sh = (params["sh_dc"], params["sh_rest"][:, :k - 1])
            render(params["means"], params["log_scales"], params["quats"], params["logit_opacities"], sh,
                   viewmat, K, w, h, sh_degree=degree, background=torch.zeros(3), compiled=True)
    m = marker()
    m.parent.mkdir(parents=True, exist_ok=True)
    m.write_text(f"warmed {time.strftime('%Y-%m-%d %H:%M:%S')} torch {torch.__version__}\n")


#: Sources whose change invalidates numba's warm marker (what its kernels are made of).
_NUMBA_SOURCES = ("render/_numba_impl.py", "render/_numba_project.py", "render/_numba_tiles.py",
                  "render/numba_kernels.py", "train/_numba_ssim.py", "train/numba_ssim.py")


def numba_dir() -> Path:
    """Where numba's cache goes: per user, beside RecGS's other caches."""
    return user_cache_dir() / "numba"


def use_numba_cache() -> Path:
    """Point numba's cache at :func:`numba_dir` (before its kernels load), unless the user set
    ``NUMBA_CACHE_DIR``."""
    os.environ.setdefault("NUMBA_CACHE_DIR", str(numba_dir()))
    return Path(os.environ["NUMBA_CACHE_DIR"])


def _triton_ready() -> bool:
    """Whether Triton's GPU kernels load here (Triton installed, a CUDA device)."""
    from ..render import triton_kernels
    from ..render.chunks import ALPHA_MAX, T_MIN
    from ..render.projection import ALPHA_MIN
    return triton_kernels.available() and triton_kernels.load(ALPHA_MIN, ALPHA_MAX, T_MIN) is not None


def numba_importable() -> bool:
    import importlib.util
    return importlib.util.find_spec("numba") is not None


def numba_marker() -> Path:
    """Written once numba's kernels are compiled into the cache: numba and Python versions,
    machine, CPU (numba compiles for the host CPU) and the kernels' sources."""
    import numba
    try:
        import llvmlite.binding as llvm
        cpu = llvm.get_host_cpu_name()
    except Exception:  # noqa: BLE001 - the marker just gets less specific
        cpu = "?"
    h = hashlib.sha256(f"{numba.__version__}|{sys.version_info[:2]}|{platform.machine()}|{cpu}".encode())
    for rel in _NUMBA_SOURCES:
        h.update((_CORE / rel).read_bytes())
    return use_numba_cache() / f"recgs-warm-{h.hexdigest()[:16]}"


def numba_is_warm() -> bool:
    try:
        return numba_marker().exists()
    except Exception:  # noqa: BLE001 - numba missing or broken: not warm
        return False


def _numba_ready() -> bool:
    """Load numba's kernels here (compiling them if the cache is cold): the rasterizer's, then
    the loss's SSIM (whose failure alone leaves the SSIM eager); False if the rasterizer's fail."""
    use_numba_cache()
    from ..render.kernels import numba_kernels_ready
    from . import numba_ssim
    if not numba_kernels_ready():
        return False
    numba_ssim.load()
    return True


def warm_up_numba() -> None:
    """Compile numba's kernels into the cache, then write the warm marker."""
    if not _numba_ready():
        from ..render import numba_kernels
        raise RuntimeError(f"numba kernels unavailable: {numba_kernels.error()!r}")
    m = numba_marker()
    m.parent.mkdir(parents=True, exist_ok=True)
    m.write_text(f"warmed {time.strftime('%Y-%m-%d %H:%M:%S')}\n")


def _lower_priority() -> None:  # pragma: no cover - runs in the child
    try:
        os.nice(10)
    except (AttributeError, OSError):
        pass


class CompileSwitch:
    """Which rasterizer path the next step takes (see the module docstring).

    ``requested``: True = compiled now (waits for the compiler; raises if it fails), False =
    eager, None = automatic. ``log(message)`` hears each change of state. ``state`` is one of
    ``eager``, ``unavailable``, ``warming``, ``compiled`` (torch.compile), ``triton`` (a CUDA
    device with Triton's kernels); ``numba`` is one of
    ``None`` (not used), ``warming``, ``ready``, ``failed``. ``switched_at`` is the step
    (``note_step``) at which a faster path (compiled, or numba after its warm-up) took over,
    ``None`` if none did. ``stall`` accumulates the seconds spent loading a path mid-run (the
    trainer keeps them out of the schedule's clock).
    """

    def __init__(self, requested: Optional[bool], log: Optional[Callable[[str], None]] = None,
                 max_degree: int = 3, device: str = "cpu") -> None:
        #: every message so far (a caller may attach ``log`` after construction)
        self.messages: list[str] = []
        self.log = log or (lambda m: None)
        self.proc: Optional[subprocess.Popen] = None
        self.switched_at: Optional[int] = None
        self.reason = ""
        self.stall = 0.0
        self.numba: Optional[str] = None
        self._step = 0
        self._threads: Optional[int] = None   # the trainer's thread count, while one is lent out
        if requested is False:
            self.state = "eager"
        elif requested is True:
            use_user_cache()
            self.state = "compiled"
        elif str(device).startswith("cuda") and _triton_ready():
            # culling, binning, projection, colour and compositing in Triton's kernels
            self.state, self.reason = "triton", f"device {device}"
            self._say(f"device {device}: training on Triton's GPU kernels")
        elif str(device) != "cpu":
            # numba's kernels are CPU code; the eager path runs on any torch device (the meta
            # device check in tests/test_device.py), torch.compile on a GPU only when asked for
            self.state, self.reason = "eager", f"device {device}"
            self._say(f"device {device}: training on the eager path (numba's kernels run on the CPU only; "
                      "Triton's GPU kernels need Triton and a CUDA device)")
        else:
            self._automatic(max_degree)

    def _automatic(self, max_degree: int) -> None:
        """The path on the CPU when none was asked for.

        numba wherever it is installed, compiler or not: it needs no C++ compiler, its cold
        cache costs ~13 s of one core instead of minutes, and it was the fastest path measured
        (one thread, 320x240: 0.095 s a forward + backward at 50k Gaussians against 0.122 s
        compiled and 0.290 s eager; 1000 training steps on the sample 27.6 s against 54.8 s
        compiled; benchmarks/RESULTS.md). torch.compile where numba is refused or absent, or its
        kernels fail to load, and a C++ compiler is on PATH; else eager torch.
        """
        compiler = find_compiler()
        if os.environ.get("RECGS_NUMBA", "").strip() != "0" and numba_importable():
            self.state = "unavailable"
            self.reason = "numba installed" if compiler else "no C++ compiler on PATH"
            self._start_numba()
            if self.numba != "failed" or compiler is None:
                return   # numba's path (now, or after its warm-up), or eager if it failed
        if compiler is None:
            self.state, self.reason = "unavailable", "no C++ compiler on PATH"
            self._say(f"torch.compile: no C++ compiler on PATH; training on {self._fallback()}")
            return
        use_user_cache()
        if is_warm():
            self.state = "compiled"
            return
        self.state = "warming"
        self._start([sys.executable, "-m", "recgs_addon.core.train.compiling", "--max-degree",
                     str(max_degree), "--threads", str(torch.get_num_threads())],
                    {"TORCHINDUCTOR_COMPILE_THREADS": "1"})   # one core (not part of the cache key)
        if self.state == "warming":
            self._say(f"torch.compile: cache is cold; training starts on {self._fallback()} while it warms up")
        else:
            self._say(f"torch.compile: {self.reason}; training on {self._fallback()}")

    # --- numba ----------------------------------------------------------------------------
    def _start_numba(self) -> None:
        """numba's path now if its cache is warm, else after a background warm-up."""
        why = self.reason
        if numba_is_warm():
            self._load_numba()
            if self.numba == "ready":
                self._say(f"{why}: training on numba's kernels")
            else:
                self._say(f"{why}; numba's kernels failed ({self.reason}): training on the eager path")
            return
        # not at a lowered priority: ~15 s of one core, which a busy machine would otherwise
        # starve for minutes (measured: no switch within a 66 s run at load 6 on 2 cores)
        self._start([sys.executable, "-m", "recgs_addon.core.train.compiling", "--numba"], {}, nice=False)
        if self.proc is None:
            self.numba = "failed"
            self._say(f"{why}; {self.reason}: training on the eager path")
            return
        self.numba = "warming"
        self._say(f"{why}; numba's cache is cold: training starts on the eager path while it warms up")

    def _load_numba(self) -> None:
        t0 = time.perf_counter()
        try:
            ok = _numba_ready()
        except Exception as exc:  # noqa: BLE001 - any failure: stay on the path we are on
            ok, self.reason = False, repr(exc)
        if not ok:
            from ..render import numba_kernels
            self.reason = self.reason if not numba_kernels.error() else repr(numba_kernels.error())
        self.numba = "ready" if ok else "failed"
        self.stall += time.perf_counter() - t0

    # --- background warm-ups ----------------------------------------------------------------
    def _start(self, cmd: list, extra_env: dict, nice: bool = True) -> None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(_CORE.parents[1])] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]),
            **extra_env)
        kw: dict = {}
        if not nice:
            pass
        elif sys.platform == "win32":
            kw["creationflags"] = getattr(subprocess, "BELOW_NORMAL_PRIORITY_CLASS", 0)
        else:
            kw["preexec_fn"] = _lower_priority
        try:
            self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, **kw)
        except OSError as exc:
            self.state, self.reason = "unavailable", f"could not start the warm-up ({exc})"
            return
        # No spare core (a 2-core laptop training on both): lend one to the warm-up, or the two
        # fight over it and the run slows down by more than the compiled path later wins back
        # (measured: 1500 steps on the sample took 192 s against 105 s eager throughout).
        threads = torch.get_num_threads()
        if threads > 1 and threads >= (os.cpu_count() or 1):
            self._threads = threads
            torch.set_num_threads(threads - 1)

    def _fallback(self) -> str:
        return "numba's kernels" if self.numba == "ready" else "the eager path"

    def _say(self, message: str) -> None:
        self.messages.append(message)
        self.log(message)

    def note_step(self, step: int) -> None:
        self._step = step

    def _poll(self) -> None:
        """A finished warm-up: give the core back, then switch (or say why not)."""
        if self.proc is None or self.proc.poll() is None:
            return
        err = self.proc.stderr.read().decode(errors="replace").strip() if self.proc.stderr else ""
        failed = f"warm-up failed ({err.splitlines()[-1] if err else self.proc.returncode})"
        ok = self.proc.returncode == 0
        self.proc = None
        if self._threads is not None:   # give the core back (the inductor cache is keyed on it)
            torch.set_num_threads(self._threads)
            self._threads = None
        if self.state == "warming":
            if ok and is_warm():
                self.state, self.switched_at = "compiled", self._step
                self._say(f"torch.compile: cache warm; compiled path from step {self._step}")
            else:
                self.state, self.reason = "unavailable", failed
                self._say(f"torch.compile: {self.reason}; staying on {self._fallback()}")
        elif self.numba == "warming":
            if ok and numba_is_warm():
                self._load_numba()
            else:
                self.numba, self.reason = "failed", failed
            if self.numba == "ready":
                self.switched_at = self._step
                self._say(f"numba: cache warm; numba path from step {self._step}")
            else:
                self._say(f"numba: {self.reason}; staying on the eager path")

    def compiled(self):
        """The rasterizer path for the next render (``render(compiled=...)``): True = through
        torch.compile; ``"numba"`` = numba's kernels, where torch.compile is not (yet) used and
        they are ready; ``"triton"`` = Triton's kernels on a CUDA device; else False = eager torch."""
        self._poll()
        if self.state == "compiled":
            return True
        if self.state == "triton":
            return "triton"
        if self.state != "eager" and self.numba == "ready":
            return "numba"
        return False

    def take_stall(self) -> float:
        """Seconds spent loading a path since the last call (and forget them)."""
        s, self.stall = self.stall, 0.0
        return s

    def close(self) -> None:
        """Stop a warm-up still running (the run is over; the cache keeps what it made)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc = None
        if self._threads is not None:
            torch.set_num_threads(self._threads)
            self._threads = None

    def __del__(self) -> None:   # a trainer dropped without close(): no orphan compiler
        try:
            self.close()
        except Exception:
            pass

    def summary(self) -> dict:
        return {"state": self.state, "switched_at": self.switched_at, "reason": self.reason or None,
                "numba": self.numba}


def main(argv=None) -> int:  # pragma: no cover - exercised through CompileSwitch in tests
    import argparse

    p = argparse.ArgumentParser(description="fill the torch.compile (or numba) cache for the rasterizer")
    p.add_argument("--max-degree", type=int, default=3)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--numba", action="store_true", help="compile numba's kernels instead")
    a = p.parse_args(argv)
    if a.numba:
        warm_up_numba()
        return 0
    if a.threads:
        torch.set_num_threads(a.threads)
    use_user_cache()
    warm_up(a.max_degree)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
