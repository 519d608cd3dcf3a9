"""A job's progress in Blender's UI: the status-bar line, the window manager's progress
indicator and redraws of the areas that show it (nothing without windows, as in batch mode)."""
from __future__ import annotations

import bpy

#: Share of a job's progress bar each phase takes (start, span).
PHASE_SPANS = {
    "sfm": {"features": (0.0, 0.4), "matching": (0.4, 0.3), "mapping": (0.7, 0.3)},
    "video": {"frames": (0.0, 0.2), "features": (0.2, 0.25), "matching": (0.45, 0.2), "mapping": (0.65, 0.15),
              "looks": (0.8, 0.2)},
}


# -- progress in the UI (status bar, window-manager progress, redraws) -------------------------

def _windows():
    wm = bpy.context.window_manager
    return list(wm.windows) if wm is not None and not bpy.app.background else []


def _ui_begin() -> None:
    if _windows():
        bpy.context.window_manager.progress_begin(0, 1000)


def _ui_end() -> None:
    wins = _windows()
    if wins:
        bpy.context.window_manager.progress_end()
    _status_text(wins, None)


def status_line(s) -> str:
    if s.job_kind in PHASE_SPANS:
        what = "video import" if s.job_kind == "video" else "reconstruct"
        return f"RecGS {what}: {s.phase}, {format_seconds(s.elapsed)}"
    parts = [f"RecGS {s.status.lower()}: {s.phase}", f"iteration {s.iteration}", f"{s.gaussians:,} Gaussians"]
    if s.psnr_test >= 0:
        parts.append(f"held-out PSNR {s.psnr_test:.2f} dB")
    parts.append(f"{format_seconds(s.elapsed)} elapsed")
    if s.eta >= 0:
        parts.append(f"~{format_seconds(s.eta)} left")
    return ", ".join(parts)


def format_seconds(t: float) -> str:
    t = int(round(max(0.0, t)))
    return f"{t // 3600}:{t // 60 % 60:02d}:{t % 60:02d}" if t >= 3600 else f"{t // 60}:{t % 60:02d}"


def _ui_update(s) -> None:
    wins = _windows()
    if not wins:
        return
    bpy.context.window_manager.progress_update(int(1000 * s.progress))
    _status_text(wins, status_line(s) if s.status in ("RUNNING", "CANCELLING") else None)


def _status_text(wins, text) -> None:
    """Show ``text`` in every window's status bar (None: clear it), then redraw them."""
    for win in wins:
        try:
            win.workspace.status_text_set(text)
        except (AttributeError, RuntimeError):
            pass
    _redraw(wins)


def _redraw(wins) -> None:
    for win in wins:
        for area in win.screen.areas:
            if area.type in ("VIEW_3D", "STATUSBAR", "PROPERTIES"):
                area.tag_redraw()
