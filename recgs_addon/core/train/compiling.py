"""The compiled rasterizer without waiting for the compiler.

``torch.compile`` makes a training step about twice as fast on the CPU, but a cold cache costs
one to four minutes of C++ compilation before the first step, and machines without a C++
compiler (most Windows and macOS ones) cannot use it at all. :class:`CompileSwitch` decides,
step by step, which path the trainer takes:

- no compiler on ``PATH``: the eager path, said once (``state == "unavailable"``);
- a warm cache (a marker this module writes once a warm-up has compiled every graph a
  training step and an evaluation use): compiled from the first step (tracing the graphs
  again costs about ten seconds; the C++ compiler does not run);
- a cold cache: the eager path at once, while a background process (``python -m
  recgs_addon.core.train.compiling``, lowered priority) fills the cache with a small
  synthetic render at every SH degree; when it has finished, the next step switches to the
  compiled path. If it fails, training stays eager.

Both paths give the same numbers to float32 rounding (tests/test_rasterizer.py), so a switch
mid-run changes nothing but speed.

The inductor cache goes to a per-user folder that survives reboots (:func:`inductor_dir`),
not torch's default under ``/tmp``.
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
_SOURCES = ("render/projection.py", "render/rasterizer.py", "render/rowgrads.py", "model/sh.py",
            "train/compiling.py")
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


def _numba_ready() -> bool:
    os.environ.setdefault("NUMBA_CACHE_DIR", str(user_cache_dir() / "numba"))
    from ..render.rasterizer import numba_kernels_ready
    return numba_kernels_ready()


def _lower_priority() -> None:  # pragma: no cover - runs in the child
    try:
        os.nice(10)
    except (AttributeError, OSError):
        pass


class CompileSwitch:
    """Which rasterizer path the next step takes (see the module docstring).

    ``requested``: True = compiled now (waits for the compiler; raises if it fails), False =
    eager, None = automatic. ``log(message)`` hears each change of state. ``state`` is one of
    ``eager``, ``unavailable``, ``warming``, ``compiled``; ``switched_at`` is the step
    (``note_step``) at which the compiled path took over, ``None`` if it never did.
    """

    def __init__(self, requested: Optional[bool], log: Optional[Callable[[str], None]] = None,
                 max_degree: int = 3, device: str = "cpu") -> None:
        #: every message so far (a caller may attach ``log`` after construction)
        self.messages: list[str] = []
        self.log = log or (lambda m: None)
        self.proc: Optional[subprocess.Popen] = None
        self.switched_at: Optional[int] = None
        self.reason = ""
        self._step = 0
        self._threads: Optional[int] = None   # the trainer's thread count, while one is lent out
        #: numba's kernels stand in while torch.compile cannot (no compiler, cold cache), when
        #: asked for with RECGS_NUMBA=1: off by default, they lose to eager torch at render
        #: level here (docs/training.md)
        self.numba = (requested is None and device == "cpu" and os.environ.get("RECGS_NUMBA") == "1"
                      and _numba_ready())
        if requested is False:
            self.state = "eager"
        elif requested is True or device != "cpu":   # GPUs compile with their own toolchain
            use_user_cache()
            self.state = "compiled"
        elif find_compiler() is None:
            self.state, self.reason = "unavailable", "no C++ compiler on PATH"
            self._say(f"torch.compile: no C++ compiler on PATH; training on {self._fallback()}")
        else:
            use_user_cache()
            if is_warm():
                self.state = "compiled"
            else:
                self.state = "warming"
                self._start(max_degree)
                if self.state == "warming":
                    self._say(f"torch.compile: cache is cold; training starts on {self._fallback()} while it warms up")
                else:
                    self._say(f"torch.compile: {self.reason}; training on {self._fallback()}")

    def _start(self, max_degree: int) -> None:
        cmd = [sys.executable, "-m", "recgs_addon.core.train.compiling", "--max-degree", str(max_degree),
               "--threads", str(torch.get_num_threads())]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(_CORE.parents[1])] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]),
            TORCHINDUCTOR_COMPILE_THREADS="1")   # one core (not part of the cache key)
        kw: dict = {}
        if sys.platform == "win32":
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
        return "numba's kernels" if self.numba else "the eager path"

    def _say(self, message: str) -> None:
        self.messages.append(message)
        self.log(message)

    def note_step(self, step: int) -> None:
        self._step = step

    def compiled(self):
        """The rasterizer path for the next render (``render(compiled=...)``): True = through
        torch.compile; ``"numba"`` = numba's kernels, while torch.compile is unavailable or
        warming up (where numba is installed; else False = eager torch)."""
        if self.state == "warming" and self.proc is not None and self.proc.poll() is not None:
            err = self.proc.stderr.read().decode(errors="replace").strip() if self.proc.stderr else ""
            if self._threads is not None:   # give the core back (the cache is keyed on it)
                torch.set_num_threads(self._threads)
                self._threads = None
            if self.proc.returncode == 0 and is_warm():
                self.state, self.switched_at = "compiled", self._step
                self._say(f"torch.compile: cache warm; compiled path from step {self._step}")
            else:
                self.state = "unavailable"
                self.reason = f"warm-up failed ({err.splitlines()[-1] if err else self.proc.returncode})"
                self._say(f"torch.compile: {self.reason}; staying on {self._fallback()}")
            self.proc = None
        if self.state == "compiled":
            return True
        if self.state in ("unavailable", "warming") and self.numba:
            return "numba"
        return False

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
                "numba": bool(self.numba)}


def main(argv=None) -> int:  # pragma: no cover - exercised through CompileSwitch in tests
    import argparse

    p = argparse.ArgumentParser(description="fill the torch.compile cache for the rasterizer")
    p.add_argument("--max-degree", type=int, default=3)
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    use_user_cache()
    warm_up(a.max_degree)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
