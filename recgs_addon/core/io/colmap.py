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
import struct
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model.cameras import Camera
from ..errors import ImageError, SceneError
from .images import image_size, read_image

#: Camera models used as they are.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
#: Camera models undistorted to PINHOLE with pycolmap's undistorter before use.
UNDISTORTED_MODELS = (
    "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE", "FOV",
    "SIMPLE_DIVISION", "DIVISION",
)
#: Number of parameters per COLMAP camera model id (COLMAP's models.h), for checking cameras.bin.
_MODEL_NUM_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12,
                     11: 16, 12: 4, 13: 5, 14: 3, 15: 4, 16: 6, 17: 2}
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

    def load_image(self, camera: Camera, downscale: int = 1) -> np.ndarray:
        """(H, W, 3) float32 image of ``camera`` (see :func:`.images.read_image`)."""
        return read_image(self.image_path(camera), downscale)

    def extent(self) -> float:
        """Scene radius as INRIA defines it: 1.1 x the largest camera distance to their centroid."""
        centres = np.stack([c.center for c in self.cameras]) if self.cameras else np.zeros((1, 3))
        return float(1.1 * max(np.linalg.norm(centres - centres.mean(0), axis=1).max(), 1e-6))


def find_model_dir(scene_dir: str | os.PathLike) -> Path:
    """The folder holding cameras/images/points3D: ``sparse/0``, ``sparse`` or ``scene_dir``."""
    scene_dir = Path(scene_dir)
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


# --- binary model checks -------------------------------------------------------------------
# pycolmap reads a truncated cameras.bin without complaint, so the binary files are walked
# here first. Only cameras and images are walked record by record (a few hundred records);
# points3D.bin is checked by its exact size, computed from the observations in images.bin.

def _check_cameras_bin(path: Path) -> None:
    data = path.read_bytes()
    if len(data) < 8:
        raise SceneError(f"{path}: file is truncated ({len(data)} bytes)")
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    for i in range(n):
        if off + 24 > len(data):
            raise SceneError(f"{path}: file is truncated (camera {i + 1} of {n} is cut off)")
        _, model_id, _, _ = struct.unpack_from("<iiQQ", data, off)
        if model_id not in _MODEL_NUM_PARAMS:
            raise SceneError(f"{path}: camera {i + 1} has unknown camera model id {model_id}; "
                             "the file is corrupt or from an unsupported COLMAP version")
        off += 24 + 8 * _MODEL_NUM_PARAMS[model_id]
    if off != len(data):
        what = "truncated" if off > len(data) else f"longer than its {n} cameras ({len(data) - off} extra bytes)"
        raise SceneError(f"{path}: file is {what}; it may be corrupt")


def _check_images_bin(path: Path) -> int:
    """Walk images.bin; return the number of 2D points that have a 3D point."""
    data = path.read_bytes()
    if len(data) < 8:
        raise SceneError(f"{path}: file is truncated ({len(data)} bytes)")
    (n,) = struct.unpack_from("<Q", data, 0)
    off, n_obs = 8, 0
    for i in range(n):
        end_fixed = off + 64
        name_end = data.find(b"\0", end_fixed) if end_fixed <= len(data) else -1
        if name_end < 0 or name_end + 9 > len(data):
            raise SceneError(f"{path}: file is truncated (image {i + 1} of {n} is cut off)")
        (n2d,) = struct.unpack_from("<Q", data, name_end + 1)
        off = name_end + 9
        if off + 24 * n2d > len(data):
            raise SceneError(f"{path}: file is truncated (image {i + 1} of {n} is cut off)")
        if n2d:
            ids = np.frombuffer(data, dtype="<i8", count=3 * n2d, offset=off)[2::3]
            n_obs += int(np.count_nonzero(ids != -1))
        off += 24 * n2d
    if off != len(data):
        raise SceneError(f"{path}: file is longer than its {n} images ({len(data) - off} extra bytes); "
                         "it may be corrupt")
    return n_obs


def _check_points_bin(path: Path, n_obs: int) -> None:
    size = path.stat().st_size
    if size < 8:
        raise SceneError(f"{path}: file is truncated ({size} bytes)")
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
    # per point: id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64; 8 bytes per track element
    expected = 8 + 51 * n + 8 * n_obs
    if size != expected:
        what = "truncated" if size < expected else "longer than expected"
        raise SceneError(f"{path}: file is {what} ({size} bytes, {expected} expected for {n} points "
                         f"and {n_obs} observations in images.bin); it may be corrupt")


#: COLMAP's sensor types (sensor.h): CAMERA, IMU.
_SENSOR_TYPES = (0, 1)


def _check_rigs_bin(path: Path) -> None:
    """rigs.bin (COLMAP 3.12+): per rig id u32, sensor count u32, then the reference sensor
    (type i32, id u32) and each other sensor (type, id, has-pose u8, pose 7 f64 if it has one).
    Without this walk a truncated file surfaces as pycolmap's internal check message."""
    data = path.read_bytes()
    if len(data) < 8:
        raise SceneError(f"{path}: file is truncated ({len(data)} bytes)")
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    for i in range(n):
        cut = SceneError(f"{path}: file is truncated (rig {i + 1} of {n} is cut off)")
        if off + 8 > len(data):
            raise cut
        _, n_sensors = struct.unpack_from("<II", data, off)
        off += 8
        for j in range(n_sensors):
            if off + 8 > len(data):
                raise cut
            (kind,) = struct.unpack_from("<i", data, off)
            if kind not in _SENSOR_TYPES:
                raise SceneError(f"{path}: rig {i + 1} has a sensor of unknown type {kind}; the file is corrupt")
            off += 8
            if j:  # the reference sensor has no pose; the others say whether they have one
                if off + 1 > len(data):
                    raise cut
                has_pose = data[off]
                off += 1 + (56 if has_pose else 0)
                if off > len(data):
                    raise cut
    if off != len(data):
        raise SceneError(f"{path}: file is longer than its {n} rigs ({len(data) - off} extra bytes); "
                         "it may be corrupt")


def _check_frames_bin(path: Path) -> None:
    """frames.bin (COLMAP 3.12+): per frame id u32, rig id u32, pose 7 f64, data count u32,
    then per data (sensor type i32, sensor id u32, data id u64)."""
    data = path.read_bytes()
    if len(data) < 8:
        raise SceneError(f"{path}: file is truncated ({len(data)} bytes)")
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    for i in range(n):
        if off + 68 > len(data):
            raise SceneError(f"{path}: file is truncated (frame {i + 1} of {n} is cut off)")
        (n_data,) = struct.unpack_from("<I", data, off + 64)
        off += 68
        if off + 16 * n_data > len(data):
            raise SceneError(f"{path}: file is truncated (frame {i + 1} of {n} is cut off)")
        kinds = np.frombuffer(data, dtype="<i4", count=4 * n_data, offset=off)[::4] if n_data else []
        bad = [int(k) for k in kinds if k not in _SENSOR_TYPES]
        if bad:
            raise SceneError(f"{path}: frame {i + 1} names a sensor of unknown type {bad[0]}; the file is corrupt")
        off += 16 * n_data
    if off != len(data):
        raise SceneError(f"{path}: file is longer than its {n} frames ({len(data) - off} extra bytes); "
                         "it may be corrupt")


def _diagnose_text(model_dir: Path) -> str | None:
    """After pycolmap failed on a text model, find the first malformed line (error path only)."""
    def floats(tokens):
        try:
            [float(t) for t in tokens]
            return True
        except ValueError:
            return False

    for name in _MODEL_FILES:
        path = model_dir / f"{name}.txt"
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
        content = [(i + 1, ln.split()) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
        if name == "cameras":
            for no, tok in content:
                if len(tok) < 5 or not tok[0].isdigit() or not floats(tok[2:]):
                    return f"{path}: line {no} is not a camera (CAMERA_ID MODEL WIDTH HEIGHT PARAMS[])"
        elif name == "images":
            for k, (no, tok) in enumerate(content[::2]):
                if len(tok) < 10 or not floats(tok[:9]):
                    return f"{path}: line {no} is not an image (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)"
        else:
            for no, tok in content:
                if len(tok) < 8 or not floats(tok) or (len(tok) - 8) % 2:
                    return f"{path}: line {no} is not a 3D point (POINT3D_ID X Y Z R G B ERROR TRACK[])"
    return None


def read_reconstruction(model_dir: str | os.PathLike):
    """Read a COLMAP model with pycolmap after checking its files. Returns pycolmap.Reconstruction."""
    import pycolmap

    model_dir = Path(model_dir)
    ext = _model_format(model_dir)
    if ext == ".bin":
        for name, check in (("rigs.bin", _check_rigs_bin), ("frames.bin", _check_frames_bin)):
            if (model_dir / name).exists():  # COLMAP 3.12+ writes them; older models have neither
                check(model_dir / name)
        _check_cameras_bin(model_dir / "cameras.bin")
        n_obs = _check_images_bin(model_dir / "images.bin")
        _check_points_bin(model_dir / "points3D.bin", n_obs)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/MemoryError/RuntimeError
        where = _diagnose_text(model_dir) if ext == ".txt" else None
        raise SceneError(where or f"{model_dir}: pycolmap could not read the COLMAP model: {exc}") from exc
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
        pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), image_names=names)
        if not (tmp / "sparse").is_dir():
            raise SceneError(f"{model_dir}: pycolmap's undistortion produced no model in {tmp}")
        (tmp / "done").write_text(key)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
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
