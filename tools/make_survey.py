"""Synthetic underwater seafloor survey with ground truth, rendered with Blender Cycles.

Builds a procedural seabed (displaced, textured terrain of sand, or of square tiles or a grid
of bars with ``--floor``, matt or wet with ``--gloss``; rocks; a man-made structure: a rusty pipe
and a painted concrete block), flies a downward-looking camera (or, with ``--pitch``, one
looking forward and down) over it in a lawnmower pattern and renders every view twice: once with moving water caustics and once
without (the ground truth). It also writes the true camera poses and a sparse point cloud
as a COLMAP model, so the dataset can be used exactly like the output of SfM.

Usage (bpy as a Python module, or inside Blender)::

    python tools/make_survey.py --out data/sample --views 24 --width 256 --height 192 --seed 1
    blender -b --factory-startup --python tools/make_survey.py -- --out DIR [options]
    python tools/make_survey.py --out /tmp/survey --sfm   # also run pycolmap SfM on images/

Output folder::

    images/view_000.png ...   8-bit sRGB renders WITH caustics (what a camera would record;
                            with --overlay a time stamp burned into the top-left corner)
    clean/view_000.png  ...   the same views under the caustics' mean illumination (ground truth)
    sparse/0/               COLMAP binary model (cameras.bin, images.bin, points3D.bin) with the
                            TRUE poses and PINHOLE intrinsics, and sparse points with tracks
    sfm/0/                  (only with --sfm) pycolmap's own reconstruction from images/
    survey.json             every parameter, the cameras, per-shot caustic phase and mean gain
    frames.json             (only with --caustic-motion smooth) each frame's time, as a video import writes it
    looks/look_000_1.png .. (only with --look-frames K) the video's K frames between two shots, with
    looks.json              caustics (no clean/ copy), and their times and true poses: the look
                            frames a caustic estimator may gather from (recgs_addon/core/io/looks.py)
    README.md               short description of the dataset and the caustic model

Caustic model
-------------
A multiplicative gain ``g = 1 + s * (T - 1)`` (``T >= 0``, ``mean(T) == 1``) on the light reaching the
seabed, a new pattern for every shot: see tools/survey_light.py, which also describes the patterns
and the defaults.

Code
----
This file holds the command line, the orchestration and the file writing (PNGs, the COLMAP model,
survey.json, README.md). The rest lives beside it in tools/: ``survey_light.py`` (caustic and
sun-light model, numpy), ``survey_geometry.py`` (seabed, camera path, visibility, numpy),
``survey_materials.py`` (Blender node trees: caustic rig, seabed materials) and ``survey_scene.py``
(Blender meshes, lights, render settings, rendering).

Conventions: world frame is Blender's world frame (metres, z up). Poses are COLMAP
world-to-camera ``(R, t)``; the Blender camera matrix is built with
:func:`recgs_addon.core.model.cameras.blender_matrix_from_pose`. Intrinsics are PINHOLE with
``fx == fy`` and the principal point at exactly ``(width / 2, height / 2)`` (pixel centres at +0.5).
Images are converted from Cycles' linear EXR output with the plain sRGB transfer curve (the
"Standard" view transform) without dithering.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

TOOLS_DIR = Path(__file__).resolve().parent          # the survey_* modules beside this file
if str(TOOLS_DIR) not in sys.path:                  # (Blender's --python does not add it)
    sys.path.insert(0, str(TOOLS_DIR))

from recgs_addon.core.model.cameras import Camera, blender_matrix_from_pose  # noqa: E402
from survey_geometry import Heightfield, make_cameras, sample_triangles, visible_in_view  # noqa: E402
from survey_light import CAUSTIC_PATTERNS, caustic_gain, caustic_shots, light_direction  # noqa: E402
from survey_materials import CausticRig, _bpy, add_caustic_images  # noqa: E402
from survey_scene import (add_camera, build_scene, configure_render, log, render_exr,  # noqa: E402
                          scene_triangles, set_camera_pose)
from survey_lamp import LAMP_OFFSET, lamp_gain  # noqa: E402
from survey_water import WATER_TYPES, apply_water, ray_lengths, water_coefficients  # noqa: E402


# ---------------------------------------------------------------------------------------------
# Image files
# ---------------------------------------------------------------------------------------------

def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> 8-bit sRGB (IEC 61966-2-1 curve, clipped, rounded; 'Standard' view)."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def write_png(path: Path, rgb8: np.ndarray) -> None:
    import OpenImageIO as oiio
    buf = oiio.ImageBuf(np.ascontiguousarray(rgb8))
    if not buf.write(str(path)):
        raise RuntimeError(f"cannot write {path}: {buf.geterror()}")


# ---------------------------------------------------------------------------------------------
# Sparse points and the COLMAP model
# ---------------------------------------------------------------------------------------------

def make_sparse_points(args, cams: list[Camera], depths: list[np.ndarray], cleans: list[np.ndarray],
                       tris: np.ndarray, owner: np.ndarray, rng: np.random.Generator) -> dict:
    """Sample surface points, keep those seen (depth test) in >= 2 views, colour them, add noise."""
    # only triangles near the surveyed area (camera centres +- one footprint) are candidates
    centres = np.array([c.center for c in cams])
    reach = 2 * args.altitude * math.tan(math.radians(args.hfov) / 2)
    cxy = tris.mean(1)[:, :2]
    near = np.all((cxy > centres[:, :2].min(0) - reach) & (cxy < centres[:, :2].max(0) + reach), axis=1)
    e1 = tris[:, 1] - tris[:, 0]
    e2 = tris[:, 2] - tris[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    # denser sampling on rocks / structure than on the (large) terrain
    weights = area * near * np.where(owner == 0, 1.0, args.object_point_boost)
    pts, tri_idx = sample_triangles(tris, weights, args.points * 4, rng)
    vis = np.zeros((len(cams), len(pts)), bool)
    uv = np.zeros((len(cams), len(pts), 2))
    for j, (cam, depth) in enumerate(zip(cams, depths)):
        vis[j], uv[j] = visible_in_view(pts, cam, depth, args.depth_tol)
    keep = np.flatnonzero(vis.sum(0) >= 2)[: args.points]
    pts, vis, uv, obj = pts[keep], vis[:, keep], uv[:, keep], owner[tri_idx[keep]]
    # colour: mean clean 8-bit colour over the observations (nearest pixel)
    col_sum = np.zeros((len(pts), 3))
    for j, (cam, img) in enumerate(zip(cams, cleans)):
        c = np.clip(np.floor(uv[j, :, 0]).astype(np.int64), 0, cam.width - 1)
        r = np.clip(np.floor(uv[j, :, 1]).astype(np.int64), 0, cam.height - 1)
        col_sum += vis[j, :, None] * img[r, c].astype(np.float64)
    n_obs = vis.sum(0)
    colors = np.round(col_sum / n_obs[:, None]).astype(np.uint8)
    noisy = pts + rng.normal(0.0, args.point_noise, pts.shape) if args.point_noise > 0 else pts.copy()
    return {"xyz_true": pts, "xyz": noisy, "vis": vis, "uv": uv, "colors": colors, "object": obj}


def write_colmap_model(path: Path, cams: list[Camera], sparse: dict):
    """Write the true-pose COLMAP model (binary) with PINHOLE camera, images, points and tracks."""
    import pycolmap
    rec = pycolmap.Reconstruction()
    c0 = cams[0]
    cam = pycolmap.Camera(model="PINHOLE", width=c0.width, height=c0.height,
                          params=[c0.fx, c0.fy, c0.cx, c0.cy], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    vis, uv = sparse["vis"], sparse["uv"]
    obs_idx = np.cumsum(vis, axis=1) - 1                      # index of each observation in its image
    for j, c in enumerate(cams):
        img = pycolmap.Image(name=c.name, keypoints=np.ascontiguousarray(uv[j][vis[j]], dtype=np.float64),
                             camera_id=1, image_id=c.image_id)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t))
    image_ids = np.array([c.image_id for c in cams])
    for i in range(len(sparse["xyz"])):                      # pycolmap needs one call per point
        views = np.flatnonzero(vis[:, i])
        track = pycolmap.Track([pycolmap.TrackElement(int(image_ids[j]), int(obs_idx[j, i])) for j in views])
        rec.add_point3D(sparse["xyz"][i], track, sparse["colors"][i])
    path.mkdir(parents=True, exist_ok=True)
    rec.write(str(path))
    return rec


def reprojection_errors(rec) -> np.ndarray:
    """Per-observation reprojection error (pixels) of a pycolmap reconstruction (vectorised per image)."""
    errs = []
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        obs = [(p.xy, p.point3D_id) for p in img.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        X = np.array([rec.points3D[o[1]].xyz for o in obs])
        T = img.cam_from_world().matrix() if callable(img.cam_from_world) else img.cam_from_world.matrix()
        pc = X @ T[:3, :3].T + T[:3, 3]
        uv = pc[:, :2] / pc[:, 2:3]
        K = cam.calibration_matrix()
        uv = uv * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        errs.append(np.linalg.norm(uv - xy, axis=1))
    return np.concatenate(errs) if errs else np.zeros(0)


def run_sfm(out: Path, true_rec, threads: int) -> dict:
    """pycolmap SfM (``recgs_addon.core.capture.sfm``) on images/ -> sfm/0; compare with the truth."""
    import pycolmap

    from recgs_addon.core.errors import SceneError
    from recgs_addon.core.capture.sfm import SfmOptions, reconstruct

    t0 = time.time()
    shutil.rmtree(out / "sfm", ignore_errors=True)
    try:
        result = reconstruct(out / "images", out / "sfm" / "0", out / "database.db", SfmOptions(threads=threads))
    except SceneError:
        return {"registered": 0, "images": len(true_rec.images), "seconds": time.time() - t0}
    best = result.reconstruction
    res = {k: v for k, v in result.summary().items() if k != "model"}
    # compare with the truth: similarity from projection centres, then pose errors
    sim = pycolmap.align_reconstructions_via_proj_centers(best, true_rec, 0.1)
    if sim is not None:
        best.transform(sim)
        name_to_true = {im.name: im for im in true_rec.images.values()}
        pos_err, rot_err = [], []
        for im in best.images.values():
            if not im.has_pose:
                continue
            gt = name_to_true[im.name]
            pos_err.append(np.linalg.norm(im.projection_center() - gt.projection_center()))
            Rd = im.cam_from_world().rotation.matrix() @ gt.cam_from_world().rotation.matrix().T
            rot_err.append(math.degrees(math.acos(np.clip((np.trace(Rd) - 1) / 2, -1, 1))))
        res.update({"scale": float(sim.scale), "median_position_error_m": float(np.median(pos_err)),
                    "max_position_error_m": float(np.max(pos_err)),
                    "median_rotation_error_deg": float(np.median(rot_err))})
    return res


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------

def parse_args(argv=None) -> argparse.Namespace:
    """Command line; inside Blender (``blender -b --python ... -- args``) only the part after ``--``."""
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, type=Path, help="output dataset folder")
    g = p.add_argument_group("survey")
    g.add_argument("--views", type=int, default=24, help="number of photos")
    g.add_argument("--width", type=int, default=256, help="image width (px)")
    g.add_argument("--height", type=int, default=192, help="image height (px)")
    g.add_argument("--hfov", type=float, default=65.0, help="horizontal field of view (degrees)")
    g.add_argument("--seed", type=int, default=1, help="scene seed (terrain, objects, path jitter, points)")
    g.add_argument("--altitude", type=float, default=2.5, help="camera height above the seabed (m)")
    g.add_argument("--overlap", type=float, default=0.7, help="forward overlap of consecutive views")
    g.add_argument("--sidelap", type=float, default=0.6, help="overlap between neighbouring lines")
    g.add_argument("--pitch", type=float, default=8.0, help="forward pitch of the camera (degrees)")
    g.add_argument("--jitter-deg", type=float, default=1.5, help="random attitude jitter (degrees, std)")
    g.add_argument("--lines", type=int, default=0, help="lawnmower lines (0: about sqrt(views / 3))")
    g.add_argument("--path", choices=("lawnmower", "wander"), default="lawnmower",
                   help="survey lines, or a diver's wandering track that loops back over the seabed")
    g.add_argument("--altitude-swing", type=float, default=0.0,
                   help="the camera rises and sinks by this much (m) along the path: several ranges per point")
    g.add_argument("--altitude-period", type=float, default=40.0, help="views per rise and fall")
    g.add_argument("--rocks", type=int, default=7, help="number of rocks")
    g.add_argument("--floor", choices=("sand", "tiles", "grid"), default="sand",
                   help="the seabed: sand, square tiles (a pool, a slab), or a grid of bars (repetitive texture)")
    g.add_argument("--gloss", type=float, default=0.0,
                   help="0 = matt, 1 = wet and polished: highlights that follow the view")
    g.add_argument("--overlay", action="store_true",
                   help="burn a time stamp into the photos' top-left corner (as many cameras do)")
    g = p.add_argument_group("caustics")
    g.add_argument("--caustic-pattern", choices=CAUSTIC_PATTERNS, default="refraction", help="pattern kind")
    g.add_argument("--caustic-strength", type=float, default=0.45, help="0 = none, 1 = full contrast")
    g.add_argument("--caustic-scale", type=float, default=3.0, help="caustic tile size (m)")
    g.add_argument("--caustic-blur", type=float, default=0.03, help="softening (Gaussian std, m)")
    g.add_argument("--caustic-seed", type=int, default=None, help="pattern seed (default: --seed)")
    g.add_argument("--caustic-dt", type=float, default=1.0, help="seconds between shots")
    g.add_argument("--caustic-motion", choices=("random", "smooth"), default="random",
                   help="random: each shot's pattern at a random offset (photos); smooth: the pattern "
                        "drifts with time (video frames, --caustic-dt apart)")
    g.add_argument("--caustic-drift", default="0.01,0.004", help="smooth motion: drift in tile units per second")
    g.add_argument("--caustic-res", type=int, default=256, help="texture resolution (texels per tile)")
    g.add_argument("--look-frames", type=int, default=0,
                   help="smooth motion: render this many video frames between two shots as look frames "
                        "(looks/, looks.json: poses interpolated between the shots', caustics at their own time)")
    g = p.add_argument_group("water (attenuation and backscatter; see tools/survey_water.py)")
    g.add_argument("--water", choices=("none",) + tuple(WATER_TYPES), default="none",
                   help="water between seabed and camera; clean/ stays the true colour without it")
    g.add_argument("--water-attenuation", default="", help="override: direct attenuation 'r,g,b' per metre")
    g.add_argument("--water-backscatter", default="", help="override: backscatter coefficient 'r,g,b' per metre")
    g.add_argument("--water-colour", default="", help="override: veiling light 'r,g,b' (linear)")
    g = p.add_argument_group("a lamp on the camera (see tools/survey_lamp.py)")
    g.add_argument("--lamp", action="store_true",
                   help="light each photo by a lamp beside the camera (a cone fixed in the image, falling off "
                        "with range); clean/ stays the seabed under even light")
    g.add_argument("--lamp-beam", type=float, default=25.0, help="the lamp's beam half-width (degrees)")
    g.add_argument("--lamp-tilt", type=float, default=8.0, help="the lamp's axis, tilted down in the image (degrees)")
    g.add_argument("--vignette", type=float, default=0.0,
                   help="lens vignetting: the photo times (1 + s rho^2)^-2, rho the radius in half-widths")
    g = p.add_argument_group("lighting and rendering")
    g.add_argument("--sun-tilt", type=float, default=25.0, help="sun tilt from vertical (degrees)")
    g.add_argument("--sun-azimuth", type=float, default=35.0, help="sun azimuth (degrees from +x)")
    g.add_argument("--sun-strength", type=float, default=2.2, help="sun irradiance (W/m^2)")
    g.add_argument("--ambient-strength", type=float, default=0.6, help="blue-green world light strength")
    g.add_argument("--samples", type=int, default=8, help="Cycles samples per pixel")
    g.add_argument("--bounces", type=int, default=1, help="max diffuse light bounces")
    g.add_argument("--no-denoise", dest="denoise", action="store_false", help="disable OIDN denoising")
    g.add_argument("--denoise-prefilter", choices=("NONE", "FAST", "ACCURATE"), default="FAST",
                   help="OIDN prefilter of the albedo/normal guides")
    g.add_argument("--denoise-quality", choices=("FAST", "BALANCED", "HIGH"), default="BALANCED",
                   help="OIDN quality")
    g.add_argument("--threads", type=int, default=2, help="CPU threads for Cycles and pycolmap")
    g = p.add_argument_group("sparse model and extras")
    g.add_argument("--points", type=int, default=5000, help="target number of sparse points")
    g.add_argument("--object-point-boost", type=float, default=3.0,
                   help="point density on rocks/structure relative to the terrain")
    g.add_argument("--point-noise", type=float, default=0.005, help="std of point position noise (m)")
    g.add_argument("--depth-tol", type=float, default=0.02, help="visibility depth tolerance (m)")
    g.add_argument("--save-depth", action="store_true", help="also write depth/NAME.npy (float32 z)")
    g.add_argument("--save-blend", action="store_true", help="also save scene.blend")
    g.add_argument("--no-clean", dest="clean", action="store_false",
                   help="skip the ground-truth renders (clean/): half the time, for surveys only timed or sized")
    g.add_argument("--sfm", action="store_true", help="also run pycolmap SfM on images/ -> sfm/0")
    a = p.parse_args(argv)
    if a.caustic_seed is None:
        a.caustic_seed = a.seed
    if not 0.0 <= a.caustic_strength <= 1.0:
        p.error("--caustic-strength must be in [0, 1]")
    if a.look_frames < 0 or (a.look_frames and a.caustic_motion != "smooth"):
        p.error("--look-frames needs --caustic-motion smooth (frames of a video) and a count of 0 or more")
    if a.views < 1 or a.width < 8 or a.height < 8:
        p.error("need at least one view of at least 8 x 8 pixels")
    try:
        a.water_model = water_coefficients(a.water, a.water_attenuation, a.water_backscatter, a.water_colour)
    except ValueError as exc:
        p.error(f"--water-*: {exc}")
    return a


def prepare_output(out: Path) -> None:
    """Create the dataset folder, removing only outputs this script writes."""
    out.mkdir(parents=True, exist_ok=True)
    for d in ("images", "clean", "sparse", "depth", "sfm", "looks"):
        shutil.rmtree(out / d, ignore_errors=True)
    for f in ("survey.json", "frames.json", "looks.json", "README.md", "database.db", "scene.blend"):
        (out / f).unlink(missing_ok=True)
    for d in ("images", "clean", "sparse/0"):
        (out / d).mkdir(parents=True)


def _motion_text(args) -> str:
    if args.caustic_motion == "smooth":
        return (f"The pattern drifts smoothly from frame to frame ({args.caustic_dt} s apart, drift "
                f"{args.caustic_drift} tile units per second), as in a video: neighbouring frames share much "
                "of their light.")
    return (f"The pattern changes from shot to shot (time step {args.caustic_dt} s plus a random\n"
            "offset), as in a real survey where each photo is taken at a different instant.")


def dataset_readme(args, n_points: int, denoise: bool) -> str:
    return f"""# Synthetic seafloor survey (RecGS for Blender)

Generated by `tools/make_survey.py` (Blender Cycles, {args.samples} samples{' + OIDN denoiser' if denoise else ''}).

* `images/` - {args.views} views, {args.width}x{args.height}, 8-bit sRGB, **with** water caustics.
* `clean/`  - the same views without caustics: the ground truth for caustic removal.
* `sparse/0/` - COLMAP binary model with the TRUE poses, PINHOLE camera (fx = fy, principal point
  at the image centre) and {n_points} sparse points (seen in >= 2 views, depth-tested, position noise
  std {args.point_noise} m, observations = exact projections of the noise-free points).
* `survey.json` - all parameters, cameras, per-shot caustic phase and measured mean gain.

## Caustic model

Caustics multiply the light reaching the seabed by a gain g(x, y; shot) = 1 + s * (T - 1), where T is
a tileable `{args.caustic_pattern}` pattern with T >= 0 and mean(T) = 1 over a {args.caustic_scale} m tile,
and s = {args.caustic_strength}. g is looked up at each surface point projected along the sun direction
onto z = 0 and multiplies every seabed material's base colour, so in linear light an `images/`
pixel is approximately g times the matching `clean/` pixel. The mean of g is exactly 1: caustics
redistribute light without adding any, so `clean/` (g = 1) is the scene under the caustics' mean
illumination. {_motion_text(args)}
{_water_text(args)}{_lamp_text(args)}"""


def _lamp_text(args) -> str:
    if not (args.lamp or args.vignette):
        return ""
    lamp = (f"a lamp 15 cm below the camera lights the seabed: a cone of {args.lamp_beam:g} degrees (half-width) "
            f"tilted {args.lamp_tilt:g} degrees down, falling off as the inverse square of the distance from the "
            f"lamp, equal to `clean/` where its axis meets the seabed at {lamp_range(args):.2f} m"
            if args.lamp else "")
    vig = f"the lens vignettes by (1 + {args.vignette:g} rho^2)^-2" if args.vignette else ""
    return f"""
## Light on the camera

In `images/` {"; ".join(x for x in (lamp, vig) if x)} (tools/survey_lamp.py). `clean/` holds the
seabed under even light.
"""


def _water_text(args) -> str:
    w = args.water_model
    if w is None:
        return ""
    fmt = lambda v: ", ".join(f"{x:g}" for x in v)  # noqa: E731
    return f"""
## Water

Between seabed and camera: `{w["type"]}` water (tools/survey_water.py), per linear channel
I = J exp(-bD r) + Binf (1 - exp(-bB r)) with r the range along the ray, bD = ({fmt(w["attenuation_per_m"])}) per m,
bB = ({fmt(w["backscatter_per_m"])}) per m, Binf = ({fmt(w["veiling_light"])}). `images/` holds I; `clean/` holds J,
the seabed's true colour (under the caustics' mean light). The camera rises and sinks by
{args.altitude_swing} m about {args.altitude} m, so every point is seen from several ranges.
"""


def plan_survey(args) -> tuple[Heightfield, list[Camera], dict, tuple[float, float]]:
    """Seabed height field, survey cameras, path info and a terrain size that covers the survey."""
    hf = Heightfield(np.random.default_rng([args.seed, 1]), (12.0, 10.0))
    cams, path_info = make_cameras(args, hf)
    centres = np.array([c.center for c in cams])
    extent = centres[:, :2].max(0) - centres[:, :2].min(0)
    margin = 2 * path_info["footprint_across_m"] + 2.0
    terrain_size = (max(12.0, extent[0] + margin), max(10.0, extent[1] + margin))
    return hf, cams, path_info, terrain_size


#: 5x3 bitmaps of the digits, ':' and '-' a time stamp is drawn with
_GLYPHS = {"0": "111101101101111", "1": "010110010010111", "2": "111001111100111", "3": "111001111001111",
           "4": "101101111001001", "5": "111100111001111", "6": "111100111101111", "7": "111001001001001",
           "8": "111101111101111", "9": "111101111001111", ":": "000010000010000", "-": "000000111000000"}


def burn_time_stamp(img: np.ndarray, seconds: float) -> None:
    """Draw ``2026-01-01 hh:mm:ss`` in white on a dark band into ``img`` (H, W, 3 uint8)'s top-left
    corner, in place: the overlay a camera burns in. Its seconds change from shot to shot."""
    h, w = img.shape[:2]
    s = max(1, round(w / 320))   # glyph pixel size
    t = int(seconds)
    text = f"2026-01-01 {10 + t // 3600:02d}:{t // 60 % 60:02d}:{t % 60:02d}"
    x0, y0 = 2 * s, 2 * s
    img[y0 - s:y0 + 6 * s, x0 - s:x0 + 4 * s * len(text)] = 20
    for k, ch in enumerate(text):
        bits = _GLYPHS.get(ch)
        if bits is None:
            continue
        for r in range(5):
            for c in range(3):
                if bits[3 * r + c] == "1":
                    y, x = y0 + r * s, x0 + 4 * s * k + c * s
                    img[y:y + s, x:x + s] = 235


def render_views(args, out: Path, cams: list[Camera], rig: CausticRig, cam_ob, shots: list[dict]):
    """Render every view with and without caustics, put the water (if any) in front of the photo;
    write the PNGs. Returns (depths, sRGB8 images the sparse points take their colours from)."""
    depths, colour_sources = [], []
    water = args.water_model
    with tempfile.TemporaryDirectory(prefix="make_survey_") as tmp:
        tmp = Path(tmp)
        for j, cam in enumerate(cams):
            t0 = time.time()
            set_camera_pose(cam_ob, cam)
            rig.set_shot(j)
            lin_c, depth = render_exr(tmp, "caustic_")
            if args.clean and args.caustic_strength > 0:
                rig.set_shot(None)
                lin_g, _ = render_exr(tmp, "clean_")
            else:   # no caustics: the photo is its own ground truth (before the water)
                lin_g = lin_c
            img_g = linear_to_srgb8(lin_g)
            shots[j]["linear_mean_ratio"] = float(lin_c.mean() / max(lin_g.mean(), 1e-12))
            if args.lamp or args.vignette:
                lin_c = lin_c * lamp_light(args, cam, depth)
            if water is not None:
                rng = depth * ray_lengths(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
                lin_c = apply_water(lin_c, rng, water)
                shots[j]["range_m"] = [float(np.percentile(rng, 1)), float(np.percentile(rng, 99))]
            img_c = linear_to_srgb8(lin_c)
            if args.overlay:
                burn_time_stamp(img_c, args.caustic_dt * j)
            write_png(out / "images" / cam.name, img_c)
            if args.clean:
                write_png(out / "clean" / cam.name, img_g)
            depths.append(depth)
            # sparse points: SfM colours them from the photos; without water or a lamp the clean
            # views (the survey's sparse colours as they always were)
            colour_sources.append(img_c if water is not None or args.lamp or args.vignette else img_g)
            shots[j]["image"] = cam.name
            if args.save_depth:
                (out / "depth").mkdir(exist_ok=True)
                np.save(out / "depth" / (Path(cam.name).stem + ".npy"), depth)
            log(f"view {j + 1}/{len(cams)} {cam.name} rendered in {time.time() - t0:.1f} s "
                f"(mean caustic/clean {shots[j]['linear_mean_ratio']:.3f})")
    return depths, colour_sources


def look_cameras(args, cams: list[Camera]) -> tuple[list[Camera], list[float]]:
    """The ``--look-frames`` video frames between each two consecutive shots: their cameras
    (poses a share of the way between the two shots', :func:`interpolate_pose`) and times."""
    from recgs_addon.core.model.cameras import interpolate_pose
    k = args.look_frames
    looks, times = [], []
    for j in range(len(cams) - 1):
        a, b = cams[j], cams[j + 1]
        for m in range(1, k + 1):
            s = m / (k + 1)
            R, t = interpolate_pose(a.R, a.t, b.R, b.t, s)
            looks.append(Camera(f"look_{j:03d}_{m}.png", a.width, a.height, a.fx, a.fy, a.cx, a.cy, R, t,
                                camera_id=1, image_id=-1))
            times.append((j + s) * args.caustic_dt)
    return looks, times


def render_looks(args, out: Path, looks: list[Camera], times: list[float], rig: CausticRig, cam_ob,
                 first_shot: int) -> list[dict]:
    """Render the look frames (caustics, the lamp and the water as the photos have them, no
    ground truth) into looks/; returns their looks.json entries."""
    from recgs_addon.core.model.cameras import rotmat_to_quat
    (out / "looks").mkdir()
    water = args.water_model
    entries = []
    with tempfile.TemporaryDirectory(prefix="make_survey_looks_") as tmp:
        tmp = Path(tmp)
        for m, (cam, t) in enumerate(zip(looks, times)):
            t0 = time.time()
            set_camera_pose(cam_ob, cam)
            rig.set_shot(first_shot + m)
            lin, depth = render_exr(tmp, "look_")
            if args.lamp or args.vignette:
                lin = lin * lamp_light(args, cam, depth)
            if water is not None:
                rng = depth * ray_lengths(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
                lin = apply_water(lin, rng, water)
            img = linear_to_srgb8(lin)
            if args.overlay:
                burn_time_stamp(img, t)
            write_png(out / "looks" / cam.name, img)
            entries.append({"name": cam.name, "time_s": round(t, 6),
                            "qvec": [round(float(v), 12) for v in rotmat_to_quat(cam.R)],
                            "tvec": [round(float(v), 12) for v in cam.t]})
            log(f"look frame {m + 1}/{len(looks)} {cam.name} rendered in {time.time() - t0:.1f} s")
    return entries


def lamp_light(args, cam, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) the gain of ``--lamp`` (on the lamp path through ``--water``'s attenuation) and
    ``--vignette`` on a view (tools/survey_lamp.py)."""
    if not args.lamp:
        rho2 = (((np.arange(cam.width) + 0.5 - cam.cx)[None, :] ** 2
                 + (np.arange(cam.height) + 0.5 - cam.cy)[:, None] ** 2) / (0.5 * cam.width) ** 2)
        return np.repeat(((1.0 + args.vignette * rho2) ** -2)[..., None], 3, -1)
    att = args.water_model["attenuation_per_m"] if args.water_model is not None else (0.0, 0.0, 0.0)
    return lamp_gain(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, depth, lamp_range(args),
                     args.lamp_beam, args.lamp_tilt, offset=getattr(args, "lamp_offset", LAMP_OFFSET),
                     attenuation=att, vignette=args.vignette)


def lamp_range(args) -> float:
    """The survey's nominal range (m): where the lamp lights the seabed as clean/ shows it."""
    return args.altitude / math.cos(math.radians(args.pitch))


def _water_metadata(args, shots) -> dict | None:
    if args.water_model is None:
        return None
    ranges = np.array([s["range_m"] for s in shots if "range_m" in s])
    return dict(args.water_model, model="I = J exp(-attenuation r) + veiling_light (1 - exp(-backscatter r)), "
                "per linear channel, r the range along the ray (m); clean/ holds J",
                range_m=[float(ranges[:, 0].min()), float(ranges[:, 1].max())] if len(ranges) else None)


def survey_metadata(args, cams, path_info, terrain_size, light_dir, objects, obj_info, shots,
                    sparse, err, denoise) -> dict:
    """Everything needed to reproduce and interpret the dataset (written to survey.json)."""
    bpy = _bpy()
    track_len = sparse["vis"].sum(0)
    c0 = cams[0]
    return {
        "generator": "tools/make_survey.py",
        "blender": bpy.app.version_string,
        "parameters": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "denoiser": "OPENIMAGEDENOISE" if denoise else None,
        "intrinsics": {"model": "PINHOLE", "width": args.width, "height": args.height,
                       "fx": c0.fx, "fy": c0.fy, "cx": c0.cx, "cy": c0.cy},
        "path": path_info,
        "terrain_size_m": list(terrain_size),
        "sun_direction": light_dir.tolist(),
        "water": _water_metadata(args, shots),
        "lamp": None if not (args.lamp or args.vignette) else {
            "lamp": args.lamp, "beam_deg": args.lamp_beam, "tilt_deg": args.lamp_tilt, "vignette": args.vignette,
            "nominal_range_m": lamp_range(args),
            "model": "I = J beam(angle) (r0 / d)^2 exp(-attenuation d) (1 + vignette rho^2)^-2, d the lamp-to-"
                     "seabed distance; clean/ holds J (tools/survey_lamp.py)"},
        "objects": obj_info,
        "cameras": [{"name": c.name, "image_id": c.image_id, "R": c.R.tolist(), "t": c.t.tolist(),
                     "center": c.center.tolist(),
                     "blender_matrix_world": blender_matrix_from_pose(c.R, c.t).tolist()} for c in cams],
        "caustics": {"pattern": args.caustic_pattern, "strength": args.caustic_strength,
                     "tile_m": args.caustic_scale, "blur_m": args.caustic_blur, "seed": args.caustic_seed,
                     "resolution": args.caustic_res,
                     "model": "gain = 1 + strength * (T - 1), T >= 0, mean(T) = 1 over the tile; looked up at "
                              "world XY projected along sun_direction onto z = 0, divided by tile_m (repeat)",
                     "shots": shots},
        "sparse": {"points": int(len(sparse["xyz"])), "mean_track_length": float(track_len.mean()),
                   "points_per_object": {objects[k].name: int((sparse["object"] == k).sum())
                                         for k in range(len(objects))},
                   "mean_reprojection_error_px": float(err.mean()),
                   "max_reprojection_error_px": float(err.max())},
    }


def main(argv=None) -> int:
    t_start = time.time()
    args = parse_args(argv)
    try:
        import pycolmap  # noqa: F401  (fail before rendering, not after)
        import OpenImageIO  # noqa: F401
    except ImportError as exc:
        sys.exit(f"make_survey: {exc}. Install pycolmap and OpenImageIO into this Python "
                 "(see docs/dev/import_export.md).")
    out = args.out.resolve()
    bpy = _bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    prepare_output(out)
    log(f"output {out}")

    hf, cams, path_info, terrain_size = plan_survey(args)
    log(f"{len(cams)} views on {path_info['lines']} lines, spacing {path_info['along_spacing_m']:.2f} m "
        f"along / {path_info['line_spacing_m']:.2f} m across, "
        f"terrain {terrain_size[0]:.1f} x {terrain_size[1]:.1f} m")
    drift = tuple(float(v) for v in args.caustic_drift.split(","))
    shots = caustic_shots(len(cams), args.caustic_seed, args.caustic_dt, args.caustic_motion, drift)
    looks, look_times = look_cameras(args, cams) if args.look_frames else ([], [])
    look_shots = caustic_shots(len(looks), args.caustic_seed, args.caustic_dt, args.caustic_motion, drift,
                               times=look_times) if looks else []
    gains = [caustic_gain(args.caustic_pattern, args.caustic_res, s["time_s"], s["offset"],
                          args.caustic_seed, args.caustic_strength, args.caustic_blur / args.caustic_scale)
             for s in shots + look_shots]

    light_dir = light_direction(args.sun_tilt, args.sun_azimuth)
    rig, objects, obj_info = build_scene(args, hf, cams, terrain_size, light_dir)
    for s, st in zip(shots + look_shots, add_caustic_images(rig, gains)):
        s.update(st)
    denoise = configure_render(args)
    cam_ob = add_camera(cams[0])
    log(f"scene built in {time.time() - t_start:.1f} s (denoiser: {'OIDN' if denoise else 'off'})")
    if args.save_blend:
        bpy.ops.wm.save_as_mainfile(filepath=str(out / "scene.blend"), check_existing=False)

    t_render = time.time()
    depths, cleans = render_views(args, out, cams, rig, cam_ob, shots)
    look_entries = render_looks(args, out, looks, look_times, rig, cam_ob, len(cams)) if looks else []
    t_render = time.time() - t_render
    if not args.clean:
        (out / "clean").rmdir()

    tris, owner = scene_triangles(objects)
    sparse = make_sparse_points(args, cams, depths, cleans, tris, owner, np.random.default_rng([args.seed, 5]))
    rec = write_colmap_model(out / "sparse" / "0", cams, sparse)
    err = reprojection_errors(rec)
    log(f"sparse model: {len(sparse['xyz'])} points, mean track {sparse['vis'].sum(0).mean():.2f}, "
        f"reprojection error mean {err.mean():.4f} px max {err.max():.4f} px (point noise {args.point_noise} m)")

    meta = survey_metadata(args, cams, path_info, terrain_size, light_dir, objects, obj_info, shots,
                           sparse, err, denoise)
    if args.sfm:
        log("running pycolmap SfM on images/ ...")
        res = run_sfm(out, rec, args.threads)
        meta["sfm"] = res
        log(f"SfM registered {res['registered']}/{res['images']} images in {res['seconds']:.1f} s: {res}")
    meta["timing_s"] = {"render": t_render, "total": time.time() - t_start}
    (out / "survey.json").write_text(json.dumps(meta, indent=1))
    if args.caustic_motion == "smooth":   # frames of a video: their times, as a video import writes them
        from recgs_addon.core.io.frames import write_frame_times
        write_frame_times(out, {s["image"]: s["time_s"] for s in shots}, source="tools/make_survey.py",
                          fps=1.0 / args.caustic_dt)
    if look_entries:   # the video's frames between the shots, as a look-frame import writes them
        (out / "looks.json").write_text(json.dumps(
            {"source": "tools/make_survey.py", "fps": (args.look_frames + 1) / args.caustic_dt,
             "poses": "true (COLMAP cam_from_world: qvec w, x, y, z; tvec)", "looks": look_entries}, indent=1))
    (out / "README.md").write_text(dataset_readme(args, len(sparse["xyz"]), denoise))
    log(f"done in {time.time() - t_start:.1f} s (render {t_render:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
