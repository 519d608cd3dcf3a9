"""How every command speaks: JSON-lines events on stdout and one error path.

Each event is one JSON object on a line of its own, ``"event"`` first; non-finite floats
become null (the JSON stays standard) and numpy scalars and paths are written as plain values.
A command that fails says so with :func:`fail`: an ``error`` event, ``error: MESSAGE`` on
stderr, exit status 1.
"""
from __future__ import annotations

import json
import math
import os
import signal
import sys
import threading
from pathlib import Path

import numpy as np


def emit(event: str, **fields) -> None:
    print(json.dumps(_finite_tree({"event": event, **fields}), allow_nan=False, default=_json_default), flush=True)


def fail(message: str, *, detail: str | None = None) -> int:
    """The error path of every command: an ``error`` event, ``error: MESSAGE`` on stderr, and
    the exit status 1. ``detail`` (where training stopped, what is kept) goes in the event's
    message only, in parentheses; the stderr line stays the message alone."""
    emit("error", message=f"{message} ({detail})" if detail else message)
    print(f"error: {message}", file=sys.stderr)
    return 1


class StopSignals:
    """SIGTERM and SIGINT, while installed, ask a command to stop instead of ending it: calling
    the object says whether one came (the ``should_stop`` a long step polls), ``received`` is
    its name. A command installs it before its long work and restores the handlers after."""

    def __init__(self) -> None:
        self.received: str | None = None
        self._old: dict = {}
        #: a file whose appearing asks the same (a job run as a block of ``train --blocks``)
        self.stop_file = os.environ.get("RECGS_STOP_FILE") or None

    def __call__(self) -> bool:
        if self.received is None and self.stop_file and os.path.exists(self.stop_file):
            self.received = "a stop of the whole job"
        return self.received is not None

    def install(self) -> "StopSignals":
        if threading.current_thread() is not threading.main_thread():
            return self   # handlers are the main thread's to set: only the stop file is watched
        self._old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        return self

    def restore(self) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old = {}

    def _on_signal(self, signum, _frame) -> None:
        self.received = signal.Signals(signum).name


def _finite_tree(o):
    """Non-finite floats (a PSNR of identical images is inf) become null, so the JSON is standard."""
    if isinstance(o, dict):
        return {k: _finite_tree(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_tree(v) for v in o]
    if isinstance(o, (float, np.floating)) and not math.isfinite(o):
        return None
    return o


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def finite(x):
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x


