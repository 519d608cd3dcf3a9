"""Look frames placed against the solved survey: each look frame of a video import
(core/io/looks.py) registered with pycolmap from the 3D points of the keyframes next to it in
time.

A pose interpolated between two keyframes is as good as the camera's motion is steady; a
diver's hand, a turn at a row's end or the keyframes' own spacing put it off by a pixel or
more, and a caustic estimator reads a misplaced frame's misregistration as light. So each look
frame is matched as structure from motion matched the keyframes: SIFT features (pycolmap's),
matched against the features of the keyframe before and after it (read from the survey's
``database.db``) by mutual nearest neighbours under Lowe's ratio, and those that belong to a
3D point of the model give an absolute pose (``pycolmap.estimate_and_refine_absolute_pose``:
LO-RANSAC, then a non-linear refinement). A pose is kept where enough points agree with it
(:data:`MIN_INLIERS`, :data:`MIN_INLIER_SHARE`) and their reprojection error is small
(:data:`MAX_ERROR_PX`); a frame that cannot be placed so keeps no pose, and a job places it
between its keyframes and checks it there (``place_looks``). The poses go into ``looks.json``
(``qvec``, ``tvec``, and ``inliers``, ``error_px``), with how far the placing got against which
model (``"placing"``): a stopped import keeps the frames placed so far, and one run again
against the same model places only the rest.
"""
from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..errors import Cancelled
from ..io.atomic import atomic_path
from ..io.images import image_size, read_image
from ..io.looks import LOOKS_DIR, LOOKS_FILE, model_digest

#: Long side (px) of a look frame as its features are found, from the image itself (not from it
#: upsampled twice, SIFT's first octave): a look frame serves the caustic work at the training
#: size (a few hundred to 1,600 px) and needs its pose to a fraction of a pixel there, not at the
#: clip's full size; it takes a quarter of the time SfM's settings would.
SIFT_MAX_SIDE = 640
SIFT_FEATURES = 2048
#: Lowe's ratio test on the descriptors' distances.
RATIO = 0.8
#: A pose is kept where at least this many 2D-3D matches, and this share of them, agree with
#: it, and where their median reprojection error (px at the keyframes' size) is at most this.
MIN_INLIERS = 40
MIN_INLIER_SHARE = 0.3
MAX_ERROR_PX = 1.5
#: Progress reports over the whole registration, at most (``looks.json`` is written at each).
PROGRESS_STEPS = 25


def _keyframe_table(rec, db) -> dict:
    """{image name: (unit descriptors (N, 128) float32, world points (N, 3))} of the features
    of the model's registered images that belong to one of its 3D points."""
    out = {}
    for image_id, im in rec.images.items():
        if not im.has_pose:
            continue
        raw = db.read_descriptors(image_id)
        desc = np.asarray(getattr(raw, "data", raw), np.float32)
        ids = [(k, p.point3D_id) for k, p in enumerate(im.points2D) if p.has_point3D() and k < len(desc)]
        rows = np.array([k for k, _ in ids], np.int64)
        desc = desc[rows] / np.maximum(np.linalg.norm(desc[rows], axis=1, keepdims=True), 1e-9)
        xyz = np.array([rec.points3D[pid].xyz for _, pid in ids], np.float64).reshape(-1, 3)
        out[im.name] = (desc, xyz)
    return out


def _extractor(pycolmap, upsample: bool) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``extract(grey) -> (keypoints (N, 2) px, descriptors (N, 128) float32)``: pycolmap's SIFT
    on the CPU, from the image upsampled twice (``upsample``, for frames smaller than
    :data:`SIFT_MAX_SIDE`, which give too few features otherwise) or from the image itself."""
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = SIFT_MAX_SIDE
    ext.sift.max_num_features = SIFT_FEATURES
    ext.sift.first_octave = -1 if upsample else 0
    ext.num_threads = 1
    if hasattr(pycolmap, "FeatureExtractor"):     # pycolmap 3.12 and later
        run = pycolmap.FeatureExtractor.create(ext, device=pycolmap.Device.cpu).extract_from_float32_array
    else:
        run = pycolmap.Sift(ext, device=pycolmap.Device.cpu).extract

    def extract(grey: np.ndarray):
        kp, desc = run(grey)
        if not isinstance(kp, np.ndarray):   # FeatureKeypoints: a list of keypoints
            kp = np.array([(k.x, k.y) for k in kp], np.float64).reshape(-1, 2)
        return np.asarray(kp, np.float64)[:, :2], np.asarray(getattr(desc, "data", desc), np.float32)
    return extract


def _project(cam, xc: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of camera-frame points ``xc`` (N, 3) through ``cam``'s lens (pycolmap 4
    takes the points, 3.x their normalised coordinates)."""
    try:
        return np.asarray(cam.img_from_cam(xc), np.float64)
    except TypeError:
        return np.asarray(cam.img_from_cam(xc[:, :2] / xc[:, 2:3]), np.float64)


def _matches(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, 2) indices of mutual nearest neighbours between unit descriptors ``a`` and ``b``
    that pass the ratio test."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    sim = a @ b.T
    d2 = np.maximum(2.0 - 2.0 * sim, 0.0)
    ab = np.argsort(d2, axis=1)[:, :2]
    best = d2[np.arange(len(a)), ab[:, 0]]
    second = d2[np.arange(len(a)), ab[:, 1]]
    ba = np.argmin(d2, axis=0)
    ok = (best < RATIO ** 2 * second) & (ba[ab[:, 0]] == np.arange(len(a)))
    return np.stack([np.nonzero(ok)[0], ab[ok, 0]], 1)


def register_looks(survey: str | Path, model_dir: str | Path, database: str | Path,
                   progress: Optional[Callable[[int, int], None]] = None,
                   should_stop: Callable[[], bool] = lambda: False) -> dict:
    """Register the look frames of ``survey`` (its ``looks.json``) against the model in
    ``model_dir`` and the features in ``database``; writes their poses into ``looks.json`` and
    returns the counts {"registered", "unregistered", "reused" (the frames placed before against
    the same model, kept), "seconds"} (empty where the survey has no look frames). Stopped
    (``should_stop``), it keeps what it placed and raises :class:`Cancelled`."""
    import pycolmap

    survey = Path(survey)
    listing = survey / LOOKS_FILE
    if not listing.is_file():
        return {}
    t0 = time.perf_counter()
    doc = json.loads(listing.read_text(encoding="utf-8"))
    looks = doc.get("looks", [])
    times = {f["name"]: float(f["time_s"]) for f in json.loads((survey / "frames.json").read_text())["frames"]}
    rec = pycolmap.Reconstruction(str(model_dir))
    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        table = _keyframe_table(rec, db)
    keys = sorted((times[n], n) for n in table if n in times)
    key_t = np.array([t for t, _ in keys])
    by_name = {im.name: im for im in rec.images.values()}
    extractors: dict = {}
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = 4.0
    digest = model_digest(model_dir)
    placing = doc.get("placing") or {}
    start = min(int(placing.get("done", 0)), len(looks)) if placing.get("model") == digest else 0
    registered = sum("qvec" in lk for lk in looks[:start])

    def save(done: int) -> None:
        doc["placing"] = {"model": digest, "done": done}
        with atomic_path(listing, "look frame list") as tmp:
            tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")

    every = max(1, len(looks) // PROGRESS_STEPS)
    if start and progress is not None:
        progress(start, len(looks))
    for n in range(start, len(looks)):
        lk = looks[n]
        if should_stop():
            save(n)
            raise Cancelled("stopped while placing the look frames")
        for k in ("qvec", "tvec", "inliers", "error_px"):
            lk.pop(k, None)
        pos = int(np.searchsorted(key_t, lk["time_s"]))
        near = [keys[p][1] for p in (pos - 1, pos) if 0 <= p < len(keys)]
        if not near:
            continue
        cam = rec.cameras[by_name[near[0]].camera_id]
        path = survey / LOOKS_DIR / lk["name"]
        w, h = image_size(path)
        f = min(1.0, SIFT_MAX_SIDE / max(w, h))
        grey = np.ascontiguousarray(read_image(path, size=(round(w * f), round(h * f))).mean(-1), np.float32)
        small = max(w, h) < SIFT_MAX_SIDE
        if small not in extractors:
            extractors[small] = _extractor(pycolmap, small)
        kp, desc = extractors[small](grey)
        kp = kp * (cam.width / grey.shape[1])   # to the keyframes' size
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-9)
        pts2, pts3, seen = [], [], set()
        for name in near:
            k_desc, k_xyz = table[name]
            for i, j in _matches(desc, k_desc):
                if int(i) not in seen:   # a feature matched in both keyframes counts once
                    seen.add(int(i))
                    pts2.append(kp[i])
                    pts3.append(k_xyz[j])
        if len(pts2) >= MIN_INLIERS:
            ans = pycolmap.estimate_and_refine_absolute_pose(np.array(pts2), np.array(pts3), cam, est)
            if ans is not None:
                mask = np.asarray(ans["inlier_mask"], bool)
                pose = ans["cam_from_world"]
                R, t = pose.rotation.matrix(), np.asarray(pose.translation)
                xc = np.array(pts3)[mask] @ R.T + t
                proj = _project(cam, xc)
                err = float(np.median(np.linalg.norm(proj - np.array(pts2)[mask], axis=1))) if mask.any() else np.inf
                if mask.sum() >= MIN_INLIERS and mask.mean() >= MIN_INLIER_SHARE and err <= MAX_ERROR_PX:
                    q = np.asarray(pose.rotation.quat, np.float64)     # x, y, z, w
                    lk.update(qvec=[float(q[3]), float(q[0]), float(q[1]), float(q[2])],
                              tvec=[float(x) for x in t], inliers=int(mask.sum()), error_px=round(err, 3))
                    registered += 1
        if (n + 1) % every == 0 and n + 1 < len(looks):
            save(n + 1)
            if progress is not None:
                progress(n + 1, len(looks))
    save(len(looks))
    if progress is not None:
        progress(len(looks), len(looks))
    return {"registered": registered, "unregistered": len(looks) - registered, "reused": start,
            "seconds": round(time.perf_counter() - t0, 2)}
