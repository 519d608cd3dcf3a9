"""Loading a COLMAP reconstruction (read with pycolmap) into plain arrays.

``load_scene(scene_dir)`` finds the model (``sparse/0``, ``sparse`` or the folder itself,
binary or text), checks it and its images, undistorts non-pinhole cameras to pinhole with
pycolmap's own undistorter (into a cache, never over the user's images) and returns a
:class:`Scene`: one :class:`~.cameras.Camera` per registered image, sorted by name, and the
sparse points with their colours.

Every problem raises :class:`~.errors.SceneError` whose message names the file at fault.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model.cameras import Camera
from ..errors import ImageError, SceneError
from .colmap_checks import check_model, check_text_tracks, diagnose_failure
from .images import image_size, read_image

#: Camera models used as they are.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
#: Camera models undistorted to PINHOLE with pycolmap's undistorter before use.
UNDISTORTED_MODELS = (
    "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE", "FOV",
    "SIMPLE_DIVISION", "DIVISION",
)
_MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class Scene:
    """A loaded survey.

    Attributes:
        scene_dir: the folder the user chose.
        model_dir: the folder holding the COLMAP model that was read.
        image_dir: the folder images are read from (the undistortion cache when undistorted).
        cameras: one pinhole Camera per registered image, sorted by image name.
        points: (M, 3) float32 sparse points, world coordinates.
        colors: (M, 3) uint8 RGB colours of the points.
        undistorted: True when the images were undistorted into ``image_dir``.
    """

    scene_dir: Path
    model_dir: Path
    image_dir: Path
    cameras: list[Camera]
    points: np.ndarray = field(repr=False)
    colors: np.ndarray = field(repr=False)
    undistorted: bool = False

    def image_path(self, camera: Camera) -> Path:
        return self.image_dir / camera.name

    def load_image(self, camera: Camera, downscale: int = 1, size: tuple[int, int] | None = None,
                   compact: bool = False) -> np.ndarray:
        """(H, W, 3) image of ``camera``: float32, or uint8 / float16 with ``compact``; at
        ``size`` (width, height) or the file's size / ``downscale`` (see :func:`.images.read_image`)."""
        return read_image(self.image_path(camera), downscale, size=size, compact=compact)

    def extent(self) -> float:
        """Scene radius as INRIA defines it: 1.1 x the largest camera distance to their centroid."""
        centres = np.stack([c.center for c in self.cameras]) if self.cameras else np.zeros((1, 3))
        return float(1.1 * max(np.linalg.norm(centres - centres.mean(0), axis=1).max(), 1e-6))


def find_model_dir(scene_dir: str | os.PathLike) -> Path:
    """The folder holding cameras/images/points3D: ``sparse/0``, ``sparse`` or ``scene_dir``."""
    scene_dir = Path(scene_dir)
    if scene_dir.exists() and not scene_dir.is_dir():
        raise SceneError(f"{scene_dir}: is a file, not a folder (choose the survey's folder)")
    if not scene_dir.is_dir():
        raise SceneError(f"{scene_dir}: folder does not exist")
    candidates = [scene_dir / "sparse" / "0", scene_dir / "sparse", scene_dir]
    for cand in candidates:
        if any((cand / f"cameras{ext}").exists() or (cand / f"images{ext}").exists()
               for ext in (".bin", ".txt")):
            return cand
    looked = ", ".join(str(c) for c in candidates)
    raise SceneError(f"{scene_dir}: no COLMAP model found (looked for cameras.bin or cameras.txt in {looked})")


def _model_format(model_dir: Path) -> str:
    for ext in (".bin", ".txt"):
        present = [(model_dir / f"{n}{ext}").exists() for n in _MODEL_FILES]
        if any(present):
            missing = [f"{n}{ext}" for n, p in zip(_MODEL_FILES, present) if not p]
            if missing:
                raise SceneError(f"{model_dir / missing[0]}: file is missing (the COLMAP model needs "
                                 f"cameras{ext}, images{ext} and points3D{ext})")
            return ext
    raise SceneError(f"{model_dir}: no cameras.bin or cameras.txt")


def read_reconstruction(model_dir: str | os.PathLike):
    """Read a COLMAP model with pycolmap after checking its files (:mod:`.colmap_checks`).
    Returns pycolmap.Reconstruction."""
    import pycolmap

    model_dir = Path(model_dir)
    ext = _model_format(model_dir)
    index = check_model(model_dir, ext)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/MemoryError/RuntimeError/IndexError
        where = diagnose_failure(model_dir, index)
        raise SceneError(where or f"{model_dir}: pycolmap could not read the COLMAP model: {exc}") from exc
    if ext == ".txt":
        check_text_tracks(model_dir, rec)
    return rec


def _camera_from_pycolmap(image, cam) -> Camera:
    model = cam.model.name
    p = [float(v) for v in cam.params]
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
    else:  # only pinhole cameras reach here
        raise SceneError(f"camera {cam.camera_id} has model {model}, expected a pinhole model")
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    m = np.asarray(pose.matrix(), dtype=np.float64)
    return Camera(name=image.name, width=int(cam.width), height=int(cam.height), fx=fx, fy=fy,
                  cx=cx, cy=cy, R=m[:, :3].copy(), t=m[:, 3].copy(), camera_id=int(cam.camera_id),
                  image_id=int(image.image_id))


def _points_from_reconstruction(rec) -> tuple[np.ndarray, np.ndarray]:
    """(points (M,3) float32, colours (M,3) uint8) via pycolmap's bulk PLY export (no Python loop)."""
    from .ply import read_ply_elements

    if rec.num_points3D() == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    with tempfile.TemporaryDirectory(prefix="recgs_pts_") as tmp:
        path = os.path.join(tmp, "points.ply")
        rec.export_PLY(path)
        v = read_ply_elements(path)["vertex"]
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    cols = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)
    return pts, cols


def _check_camera(cams_file: Path, cam_id: int, cam) -> None:
    """A camera no projection can use: no pixels, or focal lengths / principal point that are
    not finite, or focal lengths that are not positive."""
    if cam.width <= 0 or cam.height <= 0:
        raise SceneError(f"{cams_file}: camera {cam_id} is {cam.width}x{cam.height} pixels")
    params = np.asarray(cam.params, dtype=np.float64)
    if not np.isfinite(params).all():
        raise SceneError(f"{cams_file}: camera {cam_id} has parameters that are NaN or infinite: "
                         f"{', '.join(f'{v:g}' for v in params)}")
    focal = params[cam.focal_length_idxs()] if hasattr(cam, "focal_length_idxs") else params[:1]
    if (focal <= 0).any():
        raise SceneError(f"{cams_file}: camera {cam_id} has a focal length <= 0 ({', '.join(f'{v:g}' for v in focal)})")


def _check_poses(images_file: Path, rec) -> None:
    """Registered images with a pose that is not finite, or two images with one name."""
    seen: dict[str, int] = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        if not np.isfinite(np.asarray(pose.matrix(), dtype=np.float64)).all():
            raise SceneError(f"{images_file}: image {image.name!r} (id {image_id}) has a pose with NaN or "
                             "infinite values")
        if image.name in seen:
            raise SceneError(f"{images_file}: images {seen[image.name]} and {image_id} have the same name "
                             f"{image.name!r}")
        seen[image.name] = image_id


def _check_images(rec, image_dir: Path) -> None:
    if not image_dir.is_dir():
        raise SceneError(f"{image_dir}: image folder does not exist")
    ids = sorted(rec.reg_image_ids())
    missing = [rec.image(i).name for i in ids if not (image_dir / rec.image(i).name).is_file()]
    if missing and len(missing) == len(ids):
        raise SceneError(f"{image_dir}: none of the {len(ids)} images the COLMAP model lists are in this "
                         f"folder (first: {missing[0]}); is it the right image folder?")
    for image_id in ids:
        image = rec.image(image_id)
        cam = rec.camera(image.camera_id)
        path = image_dir / image.name
        try:
            w, h = image_size(path)
        except ImageError as exc:
            raise SceneError(str(exc)) from exc
        if (w, h) != (cam.width, cam.height):
            raise SceneError(f"{path}: image is {w}x{h} but its COLMAP camera {cam.camera_id} "
                             f"is {cam.width}x{cam.height}")


def _cache_key(model_dir: Path, image_dir: Path, names: list[str]) -> str:
    h = hashlib.sha256()
    h.update(str(image_dir.resolve()).encode())
    for f in sorted(model_dir.iterdir()):
        if f.is_file():
            st = f.stat()
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    for n in names:
        st = (image_dir / n).stat()
        h.update(f"{n}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def default_cache_dir(scene_dir: Path) -> Path:
    """``SCENE/.recgs_cache`` when the scene folder is writable, else a per-user cache folder."""
    if os.access(scene_dir, os.W_OK):
        return scene_dir / ".recgs_cache"
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "recgs" / hashlib.sha256(str(scene_dir.resolve()).encode()).hexdigest()[:16]


def _settle(tmp: Path, out: Path) -> None:
    """Move a finished cache ``tmp`` to ``out``. Where another job (a second run on the survey
    started beside this one) finished ``out`` first, its cache stays, since that job may be
    reading it now, and ``tmp`` goes; a leftover ``out`` without its ``done`` mark is replaced."""
    try:
        os.replace(tmp, out)
        return
    except OSError:
        if not out.exists():
            raise
    if (out / "done").exists():
        shutil.rmtree(tmp, ignore_errors=True)
        return
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)


def _undistort(model_dir: Path, image_dir: Path, names: list[str], cache_dir: Path) -> Path:
    """Undistort into ``cache_dir/undistorted-KEY`` (images/ + sparse/); reuse it when present."""
    import pycolmap

    key = _cache_key(model_dir, image_dir, names)
    out = cache_dir / f"undistorted-{key}"
    if (out / "done").exists():
        return out
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".undistort-{key}-", dir=cache_dir))
    try:
        level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = 3   # COLMAP's line per image: the job says it undistorts, once
        try:
            pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), image_names=names)
        finally:
            pycolmap.logging.minloglevel = level
        if not (tmp / "sparse").is_dir():
            raise SceneError(f"{model_dir}: pycolmap's undistortion produced no model in {tmp}")
        (tmp / "done").write_text(key)
        _settle(tmp, out)
    except Exception:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def load_scene(scene_dir: str | os.PathLike, image_dir: str | os.PathLike | None = None,
               check_images: bool = True, cache_dir: str | os.PathLike | None = None) -> Scene:
    """Load a COLMAP survey.

    Args:
        scene_dir: folder with ``images/`` and ``sparse/0`` (or ``sparse/``), or a model folder.
        image_dir: image folder (default ``scene_dir/images``); e.g. ``scene_dir/clean``.
        check_images: check that every registered image exists, is readable and has its
            camera's size (reads headers only).
        cache_dir: where undistorted images go (default :func:`default_cache_dir`).
    Raises:
        SceneError naming the file at fault.
    """
    scene_dir = Path(scene_dir)
    model_dir = find_model_dir(scene_dir)
    image_dir = Path(image_dir) if image_dir is not None else scene_dir / "images"
    rec = read_reconstruction(model_dir)
    ext = _model_format(model_dir)
    cams_file = model_dir / f"cameras{ext}"
    if rec.num_reg_images() == 0:
        raise SceneError(f"{model_dir / ('images' + ext)}: the model has no registered images")
    models = {}
    for cam_id, cam in rec.cameras.items():
        name = cam.model.name
        if name not in PINHOLE_MODELS + UNDISTORTED_MODELS:
            raise SceneError(f"{cams_file}: camera {cam_id} uses the {name} model, which is not supported "
                             f"(supported: {', '.join(PINHOLE_MODELS + UNDISTORTED_MODELS)})")
        _check_camera(cams_file, cam_id, cam)
        models[cam_id] = name
    _check_poses(model_dir / f"images{ext}", rec)
    if check_images:
        _check_images(rec, image_dir)
    names = sorted(rec.image(i).name for i in rec.reg_image_ids())
    undistorted = any(m in UNDISTORTED_MODELS for m in models.values())
    if undistorted:
        cache = Path(cache_dir) if cache_dir is not None else default_cache_dir(scene_dir)
        out = _undistort(model_dir, image_dir, names, cache)
        image_dir, model_dir = out / "images", out / "sparse"
        rec = read_reconstruction(model_dir)
    by_name = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        by_name[image.name] = _camera_from_pycolmap(image, rec.camera(image.camera_id))
    cameras = [by_name[n] for n in sorted(by_name)]
    points, colors = _points_from_reconstruction(rec)
    points_file = model_dir / ("points3D" + _model_format(model_dir))
    if len(points) == 0:
        raise SceneError(f"{points_file}: the model has no 3D points; Gaussians are initialised from them")
    finite = np.isfinite(points).all(1)
    if not finite.all():
        if not finite.any():
            raise SceneError(f"{points_file}: all {len(points)} 3D points have NaN or infinite coordinates")
        warnings.warn(f"{points_file}: dropped {int((~finite).sum())} of {len(points)} 3D points with NaN or "
                      "infinite coordinates", stacklevel=2)
        points, colors = points[finite], colors[finite]
    return Scene(scene_dir=scene_dir, model_dir=model_dir, image_dir=image_dir, cameras=cameras,
                 points=points, colors=colors, undistorted=undistorted)
