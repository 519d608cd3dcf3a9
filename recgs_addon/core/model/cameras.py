"""Pinhole cameras and the one place where coordinate conventions are written down.

Conventions
-----------
* World frame: the COLMAP model's world frame is used unchanged as Blender's world frame
  (metres, whatever "up" the reconstruction has). No axis change is applied to the world.
* Camera frame (COLMAP / OpenCV): x right, y down, z forward (the camera looks along +z).
  A pose is world-to-camera: ``x_cam = R @ x_world + t``.
* Camera frame (Blender): x right, y up, the camera looks along -z. So
  ``x_blender_cam = CV_TO_BLENDER_CAM @ x_cv_cam`` with ``CV_TO_BLENDER_CAM = diag(1, -1, -1)``.
  A Blender camera's ``matrix_world`` (camera-to-world, Blender camera axes) is therefore
  ``[[R.T @ CV_TO_BLENDER_CAM, C], [0, 1]]`` with ``C = -R.T @ t`` the camera centre.
  This is the only axis change between COLMAP and Blender; every converter uses
  :func:`blender_matrix_from_pose` / :func:`pose_from_blender_matrix`.
* Pixels: pixel (i, j) (column i, row j) covers [i, i+1) x [j, j+1) and is centred at
  (i + 0.5, j + 0.5), as in COLMAP: ``u = fx * x / z + cx`` with cx = width / 2 for a centred
  principal point.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Rotation taking OpenCV/COLMAP camera axes to Blender camera axes (and back: it is its own inverse).
CV_TO_BLENDER_CAM = np.diag([1.0, -1.0, -1.0])


@dataclass
class Camera:
    """A pinhole view of the scene.

    Attributes:
        name: image file name relative to the image folder (e.g. ``"0001.png"``).
        width, height: image size in pixels.
        fx, fy, cx, cy: pinhole intrinsics in pixels (COLMAP convention, see module doc).
        R: (3, 3) float64 world-to-camera rotation.
        t: (3,) float64 world-to-camera translation.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray = field(repr=False)
    t: np.ndarray = field(repr=False)
    camera_id: int = -1
    image_id: int = -1

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def viewmat(self) -> np.ndarray:
        """(4, 4) world-to-camera matrix (OpenCV camera axes)."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Args:
            points: (N, 3) world coordinates.
        Returns:
            uv: (N, 2) pixel coordinates (continuous; pixel centres at +0.5).
            depth: (N,) camera-space z (positive in front of the camera).
        """
        return project_points(points, self.R, self.t, self.K)

    def in_view(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The world points (N, 3) in front of the camera and inside its image (no occlusion
        test): their indices (K,), pixel coordinates ``u``, ``v`` (K,) as :meth:`project`
        gives them, and ranges (K,), the distance from the camera's centre."""
        pc = np.asarray(points, np.float64) @ self.R.T + self.t
        z = pc[:, 2]
        u, v = _pixels(pc, self.K)
        seen = np.flatnonzero((z > 1e-6) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height))
        return seen, u[seen], v[seen], np.linalg.norm(pc[seen], axis=1)

    def scaled(self, factor: float) -> "Camera":
        """The same view at ``1/factor`` resolution (integer sizes, intrinsics scaled to match)."""
        return self.resized(max(1, int(round(self.width / factor))), max(1, int(round(self.height / factor))))

    def resized(self, width: int, height: int) -> "Camera":
        """The same view as an image of exactly ``width`` x ``height`` (e.g. a downscaled file)."""
        sx, sy = width / self.width, height / self.height
        return Camera(self.name, width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      self.R.copy(), self.t.copy(), self.camera_id, self.image_id)


def project_points(points: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray):
    """Pinhole projection. points (N, 3) world -> (uv (N, 2) pixels, depth (N,))."""
    pc = np.asarray(points, dtype=np.float64) @ np.asarray(R).T + np.asarray(t)
    return np.stack(_pixels(pc, K), axis=1), pc[:, 2]


def _pixels(pc: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of camera-space points ``pc`` (N, 3) through the pinhole ``K``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]


def blender_matrix_from_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) Blender camera ``matrix_world`` from a COLMAP world-to-camera pose (R, t)."""
    m = np.eye(4)
    m[:3, :3] = R.T @ CV_TO_BLENDER_CAM
    m[:3, 3] = -R.T @ t
    return m


def pose_from_blender_matrix(matrix_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP world-to-camera (R, t) from a Blender camera ``matrix_world`` (no scale)."""
    m = np.asarray(matrix_world, dtype=np.float64)
    R = (m[:3, :3] @ CV_TO_BLENDER_CAM).T
    t = -R @ m[:3, 3]
    return R, t


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (w, x, y, z) -> rotation matrices (..., 3, 3). Normalises first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z), w >= 0.

    Uses the numerically stable branch on the largest diagonal term (vectorised).
    """
    R = np.asarray(R, dtype=np.float64)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((R.shape[0], 4))
    # case w largest
    s = np.sqrt(np.maximum(1.0 + cand[np.arange(len(k)), k] * 2 - tr, 1e-300)) * 2  # 4*|component|
    for case in range(4):
        idx = k == case
        if not np.any(idx):
            continue
        r = R[idx]
        ss = s[idx]
        if case == 0:
            q[idx] = np.stack([0.25 * ss, (r[:, 2, 1] - r[:, 1, 2]) / ss,
                               (r[:, 0, 2] - r[:, 2, 0]) / ss, (r[:, 1, 0] - r[:, 0, 1]) / ss], 1)
        elif case == 1:
            q[idx] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / ss, 0.25 * ss,
                               (r[:, 0, 1] + r[:, 1, 0]) / ss, (r[:, 0, 2] + r[:, 2, 0]) / ss], 1)
        elif case == 2:
            q[idx] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / ss, (r[:, 0, 1] + r[:, 1, 0]) / ss,
                               0.25 * ss, (r[:, 1, 2] + r[:, 2, 1]) / ss], 1)
        else:
            q[idx] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / ss, (r[:, 0, 2] + r[:, 2, 0]) / ss,
                               (r[:, 1, 2] + r[:, 2, 1]) / ss, 0.25 * ss], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q.reshape(shape + (4,))


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """The unit quaternion (w, x, y, z) a share ``s`` in [0, 1] of the way from ``q0`` to ``q1``
    along the shorter arc (spherical linear interpolation)."""
    q0 = np.asarray(q0, np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, np.float64) / np.linalg.norm(q1)
    d = float(q0 @ q1)
    if d < 0:   # q and -q are one rotation: take the shorter way
        q1, d = -q1, -d
    if d > 0.9995:   # nearly the same: the chord is the arc
        q = q0 + s * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - s) * th) * q0 + math.sin(s * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


def interpolate_pose(R0: np.ndarray, t0: np.ndarray, R1: np.ndarray, t1: np.ndarray,
                     s: float) -> tuple[np.ndarray, np.ndarray]:
    """The world-to-camera pose (R, t) a share ``s`` of the way between two poses: the rotation
    by :func:`slerp`, the camera centre on the straight line between the two centres (a camera
    moving steadily between two frames of a video)."""
    R = quat_to_rotmat(slerp(rotmat_to_quat(R0), rotmat_to_quat(R1), s))
    c = (1 - s) * (-R0.T @ t0) + s * (-R1.T @ t1)
    return R, -R @ c


#: Sensor width used for Blender cameras (mm). Any value works; the lens is set to match fx.
BLENDER_SENSOR_WIDTH = 36.0


def blender_intrinsics(cam: Camera) -> dict:
    """Blender camera and render settings that reproduce a pinhole camera exactly.

    Blender, with ``sensor_fit='HORIZONTAL'``, maps the sensor width to the image width, so
    ``fx = lens / sensor_width * W``. Non-square pixels (fx != fy) are expressed with the
    render pixel aspect: Blender's y pixel is ``ycor = aspect_y / aspect_x`` x-pixels tall,
    so ``fy = fx / ycor``. The lens shift is in units of the image width (the sensor-fit
    dimension): ``cx = W/2 - shift_x W`` and ``cy = H/2 + shift_y W / ycor`` (COLMAP's v
    runs down, Blender's y up). Blender wants both aspects >= 1, so the smaller is 1.
    """
    W, H = cam.width, cam.height
    if cam.fx >= cam.fy:
        aspect_x, aspect_y = 1.0, cam.fx / cam.fy
    else:
        aspect_x, aspect_y = cam.fy / cam.fx, 1.0
    ycor = aspect_y / aspect_x
    return {
        "lens": cam.fx / W * BLENDER_SENSOR_WIDTH,
        "sensor_width": BLENDER_SENSOR_WIDTH,
        "sensor_fit": "HORIZONTAL",
        "shift_x": (W / 2.0 - cam.cx) / W,
        "shift_y": (cam.cy - H / 2.0) * ycor / W,
        "resolution_x": W,
        "resolution_y": H,
        "pixel_aspect_x": aspect_x,
        "pixel_aspect_y": aspect_y,
    }
