"""Look frames: a video's frames between the survey's keyframes, for the caustic estimator.

A survey filmed as a video trains on the frames structure from motion keeps (its keyframes,
``images/``), a tenth of an image apart; between two of them the camera took a dozen more,
each under light of its own instant. Caustics forget themselves in 0.1-0.5 s, so those frames
are further looks at the light over each seabed point, which the caustic estimator gathers
from as it gathers from the keyframes (core/caustics/passes.py); they do not train. A survey
brings them as ``SCENE/looks/`` and ``SCENE/looks.json``::

    {"source": "dive.mp4", "fps": 30.0,
     "looks": [{"name": "frame_000124.jpg", "time_s": 4.133,
                "qvec": [w, x, y, z], "tvec": [x, y, z]}, ...]}

``name`` is the image in ``looks/``, ``time_s`` its time in the clip on the clock of
``frames.json`` (the keyframes' times). ``qvec`` and ``tvec`` (optional) are the frame's pose as
COLMAP writes it (world to camera: the rotation's unit quaternion, w first, and the
translation, in the survey's world); a look without them is placed between the keyframes
before and after it in time (:func:`place_looks`). A look frame has the survey's camera (the
keyframe nearest in time), at any image size of the same aspect (its intrinsics are scaled).
Import Video also records how far its placing of the looks got (``"placing"``: the digest of
the model they were placed against, :func:`model_digest`, and how many, in order, were tried;
:func:`placing_finished`).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import SceneError
from ..model.cameras import Camera, interpolate_pose, quat_to_rotmat

LOOKS_FILE = "looks.json"
LOOKS_DIR = "looks"
#: A look frame is placed between two keyframes at most this far apart in time (seconds);
#: further apart the camera may have turned or stopped, and a straight line says little.
MAX_BRACKET_S = 2.0


@dataclass
class Look:
    """One look frame: its image, its time, and its pose where known."""

    name: str
    path: Path
    time: float
    R: Optional[np.ndarray] = None   # (3, 3) world-to-camera, or None: to be placed
    t: Optional[np.ndarray] = None   # (3,)

    @property
    def posed(self) -> bool:
        return self.R is not None


@dataclass
class LookSet:
    """A survey's look frames (``read_looks``): those whose images are there, and how many the
    file listed without one."""

    looks: list[Look]
    listed: int
    missing: list[str]
    source: Optional[str] = None
    fps: Optional[float] = None


def read_looks(scene_dir) -> Optional[LookSet]:
    """The look frames of the survey in ``scene_dir`` (module docstring), or None when it has
    none. A file that is there but unreadable, or an entry without a finite time or with a pose
    that is no rotation, is an error naming the file; a listed image missing from ``looks/`` is
    left out and counted (:attr:`LookSet.missing`)."""
    path = Path(scene_dir) / LOOKS_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        entries = doc["looks"]
        if not isinstance(entries, list):
            raise TypeError("'looks' is no list")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SceneError(f"{path}: cannot read the look frames ({exc.__class__.__name__}: {exc}); "
                         "fix or delete the file") from None
    folder = Path(scene_dir) / LOOKS_DIR
    looks, missing = [], []
    for k, e in enumerate(entries):
        try:
            name, time_s = str(e["name"]), float(e["time_s"])
        except (KeyError, TypeError, ValueError):
            raise SceneError(f"{path}: look frame {k} needs a name and a time_s") from None
        if not math.isfinite(time_s):
            raise SceneError(f"{path}: look frame {name} has no finite time_s")
        R = t = None
        if "qvec" in e or "tvec" in e:
            try:
                q = np.asarray(e["qvec"], np.float64)
                t = np.asarray(e["tvec"], np.float64)
            except (KeyError, TypeError, ValueError):
                raise SceneError(f"{path}: look frame {name} needs both qvec and tvec, or neither") from None
            n = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
            if q.shape != (4,) or t.shape != (3,) or not np.isfinite(q).all() or not np.isfinite(t).all() \
                    or abs(n - 1.0) > 1e-3:
                raise SceneError(f"{path}: look frame {name}'s pose is no unit quaternion (qvec, 4 numbers) and "
                                 "translation (tvec, 3 numbers)")
            R = quat_to_rotmat(q)
        image = folder / name
        if not image.is_file():
            missing.append(name)
            continue
        looks.append(Look(name, image, time_s, R, t))
    fps = doc.get("fps")
    return LookSet(sorted(looks, key=lambda lk: lk.time), len(entries), missing, doc.get("source"),
                   float(fps) if isinstance(fps, (int, float)) else None)


def place_looks(looks: Sequence[Look], keyframes: Sequence[Camera], times: Sequence[Optional[float]],
                max_gap: float = MAX_BRACKET_S) -> tuple[list[tuple[Look, Camera, int]], dict]:
    """Each look frame's camera: its own pose where ``looks.json`` gives one, else the pose a
    share of the way between the keyframes just before and after it in time (the camera moving
    steadily between them, :func:`~..model.cameras.interpolate_pose`), those no more than
    ``max_gap`` s apart. ``keyframes``' cameras and their ``times`` (None: untimed). The
    intrinsics are those of the keyframe nearest in time (of untimed keyframes: the one nearest
    in space, for a look with a pose; one without cannot be placed). Returns ([(look, camera, index of that
    keyframe)], counts {"given", "interpolated", "unplaced"})."""
    timed = sorted((float(t), k) for k, t in enumerate(times) if t is not None)
    key_t = np.array([t for t, _ in timed])
    counts = {"given": 0, "interpolated": 0, "unplaced": 0}
    out = []
    centres = np.array([c.center for c in keyframes]) if len(keyframes) else np.zeros((0, 3))
    for lk in looks:
        if not len(key_t):   # untimed keyframes: a posed look takes the nearest keyframe's camera
            if lk.posed and len(keyframes):
                k = int(np.argmin(np.linalg.norm(centres - (-lk.R.T @ lk.t), axis=1)))
                base = keyframes[k]
                out.append((lk, Camera(lk.name, base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                                       np.asarray(lk.R, np.float64), np.asarray(lk.t, np.float64),
                                       base.camera_id, -1), k))
                counts["given"] += 1
            else:
                counts["unplaced"] += 1
            continue
        pos = int(np.searchsorted(key_t, lk.time))
        near = min((p for p in (pos - 1, pos) if 0 <= p < len(key_t)), key=lambda p: abs(key_t[p] - lk.time))
        base = keyframes[timed[near][1]]
        if lk.posed:
            R, t = lk.R, lk.t
            counts["given"] += 1
        elif 0 < pos < len(key_t) and key_t[pos] - key_t[pos - 1] <= max_gap:
            a, b = keyframes[timed[pos - 1][1]], keyframes[timed[pos][1]]
            span = key_t[pos] - key_t[pos - 1]
            R, t = interpolate_pose(a.R, a.t, b.R, b.t, 0.0 if span <= 0 else (lk.time - key_t[pos - 1]) / span)
            counts["interpolated"] += 1
        else:
            counts["unplaced"] += 1
            continue
        cam = Camera(lk.name, base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                     np.asarray(R, np.float64), np.asarray(t, np.float64), base.camera_id, -1)
        out.append((lk, cam, timed[near][1]))
    return out, counts


def look_reader(scene_dir, undistorted: bool):
    """A function ``read(look, camera) -> (H, W, 3) float32 sRGB`` giving a look frame's image at
    ``camera``'s size (a keyframe's camera at the size it is used at). Where the survey's lens
    was undistorted (``undistorted``: the keyframes were, by pycolmap into a cache), each look
    frame is undistorted as they were (its distorted camera the survey model's, scaled to the
    frame's size), then brought to that size."""
    from .images import read_image
    if not undistorted:
        return lambda lk, cam: read_image(lk.path, size=(cam.width, cam.height))
    import copy

    import pycolmap
    import torch

    from .colmap import find_model_dir, read_reconstruction
    rec = read_reconstruction(find_model_dir(scene_dir))
    options = pycolmap.UndistortCameraOptions()

    def read(lk: Look, cam: Camera) -> np.ndarray:
        raw = read_image(lk.path, compact=True)
        if raw.dtype != np.uint8:
            raw = (np.clip(raw.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
        if cam.camera_id not in rec.cameras:
            raise SceneError(f"{lk.path}: its keyframe's camera {cam.camera_id} is not in the survey's model")
        src = copy.copy(rec.cameras[cam.camera_id])
        if (src.width, src.height) != (raw.shape[1], raw.shape[0]):
            src.rescale(raw.shape[1], raw.shape[0])
        flat, _ = pycolmap.undistort_image(options, pycolmap.Bitmap.from_array(np.ascontiguousarray(raw[..., :3])), src)
        img = torch.from_numpy(np.asarray(flat.to_array(), np.float32) / 255.0).permute(2, 0, 1)[None]
        img = torch.nn.functional.interpolate(img, size=(cam.height, cam.width), mode="bilinear",
                                              align_corners=False, antialias=True)
        return img[0].permute(1, 2, 0).clamp(0, 1).numpy()
    return read


def model_digest(model_dir: str | Path) -> str:
    """A digest of the model's files: the look frames placed against one model are kept for
    that model only."""
    h = hashlib.sha1()
    for path in sorted(Path(model_dir).iterdir()):
        if path.is_file():
            h.update(path.name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def placing_finished(survey: str | Path, model_dir: str | Path) -> bool:
    """Whether every look frame of ``survey`` was tried against the model in ``model_dir`` (or
    it has none): an import stopped before then goes on with the look frames."""
    listing = Path(survey) / LOOKS_FILE
    if not listing.is_file():
        return True
    try:
        doc = json.loads(listing.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    placing = doc.get("placing") or {}
    return placing.get("done") == len(doc.get("looks", [])) and placing.get("model") == model_digest(model_dir)
