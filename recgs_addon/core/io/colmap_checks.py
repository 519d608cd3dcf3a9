"""Checks of a COLMAP model's files, before and after pycolmap reads them.

pycolmap reads some damaged models without complaint (a truncated ``cameras.bin``, a cut-off
``points3D.txt``, a rotation quaternion of zeros, which it turns into no rotation at all),
hangs on others (a damaged ``frames.bin``) and refuses the rest with its own internal check
messages (``Check failed: frame->HasDataId(DataId())``, ``unordered_map::at``, ``Rig with ID
7 does not exist``) that name no file. So, before pycolmap reads a model,
:func:`check_model` walks its small files record by record: every count, every reference
between them (an image's camera, a rig's cameras, a frame's rig and images) and the poses in
the file pycolmap takes them from (``frames`` when the model has one, else ``images``);
``points3D.bin`` is checked by its exact size. When pycolmap still fails,
:func:`diagnose_failure` walks the points too and names the first bad line or record. After
a text model is read, :func:`check_text_tracks` compares its points' tracks with the
observations ``images.txt`` lists (a cut-off ``points3D.txt`` reads without an error).

Every problem raises or returns a message that names the file and the record at fault.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import SceneError

#: Number of parameters per COLMAP camera model id (COLMAP's models.h), for checking cameras.bin.
_MODEL_NUM_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12,
                     11: 16, 12: 4, 13: 5, 14: 3, 15: 4, 16: 6, 17: 2}
#: COLMAP's sensor types (sensor.h): CAMERA, IMU.
_SENSOR_TYPES = (0, 1)
_SENSOR_NAMES = {"CAMERA": 0, "IMU": 1}
_CAMERA = 0


@dataclass
class ImageRecord:
    camera_id: int
    name: str
    pose: tuple          # qw qx qy qz tx ty tz as the file gives them
    where: str           # "image 3" or "line 12" for messages


@dataclass
class FrameRecord:
    frame_id: int
    rig_id: int
    pose: tuple
    data: list           # (sensor type, sensor id, data id): a camera's data id is an image id
    where: str


@dataclass
class ModelIndex:
    """What a model's files say about each other (read before pycolmap reads them)."""
    ext: str
    cameras: dict = field(default_factory=dict)    # camera id -> where
    images: dict = field(default_factory=dict)     # image id -> ImageRecord
    rigs: Optional[dict] = None                    # rig id -> [camera ids]; None: no rigs file
    frames: Optional[list] = None                  # [FrameRecord]; None: no frames file
    n_obs: int = 0                                 # 2D points with a 3D point (binary)


# --- binary files ------------------------------------------------------------------------------

def _read(path: Path) -> bytes:
    data = path.read_bytes()
    if len(data) < 8:
        raise SceneError(f"{path}: file is truncated ({len(data)} bytes)")
    return data


def _cameras_bin(path: Path, index: ModelIndex) -> None:
    data = _read(path)
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    for i in range(n):
        if off + 24 > len(data):
            raise SceneError(f"{path}: file is truncated (camera {i + 1} of {n} is cut off)")
        cam_id, model_id, _, _ = struct.unpack_from("<iiQQ", data, off)
        if model_id not in _MODEL_NUM_PARAMS:
            raise SceneError(f"{path}: camera {i + 1} has unknown camera model id {model_id}; "
                             "the file is corrupt or from an unsupported COLMAP version")
        if cam_id in index.cameras:
            raise SceneError(f"{path}: two cameras have the id {cam_id}; the file is corrupt")
        index.cameras[cam_id] = f"camera {cam_id}"
        off += 24 + 8 * _MODEL_NUM_PARAMS[model_id]
    if off != len(data):
        what = "truncated" if off > len(data) else f"longer than its {n} cameras ({len(data) - off} extra bytes)"
        raise SceneError(f"{path}: file is {what}; it may be corrupt")


def _images_bin(path: Path, index: ModelIndex, observations: Optional[dict] = None) -> None:
    """Walk images.bin; count the 2D points that have a 3D point. ``observations`` (error path
    only) receives each image's 3D point ids, one per 2D point (-1: none)."""
    data = _read(path)
    (n,) = struct.unpack_from("<Q", data, 0)
    off, n_obs = 8, 0
    for i in range(n):
        end_fixed = off + 64
        name_end = data.find(b"\0", end_fixed) if end_fixed <= len(data) else -1
        if name_end < 0 or name_end + 9 > len(data):
            raise SceneError(f"{path}: file is truncated (image {i + 1} of {n} is cut off)")
        image_id, *pose, camera_id = struct.unpack_from("<I7dI", data, off)
        name = data[end_fixed:name_end].decode("utf-8", errors="replace")
        (n2d,) = struct.unpack_from("<Q", data, name_end + 1)
        off = name_end + 9
        if off + 24 * n2d > len(data):
            raise SceneError(f"{path}: file is truncated (image {i + 1} of {n} is cut off)")
        if n2d:
            ids = np.frombuffer(data, dtype="<i8", count=3 * n2d, offset=off)[2::3]
            n_obs += int(np.count_nonzero(ids != -1))
            if observations is not None:
                observations[image_id] = ids
        elif observations is not None:
            observations[image_id] = np.zeros(0, np.int64)
        off += 24 * n2d
        if image_id in index.images:
            raise SceneError(f"{path}: two images have the id {image_id} ({index.images[image_id].name!r} and "
                             f"{name!r}); the file is corrupt")
        index.images[image_id] = ImageRecord(camera_id, name, tuple(pose), f"image {image_id}")
    if off != len(data):
        raise SceneError(f"{path}: file is longer than its {n} images ({len(data) - off} extra bytes); "
                         "it may be corrupt")
    index.n_obs = n_obs


def _points_bin_size(path: Path, n_obs: int) -> None:
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


def _rigs_bin(path: Path, index: ModelIndex) -> None:
    """rigs.bin (COLMAP 3.12+): per rig id u32, sensor count u32, then the reference sensor
    (type i32, id u32) and each other sensor (type, id, has-pose u8, pose 7 f64 if it has one).
    Without this walk a truncated file surfaces as pycolmap's internal check message."""
    data = _read(path)
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    index.rigs = {}
    for i in range(n):
        cut = SceneError(f"{path}: file is truncated (rig {i + 1} of {n} is cut off)")
        if off + 8 > len(data):
            raise cut
        rig_id, n_sensors = struct.unpack_from("<II", data, off)
        off += 8
        if rig_id in index.rigs:
            raise SceneError(f"{path}: two rigs have the id {rig_id}; the file is corrupt")
        cameras = index.rigs.setdefault(rig_id, [])
        for j in range(n_sensors):
            if off + 8 > len(data):
                raise cut
            kind, sensor_id = struct.unpack_from("<iI", data, off)
            if kind not in _SENSOR_TYPES:
                raise SceneError(f"{path}: rig {i + 1} has a sensor of unknown type {kind}; the file is corrupt")
            if kind == _CAMERA:
                cameras.append(sensor_id)
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


_DATA = np.dtype([("type", "<i4"), ("sensor", "<u4"), ("data", "<u8")])


def _frames_bin(path: Path, index: ModelIndex) -> None:
    """frames.bin (COLMAP 3.12+): per frame id u32, rig id u32, pose 7 f64, data count u32,
    then per data (sensor type i32, sensor id u32, data id u64)."""
    data = _read(path)
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    index.frames, seen = [], set()
    for i in range(n):
        if off + 68 > len(data):
            raise SceneError(f"{path}: file is truncated (frame {i + 1} of {n} is cut off)")
        frame_id, rig_id, *pose, n_data = struct.unpack_from("<II7dI", data, off)
        if frame_id in seen:
            raise SceneError(f"{path}: two frames have the id {frame_id}; the file is corrupt")
        seen.add(frame_id)
        off += 68
        if off + 16 * n_data > len(data):
            raise SceneError(f"{path}: file is truncated (frame {i + 1} of {n} is cut off)")
        items = np.frombuffer(data, dtype=_DATA, count=n_data, offset=off) if n_data else np.zeros(0, _DATA)
        bad = [int(k) for k in items["type"] if k not in _SENSOR_TYPES]
        if bad:
            raise SceneError(f"{path}: frame {i + 1} names a sensor of unknown type {bad[0]}; the file is corrupt")
        index.frames.append(FrameRecord(frame_id, rig_id, tuple(pose),
                                        [(int(t), int(s), int(d)) for t, s, d in items], f"frame {frame_id}"))
        off += 16 * n_data
    if off != len(data):
        raise SceneError(f"{path}: file is longer than its {n} frames ({len(data) - off} extra bytes); "
                         "it may be corrupt")


# --- text files -----------------------------------------------------------------------------------
# The lines of cameras, images (the image lines), rigs and frames are read as COLMAP reads
# them, and one it cannot read is named here; so are values no reconstruction can hold (NaN,
# an unknown camera model) and references to records that do not exist. The lines of 2D and
# 3D points (the bulk of a model) are left to pycolmap, and to diagnose_failure if it fails.

def _content(path: Path):
    """(line number, stripped line) of the data lines, as COLMAP reads them."""
    for no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield no, s


def _image_lines(path: Path):
    """(line number, image line, the line after it or None): COLMAP reads an image's line,
    then the next line whatever it holds (empty for an image without 2D points)."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            i += 1
            continue
        yield i + 1, s, (lines[i + 1] if i + 1 < len(lines) else None)
        i += 2


def _floats(tokens) -> Optional[list]:
    try:
        return [float(t) for t in tokens]
    except ValueError:
        return None


def _ints(tokens) -> Optional[list]:
    try:
        return [int(t) for t in tokens]
    except ValueError:
        return None


def _model_names() -> dict:
    import pycolmap

    return {k: int(v) for k, v in pycolmap.CameraModelId.__members__.items() if k != "INVALID"}


def _cameras_txt(path: Path, index: ModelIndex) -> None:
    models = _model_names()
    for no, s in _content(path):
        tok = s.split()
        ids = _ints(tok[:1] + tok[2:4])
        params = _floats(tok[4:])
        if len(tok) < 5 or ids is None or params is None:
            raise SceneError(f"{path}: line {no} is not a camera (CAMERA_ID MODEL WIDTH HEIGHT PARAMS[])")
        cam_id, model = ids[0], tok[1]
        if model not in models:
            raise SceneError(f"{path}: line {no}: camera {cam_id} uses the unknown camera model {model!r} "
                             f"(COLMAP's models: {', '.join(models)})")
        if len(params) != _MODEL_NUM_PARAMS.get(models[model], len(params)):
            raise SceneError(f"{path}: line {no}: camera {cam_id} has {len(params)} parameters; the {model} "
                             f"model has {_MODEL_NUM_PARAMS[models[model]]}")
        if not all(math.isfinite(v) for v in params):
            raise SceneError(f"{path}: line {no}: camera {cam_id} has parameters that are NaN or infinite: "
                             f"{' '.join(tok[4:])}")
        if cam_id in index.cameras:
            raise SceneError(f"{path}: line {no}: camera {cam_id} is listed twice (first on {index.cameras[cam_id]})")
        index.cameras[cam_id] = f"line {no}"


def _images_txt(path: Path, index: ModelIndex) -> None:
    for no, s, _ in _image_lines(path):
        tok = s.split(maxsplit=9)
        ids = _ints([tok[0], tok[8]]) if len(tok) == 10 else None
        pose = _floats(tok[1:8])
        if ids is None or pose is None:
            raise SceneError(f"{path}: line {no} is not an image (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
        image_id, camera_id = ids
        if image_id in index.images:
            raise SceneError(f"{path}: line {no}: image {image_id} is listed twice (first on "
                             f"{index.images[image_id].where})")
        index.images[image_id] = ImageRecord(camera_id, tok[9], tuple(pose), f"line {no}")


def _sensor(tokens) -> Optional[tuple]:
    if len(tokens) < 2 or tokens[0] not in _SENSOR_NAMES or _ints(tokens[1:2]) is None:
        return None
    return _SENSOR_NAMES[tokens[0]], int(tokens[1])


def _rigs_txt(path: Path, index: ModelIndex) -> None:
    index.rigs = {}
    for no, s in _content(path):
        tok = s.split()
        problem = _rig_line_problem(tok)
        if problem:
            raise SceneError(f"{path}: line {no} {problem}")
        rig_id, n_sensors = _ints(tok[:2])
        if rig_id in index.rigs:
            raise SceneError(f"{path}: line {no}: rig {rig_id} is listed twice")
        cameras, k = [], 2
        for j in range(n_sensors):
            sensor = _sensor(tok[k:k + 2])
            if sensor is None:
                break
            if sensor[0] == _CAMERA:
                cameras.append(sensor[1])
            k += 2
            if j:
                has_pose = tok[k:k + 1] == ["1"]
                k += 1 + (7 if has_pose else 0)
        index.rigs[rig_id] = cameras


def _frames_txt(path: Path, index: ModelIndex) -> None:
    index.frames, seen = [], set()
    for no, s in _content(path):
        tok = s.split()
        problem = _frame_line_problem(tok, allow_nonfinite=True)   # a NaN pose is named with its image below
        if problem:
            raise SceneError(f"{path}: line {no} {problem}")
        head, pose, count = _ints(tok[:2]), _floats(tok[2:9]), _ints(tok[9:10])
        data = []
        for k in range(10, 10 + 3 * count[0], 3):
            sensor, data_id = _sensor(tok[k:k + 2]), _ints(tok[k + 2:k + 3])
            if sensor is None or not data_id:
                break
            data.append((sensor[0], sensor[1], data_id[0]))
        if head[0] in seen:
            raise SceneError(f"{path}: line {no}: frame {head[0]} is listed twice")
        seen.add(head[0])
        index.frames.append(FrameRecord(head[0], head[1], tuple(pose), data, f"line {no}"))


# --- the whole model --------------------------------------------------------------------------

def check_model(model_dir: Path, ext: str) -> ModelIndex:
    """Walk the model's files before pycolmap reads them; SceneError naming the file and the
    record at fault. Returns what was read (for :func:`diagnose_failure`)."""
    index = ModelIndex(ext)
    f = {n: model_dir / f"{n}{ext}" for n in ("cameras", "images", "points3D", "rigs", "frames")}
    if ext == ".bin":
        readers = (("rigs", _rigs_bin), ("frames", _frames_bin), ("cameras", _cameras_bin), ("images", _images_bin))
    else:
        readers = (("rigs", _rigs_txt), ("frames", _frames_txt), ("cameras", _cameras_txt), ("images", _images_txt))
    for name, reader in readers:
        if name in ("rigs", "frames") and not f[name].exists():   # COLMAP 3.12+ writes them; older models have neither
            continue
        reader(f[name], index)
    if ext == ".bin":
        _points_bin_size(f["points3D"], index.n_obs)
    _check_links(f, index)
    _check_poses(f, index)
    return index


def _check_links(f: dict, index: ModelIndex) -> None:
    cams = f["cameras"].name
    for image_id, im in index.images.items():
        if im.camera_id not in index.cameras:
            raise SceneError(f"{f['images']}: {_at(im.where, 'image', image_id)} ({im.name!r}) names camera "
                             f"{im.camera_id}, which {cams} does not have")
    for rig_id, cameras in (index.rigs or {}).items():
        for cam in cameras:
            if cam not in index.cameras:
                raise SceneError(f"{f['rigs']}: rig {rig_id} names camera {cam}, which {cams} does not have")
    if index.frames is None:
        return
    in_frame: dict = {}
    for fr in index.frames:
        where = _at(fr.where, "frame", fr.frame_id)
        if index.rigs is not None and fr.rig_id not in index.rigs:
            raise SceneError(f"{f['frames']}: {where} names rig {fr.rig_id}, which {f['rigs'].name} does not have")
        for kind, sensor, data_id in fr.data:
            if kind != _CAMERA:
                continue
            if data_id not in index.images:
                raise SceneError(f"{f['frames']}: {where} names image {data_id}, which {f['images'].name} "
                                 "does not have")
            im = index.images[data_id]
            if im.camera_id != sensor and im.camera_id in index.cameras:
                raise SceneError(f"{f['frames']}: {where} says image {data_id} ({im.name!r}) was taken by camera "
                                 f"{sensor}, but {f['images'].name} says camera {im.camera_id}")
            if index.rigs is not None and sensor not in index.rigs[fr.rig_id]:
                raise SceneError(f"{f['frames']}: {where} names camera {sensor}, which its rig {fr.rig_id} in "
                                 f"{f['rigs'].name} does not have")
            if data_id in in_frame:
                raise SceneError(f"{f['frames']}: {where} names image {data_id} ({im.name!r}), which "
                                 f"{in_frame[data_id]} names too")
            in_frame[data_id] = where
    for image_id, im in index.images.items():
        if image_id not in in_frame:
            raise SceneError(f"{f['images']}: {_at(im.where, 'image', image_id)} ({im.name!r}) is in no frame of "
                             f"{f['frames'].name} (did that file lose a line?)")


def _at(where: str, kind: str, ident: int) -> str:
    """"image 3" (binary) or "line 12: image 3" (text)."""
    return f"{where}: {kind} {ident}" if where.startswith("line") else f"{kind} {ident}"


def _check_poses(f: dict, index: ModelIndex) -> None:
    """The poses pycolmap will use (the frames', when the model has frames): finite, and a
    rotation quaternion that is not zero (pycolmap reads zeros as no rotation at all)."""
    if index.frames is not None:
        names = {i: im.name for i, im in index.images.items()}
        poses = [(f["frames"], _at(fr.where, "frame", fr.frame_id), fr.pose,
                  ", ".join(repr(names.get(d, d)) for k, _, d in fr.data if k == _CAMERA)) for fr in index.frames]
    else:
        poses = [(f["images"], _at(im.where, "image", i), im.pose, repr(im.name)) for i, im in index.images.items()]
    for path, where, pose, name in poses:
        label = f"{where} ({name})" if name else where
        if not all(math.isfinite(v) for v in pose):
            raise SceneError(f"{path}: {label} has a pose with NaN or infinite values: {' '.join(f'{v:g}' for v in pose)}")
        if math.sqrt(sum(v * v for v in pose[:4])) < 1e-9:
            raise SceneError(f"{path}: {label} has a rotation quaternion of length 0 (no rotation can be "
                             "made from it); the file is corrupt")


# --- after pycolmap refused the model -----------------------------------------------------------

def diagnose_failure(model_dir: Path, index: ModelIndex) -> Optional[str]:
    """The first line or record at fault in a model pycolmap refused (error path only), or None."""
    if index.ext == ".txt":
        return _diagnose_text_lines(model_dir) or _diagnose_points(model_dir, index)
    return _diagnose_points(model_dir, index)


def _diagnose_text_lines(model_dir: Path) -> Optional[str]:
    """The lines check_model leaves to pycolmap (cameras', images' and frames' own lines were
    read there): an image's pose pycolmap cannot read, its line of 2D points, the 3D points."""
    ims = model_dir / "images.txt"
    for no, s, points in _image_lines(ims):
        tok = s.split(maxsplit=9)
        if not all(math.isfinite(v) for v in _floats(tok[1:8])):
            return (f"{ims}: line {no}: image {tok[0]} ({tok[9]!r}) has a pose with NaN or infinite values "
                    "(COLMAP's text reader cannot read them)")
        if points is None:
            return (f"{ims}: line {no}: image {tok[0]} ({tok[9]!r}) has no line of 2D points after it "
                    "(the file is cut short?)")
        values = _floats(points.split())
        ids = _ints(points.split()[2::3])
        if (values is None or len(values) % 3 or ids is None or min(ids, default=0) < -1
                or not all(math.isfinite(v) for v in values)):
            return (f"{ims}: line {no + 1} is not a line of 2D points (X Y POINT3D_ID ..., finite numbers) "
                    f"for image {tok[0]}")
    pts = model_dir / "points3D.txt"
    for no, s in _content(pts):
        tok = s.split()
        values = _floats(tok)
        ints = _ints(tok[:1] + tok[4:7] + tok[8:])
        if (len(tok) < 8 or values is None or (len(tok) - 8) % 2 or ints is None or min(ints) < 0
                or not math.isfinite(values[7])):
            return (f"{pts}: line {no} is not a 3D point (POINT3D_ID X Y Z R G B ERROR TRACK[], with whole "
                    "numbers for the id, the colour and the track)")
        if not all(math.isfinite(v) for v in values[1:4]):
            return (f"{pts}: line {no}: 3D point {tok[0]} has NaN or infinite coordinates "
                    "(COLMAP's text reader cannot read them)")
    return None


def _rig_line_problem(tok) -> Optional[str]:
    """What is wrong with a rigs.txt line (None if COLMAP can read it)."""
    form = "is not a rig (RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[])"
    head = _ints(tok[:2])
    if head is None or len(head) < 2 or head[1] < 0:
        return form
    k = 2
    for j in range(head[1]):
        if len(tok) < k + 2 or _sensor(tok[k:k + 2]) is None or int(tok[k + 1]) < 0:
            return f"{form}: sensor {j + 1} is not SENSOR_TYPE (CAMERA or IMU) and SENSOR_ID"
        k += 2
        if j:
            if tok[k:k + 1] not in (["0"], ["1"]):
                return f"{form}: sensor {j + 1} has no HAS_POSE (0 or 1)"
            k += 1
            if tok[k - 1] == "1":
                pose = _floats(tok[k:k + 7])
                if pose is None or len(pose) < 7 or not all(math.isfinite(v) for v in pose):
                    return f"{form}: sensor {j + 1}'s pose is not 7 finite numbers"
                k += 7
    return None if k == len(tok) else f"{form}: {len(tok) - k} values more than its sensors need"


def _frame_line_problem(tok, allow_nonfinite: bool = False) -> Optional[str]:
    """What is wrong with a frames.txt line (None if COLMAP can read it)."""
    form = "is not a frame (FRAME_ID RIG_ID QW QX QY QZ TX TY TZ NUM_DATA_IDS DATA_IDS[])"
    head, pose, count = _ints(tok[:2]), _floats(tok[2:9]), _ints(tok[9:10])
    if head is None or len(head) < 2 or min(head) < 0 or pose is None or len(pose) < 7 or not count or count[0] < 0:
        return form
    if not allow_nonfinite and not all(math.isfinite(v) for v in pose):
        return f"{form}: its pose has NaN or infinite values"
    if len(tok) != 10 + 3 * count[0]:
        return f"{form}: it says {count[0]} data ids but has {len(tok) - 10} values for them (3 each)"
    for k in range(10, len(tok), 3):
        data_id = _ints(tok[k + 1:k + 3])
        if _sensor(tok[k:k + 2]) is None or data_id is None or min(data_id) < 0:
            return f"{form}: data id {(k - 10) // 3 + 1} is not SENSOR_TYPE SENSOR_ID DATA_ID"
    return None


def _diagnose_points(model_dir: Path, index: ModelIndex) -> Optional[str]:
    """Every 3D point's track against the images' observations, both ways."""
    ims, pts = model_dir / f"images{index.ext}", model_dir / f"points3D{index.ext}"
    observations: dict = {}
    try:
        if index.ext == ".bin":
            _images_bin(ims, ModelIndex(".bin"), observations)
            tracks = list(_points_bin_tracks(pts))
        else:
            for no, s, points in _image_lines(ims):
                values = np.array(_floats((points or "").split()) or [], np.float64)
                observations[int(s.split()[0])] = values[2::3].astype(np.int64)
            tracks = list(_points_txt_tracks(pts))
    except (SceneError, ValueError, IndexError, struct.error):
        return None
    names = {i: im.name for i, im in index.images.items()}
    seen = set()
    for pid, where, _ in tracks:
        if pid in seen:
            return f"{pts}: {where}3D point {pid} appears twice"
        seen.add(pid)
    for image_id, obs in observations.items():
        missing = [int(p) for p in obs if p != -1 and p not in seen]
        if missing:
            return (f"{ims}: image {image_id} ({names.get(image_id, '?')!r}) observes 3D point {missing[0]}, "
                    f"which {pts.name} does not have")
    for pid, where, track in tracks:
        for image_id, idx in track:
            obs = observations.get(image_id)
            if obs is None:
                return f"{pts}: {where}3D point {pid}'s track names image {image_id}, which {ims.name} does not have"
            if idx >= len(obs):
                return (f"{pts}: {where}3D point {pid}'s track names 2D point {idx} of image {image_id} "
                        f"({names.get(image_id, '?')!r}), which has {len(obs)} 2D points")
            if obs[idx] != pid:
                return (f"{pts}: {where}3D point {pid}'s track says image {image_id} ({names.get(image_id, '?')!r}) "
                        f"saw it as 2D point {idx}, but {ims.name} gives that 2D point to 3D point {obs[idx]}")
    return None


def _points_bin_tracks(path: Path):
    data = path.read_bytes()
    (n,) = struct.unpack_from("<Q", data, 0)
    off = 8
    for _ in range(n):
        (pid,) = struct.unpack_from("<Q", data, off)
        (length,) = struct.unpack_from("<Q", data, off + 43)
        off += 51
        track = np.frombuffer(data, dtype="<u4", count=2 * length, offset=off).reshape(-1, 2)
        off += 8 * length
        yield int(pid), "", [(int(a), int(b)) for a, b in track]


def _points_txt_tracks(path: Path):
    for no, s in _content(path):
        tok = s.split()
        track = [int(float(t)) for t in tok[8:]]
        yield int(tok[0]), f"line {no}: ", list(zip(track[0::2], track[1::2]))


# --- after pycolmap read a text model --------------------------------------------------------------

def check_text_tracks(model_dir: Path, rec) -> None:
    """A text model whose points' tracks hold fewer or more observations than ``images.txt``
    lists: points3D.txt lost lines or was cut short (pycolmap reads what is there)."""
    tracks = sum(p.track.length() for p in rec.points3D.values())
    listed = rec.compute_num_observations()
    if tracks != listed:
        raise SceneError(f"{model_dir / 'points3D.txt'}: its points' tracks hold {tracks} observations but "
                         f"images.txt lists {listed}: points are missing or cut short (is the file complete?)")
