"""When each frame of a video survey was taken: ``SCENE/frames.json``.

A survey made from a video (``python -m recgs_addon video``, or the generator's video-like
surveys) lists its frames with their time in the clip::

    {"source": "dive.mp4", "fps": 30.0, "frames": [{"name": "frame_000123.jpg", "time_s": 4.1}, ...]}

Frames a fraction of a second apart saw nearly the same caustic light, so caustic removal
counts them as one pass over the seabed (core/train/coverage.py). Photo surveys have no such
file: each photo counts as a pass of its own.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

from ..errors import SceneError
from .atomic import atomic_path

FRAMES_FILE = "frames.json"


def read_frame_times(scene_dir) -> Optional[dict[str, float]]:
    """{image name: seconds} from ``scene_dir/frames.json``, or None when the survey has none.
    A file that is there but unreadable is an error naming it."""
    path = Path(scene_dir) / FRAMES_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        frames = doc["frames"]
        times = {str(f["name"]): float(f["time_s"]) for f in frames}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SceneError(f"{path}: cannot read the frames' times ({exc.__class__.__name__}: {exc}); "
                         "fix or delete the file") from None
    bad = [n for n, t in times.items() if not math.isfinite(t)]
    if bad:
        raise SceneError(f"{path}: frame {bad[0]} has no finite time_s")
    return times


def write_frame_times(scene_dir, times: dict[str, float], **extra) -> Path:
    """Write ``frames.json`` for ``times`` ({name: seconds}), in time order; ``extra`` keys
    (``source``, ``fps``, ...) go beside the list."""
    path = Path(scene_dir) / FRAMES_FILE
    frames = [{"name": n, "time_s": round(float(t), 6)} for n, t in sorted(times.items(), key=lambda kv: kv[1])]
    with atomic_path(path, "frame list") as tmp:
        tmp.write_text(json.dumps({**extra, "frames": frames}, indent=1))
    return path
