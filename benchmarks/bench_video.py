"""Import Video on a 60-second 1080p clip of a generated seabed: frame choice and SfM timed per
step, the share of chosen frames registered, the camera-centre error after alignment; with
``--train-minutes N`` also RecGS training of the written survey.

    .venv/bin/python benchmarks/bench_video.py [--work out/bench_video] [--train-minutes N]
    .venv/bin/python benchmarks/bench_video.py --soft [--keyframes out/bench/surveys/dive-networks]

Goals (2 cores): frame choice + SfM under 10 minutes; >= 95 % of the chosen frames registered;
every registered camera centre within 1 % of the survey's extent (the diagonal of the true
centres' bounding box) after a similarity alignment (Umeyama on the centres).

How the clip is made. Rendering 1,800 frames at 1080p with Cycles would take hours on 2 cores,
so ``tools/make_survey.py`` renders 80 keyframes at 640 x 360 with their depth (a lawnmower
of 5 lines, forward overlap 0.75, caustics on; ~20-60 s a view here) and every clip frame is
made from them: its camera lies on the path between two consecutive keyframes (centre
interpolated linearly, rotation by quaternion slerp), and its image is the nearer keyframe
reprojected through its depth map into that camera (a z-buffered splat), holes filled from the
other keyframe, then from neighbouring pixels. Each frame thus has a true pose and real
parallax; the caustics change only at keyframes. The frames are upscaled to 1920 x 1080 by
FFmpeg's bicubic scaler and encoded with libx264 (CRF 18, 30 fps). Every 5th frame gets a
vertical motion blur (3 px at 640 x 360, 9 px at 1080p; the camera travels along the image's
vertical), and the camera hovers for 3 s in the middle (one pose, sensor noise): the figures
report how many chosen frames are blurred or hover frames. Upscaled 640 x 360 renders hold
less fine texture than a real 1080p camera, so SIFT finds fewer features than on real footage:
the SfM time here is a lower bound. Keyframes and clip are kept in ``--work`` and reused.

``--soft``: a clip like a small action camera's dive footage: soft detail (a 320 x 240 survey,
``--keyframes``, default the caustic benchmark's ``dive-networks`` with its sharp moving light
networks, blurred by 0.8 px and upscaled to 1280 x 960), low contrast (0.6 of the frame's), the
diver's slow lawnmower over the same seabed at the survey's own pace (one keyframe every 0.33 s,
48 s), no hover and no motion blur.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: Keyframes rendered by make_survey (their parameters are part of the cache key).
KEYFRAME_ARGS = ["--views", "80", "--width", "640", "--height", "360", "--overlap", "0.75", "--save-depth"]
FPS = 30
CLIP_SECONDS = 60.0
CLIP_SIZE = (1920, 1080)
HOVER_SECONDS = 3.0
BLUR_EVERY = 5
BLUR_PX = 3
NOISE_LEVELS = 1.0
GOAL_SECONDS = 600.0


@dataclass(frozen=True)
class Clip:
    """How a clip is made from its keyframes (see the module)."""
    name: str
    seconds: float
    size: tuple
    hover_seconds: float
    blur_every: int          # every Nth frame motion-blurred (0: none)
    contrast: float = 1.0    # the frame's contrast about its mean, kept
    soften_px: float = 0.0   # Gaussian blur (pixels at the keyframes' size) before upscaling


SHARP = Clip("seabed_60s_1080p", CLIP_SECONDS, CLIP_SIZE, HOVER_SECONDS, BLUR_EVERY)
SOFT = Clip("soft_8s_960p", 8.0, (1280, 960), 0.0, 0, contrast=0.6, soften_px=0.8)
GOAL_REGISTERED = 0.95
GOAL_CENTRE = 0.01


# -- rotations --------------------------------------------------------------------------------------

def quat_of(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def matrix_of(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    d = float(q0 @ q1)
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)


# -- keyframes --------------------------------------------------------------------------------------

def keyframes(work: Path) -> Path:
    """The rendered keyframe survey (rendered once, then reused)."""
    keys = work / "keyframes"
    meta = keys / "survey.json"
    if meta.is_file() and json.loads(meta.read_text()).get("video_bench_args") == KEYFRAME_ARGS:
        return keys
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, str(ROOT / "tools/make_survey.py"), "--out", str(keys), *KEYFRAME_ARGS],
                       cwd=ROOT)
    if r.returncode != 0:
        sys.exit("bench_video: tools/make_survey.py failed")
    data = json.loads(meta.read_text())
    data["video_bench_args"] = KEYFRAME_ARGS
    meta.write_text(json.dumps(data, indent=1))
    print(f"rendered {KEYFRAME_ARGS[1]} keyframes in {time.perf_counter() - t0:.0f} s", flush=True)
    return keys


class Keyframe:
    def __init__(self, keys: Path, cam: dict, K: np.ndarray):
        from recgs_addon.core.io.images import read_image

        self.R, self.t = np.array(cam["R"]), np.array(cam["t"])
        self.center = np.array(cam["center"])
        rgb = (read_image(keys / "images" / cam["name"]) * 255 + 0.5).astype(np.uint8)
        depth = np.load(keys / "depth" / (Path(cam["name"]).stem + ".npy"))
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w] + 0.5                      # pixel centres (COLMAP)
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        ok = np.isfinite(depth) & (depth > 0) & (depth < 1e3)
        self.points = (rays * depth[..., None])[ok].astype(np.float64)     # (N, 3) camera frame, metres
        self.colors = rgb[ok]
        self.size = (w, h)


def splat(key: Keyframe, R: np.ndarray, t: np.ndarray, K: np.ndarray):
    """Keyframe ``key`` seen from the camera (R, t): ((H, W, 3) uint8 image, (H, W) bool filled)."""
    w, h = key.size
    Rrel = R @ key.R.T
    trel = t - Rrel @ key.t
    X = key.points @ Rrel.T + trel
    z = X[:, 2]
    front = z > 0.05
    u = K[0, 0] * X[front, 0] / z[front] + K[0, 2]
    v = K[1, 1] * X[front, 1] / z[front] + K[1, 2]
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    pix = (row * w + col)[inside]
    zz = z[front][inside]
    order = np.lexsort((zz, pix))                           # by pixel, nearest first
    first = np.unique(pix[order], return_index=True)[1]
    chosen = order[first]
    img = np.zeros((h * w, 3), np.uint8)
    filled = np.zeros(h * w, bool)
    img[pix[chosen]] = key.colors[front][inside][chosen]
    filled[pix[chosen]] = True
    return img.reshape(h, w, 3), filled.reshape(h, w)


def _neighbours(img: np.ndarray, filled: np.ndarray):
    """Sum of the filled 4-neighbours' colours and their count, per pixel (no wrap at the edges)."""
    h, w = filled.shape
    fp = np.pad(filled, 1)
    ip = np.pad(img.astype(np.float32), ((1, 1), (1, 1), (0, 0)))
    acc = np.zeros((h, w, 3), np.float32)
    cnt = np.zeros((h, w), np.float32)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        f = fp[dy:dy + h, dx:dx + w]
        acc += ip[dy:dy + h, dx:dx + w] * f[..., None]
        cnt += f
    return acc, cnt


def close_cracks(img: np.ndarray, filled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill the one-pixel cracks a splat leaves (holes with >= 3 filled neighbours) from those
    neighbours, so the other keyframe (other caustics) only fills real gaps."""
    acc, cnt = _neighbours(img, filled)
    crack = ~filled & (cnt >= 3)
    img = img.copy()
    img[crack] = np.clip(acc[crack] / cnt[crack, None] + 0.5, 0, 255).astype(np.uint8)
    return img, filled | crack


def fill_holes(img: np.ndarray, filled: np.ndarray, rounds: int = 6) -> np.ndarray:
    """Holes take the mean of their filled 4-neighbours, a few rounds; the rest the image mean
    (ground no keyframe saw, at the corners of frames in the turns)."""
    img, filled = img.astype(np.float32), filled.copy()
    for _ in range(rounds):
        if filled.all():
            break
        acc, cnt = _neighbours(img, filled)
        grow = ~filled & (cnt > 0)
        img[grow] = acc[grow] / cnt[grow, None]
        filled |= grow
    img[~filled] = img[filled].mean(0) if filled.any() else 0
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


# -- the clip -----------------------------------------------------------------------------------------

def frame_poses(cams: list[dict], clip: Clip = SHARP):
    """Per clip frame: (R, t, centre, keyframe a, keyframe b, weight of b, hover?)."""
    n_keys = len(cams)
    n_frames = int(clip.seconds * FPS)
    moving = clip.seconds - clip.hover_seconds
    hover_start = clip.seconds / 2
    quats = [quat_of(np.array(c["R"])) for c in cams]
    centres = [np.array(c["center"]) for c in cams]
    out = []
    for f in range(n_frames):
        t = f / FPS
        hover = hover_start <= t < hover_start + clip.hover_seconds
        tau = hover_start if hover else (t if t < hover_start else t - clip.hover_seconds)
        s = min(tau / moving * (n_keys - 1), n_keys - 1 - 1e-9)
        a = int(s)
        alpha = s - a
        R = matrix_of(slerp(quats[a], quats[a + 1], alpha))
        C = (1 - alpha) * centres[a] + alpha * centres[a + 1]
        out.append((R, -R @ C, C, a, a + 1, alpha, hover))
    return out


def _soften(img: np.ndarray, sigma: float, contrast: float) -> np.ndarray:
    """A frame blurred by a Gaussian of ``sigma`` pixels and its contrast about its mean scaled."""
    x = img.astype(np.float32)
    if sigma > 0:
        r = int(math.ceil(3 * sigma))
        k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
        k /= k.sum()
        for axis in (0, 1):
            pad = [(0, 0)] * 3
            pad[axis] = (r, r)
            xp = np.pad(x, pad, mode="edge")
            x = sum(w * np.take(xp, np.arange(i, i + x.shape[axis]), axis=axis) for i, w in enumerate(k))
    mean = x.mean(axis=(0, 1), keepdims=True)
    return np.clip(mean + contrast * (x - mean) + 0.5, 0, 255).astype(np.uint8)


def make_clip(work: Path, keys: Path, spec: Clip = SHARP) -> tuple[Path, dict]:
    """The clip and its truth (per frame: centre, R, blurred, hover), made once."""
    import av

    clip, truth_path = work / f"{spec.name}.mp4", work / f"{spec.name}.json"
    meta = json.loads((keys / "survey.json").read_text())
    intr = meta["intrinsics"]
    K = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1.0]])
    if clip.is_file() and truth_path.is_file():
        return clip, {**json.loads(truth_path.read_text()), "K": K.tolist()}
    cams = meta["cameras"]
    poses = frame_poses(cams, spec)
    rng = np.random.default_rng(0)
    cache: dict[int, Keyframe] = {}
    truth = {"frames": [], "fps": FPS, "keyframes": len(cams), "K": K.tolist()}
    t0 = time.perf_counter()
    tmp = clip.with_suffix(".partial.mp4")
    with av.open(str(tmp), "w") as c:
        s = c.add_stream("libx264", rate=FPS)
        s.width, s.height = spec.size
        s.pix_fmt = "yuv420p"
        s.options = {"crf": "18", "preset": "veryfast"}
        s.thread_count = 2
        for f, (R, t, C, a, b, alpha, hover) in enumerate(poses):
            for k in (a, b):
                if k not in cache:
                    cache[k] = Keyframe(keys, cams[k], K)
            for k in [k for k in cache if k < a]:
                del cache[k]
            near, far = (cache[a], cache[b]) if alpha < 0.5 else (cache[b], cache[a])
            img, filled = close_cracks(*splat(near, R, t, K))
            img2, filled2 = close_cracks(*splat(far, R, t, K))
            take = ~filled & filled2
            img[take] = img2[take]
            img = fill_holes(img, filled | filled2)
            if spec.soften_px or spec.contrast != 1.0:
                img = _soften(img, spec.soften_px, spec.contrast)
            blurred = bool(spec.blur_every) and (f % spec.blur_every == spec.blur_every - 1) and not hover
            if blurred:   # vertical motion blur: a box of BLUR_PX rows
                acc = sum(np.roll(img.astype(np.float32), d, 0) for d in range(-(BLUR_PX // 2), BLUR_PX // 2 + 1))
                img = np.clip(acc / BLUR_PX + 0.5, 0, 255).astype(np.uint8)
            if hover:
                img = np.clip(img + rng.normal(0, NOISE_LEVELS, img.shape), 0, 255).astype(np.uint8)
            frame = av.VideoFrame.from_ndarray(img, format="rgb24").reformat(
                width=spec.size[0], height=spec.size[1], format="yuv420p", interpolation="BICUBIC")
            for packet in s.encode(frame):
                c.mux(packet)
            truth["frames"].append({"center": C.tolist(), "R": R.tolist(), "blurred": blurred, "hover": hover})
            if f % 300 == 299:
                print(f"clip: {f + 1}/{len(poses)} frames, {time.perf_counter() - t0:.0f} s", flush=True)
        for packet in s.encode():
            c.mux(packet)
    tmp.rename(clip)
    truth_path.write_text(json.dumps(truth))
    print(f"made the clip ({len(poses)} frames) in {time.perf_counter() - t0:.0f} s", flush=True)
    return clip, truth


# -- measuring ----------------------------------------------------------------------------------------

def umeyama(src: np.ndarray, dst: np.ndarray):
    """Similarity (scale, R, t) minimising |scale R src + t - dst|^2 over (N, 3) point pairs."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    scale = np.trace(np.diag(S) @ D) / (xs ** 2).sum(1).mean()
    return scale, R, mu_d - scale * R @ mu_s


def run_import(clip: Path, survey: Path, extra=()) -> tuple[dict, float]:
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "recgs_addon", "video", str(clip), "--out", str(survey),
                             "--overwrite", *extra], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    last = {}
    for line in proc.stdout:
        ev = json.loads(line)
        last[ev["event"]] = ev
    if proc.wait() != 0:
        sys.exit(f"bench_video: the video command failed: {last.get('error')}")
    return last["done"], time.perf_counter() - t0


def measure(survey: Path, truth: dict) -> dict:
    import pycolmap

    record = json.loads((survey / "frames.json").read_text())
    frames = truth["frames"]
    by_name = {f["name"]: f["index"] for f in record["frames"]}
    rec = pycolmap.Reconstruction(str(survey / "sparse" / "0"))
    ims = [im for im in rec.images.values() if im.has_pose]
    est = np.array([im.projection_center() for im in ims])
    true = np.array([frames[by_name[im.name]]["center"] for im in ims])
    scale, R, t = umeyama(est, true)
    err = np.linalg.norm(scale * est @ R.T + t - true, axis=1)
    all_centres = np.array([f["center"] for f in frames])
    extent = float(np.linalg.norm(all_centres.max(0) - all_centres.min(0)))
    rot = []
    for im in ims:
        Re = im.cam_from_world().rotation.matrix() @ R.T
        Rt = np.array(frames[by_name[im.name]]["R"])
        rot.append(math.degrees(math.acos(np.clip((np.trace(Re @ Rt.T) - 1) / 2, -1, 1))))
    chosen = [frames[f["index"]] for f in record["frames"]]
    cams = len(rec.cameras)
    track = np.array([p.track.length() for p in rec.points3D.values()])
    views = views_a_point(np.array([p.xyz for p in rec.points3D.values()]) * scale @ R.T + t, chosen,
                          truth["K"], record["size"])
    return {"chosen": len(record["frames"]), "registered": len(ims), "cameras": cams,
            "extent_m": extent, "centre_err_median": float(np.median(err)) / extent,
            "centre_err_max": float(err.max()) / extent, "rot_err_median_deg": float(np.median(rot)),
            "rot_err_max_deg": float(np.max(rot)), "chosen_blurred": sum(c["blurred"] for c in chosen),
            "blurred_in_clip": sum(f["blurred"] for f in frames),
            "chosen_hover": sum(c["hover"] for c in chosen), "stats": record["stats"],
            "points": len(track), "median_track": float(np.median(track)) if len(track) else 0.0,
            "median_views": float(np.median(views)) if len(views) else 0.0, "frame_size": record["size"]}


def views_a_point(points: np.ndarray, chosen: list[dict], K_keys: list, size: list) -> np.ndarray:
    """For each (N, 3) point (metres, true frame), in how many chosen frames its true camera
    sees it (inside the image, in front; occlusion ignored: a seabed seen from above)."""
    K = np.array(K_keys, np.float64)
    w, h = size
    K[:2] *= w / (2 * K[0, 2])                 # the keyframes' intrinsics at the written size
    counts = np.zeros(len(points), int)
    for c in chosen:
        Rc, C = np.array(c["R"]), np.array(c["center"])
        X = (points - C) @ Rc.T
        z = X[:, 2]
        u = K[0, 0] * X[:, 0] / np.maximum(z, 1e-9) + K[0, 2]
        v = K[1, 1] * X[:, 1] / np.maximum(z, 1e-9) + K[1, 2]
        counts += (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return counts


def train(survey: Path, minutes: float) -> dict:
    out = survey / "recgs_out"
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "recgs_addon", "train", str(survey), "--out", str(out),
                        "--mode", "recgs", "--max-minutes", str(minutes)], cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        return {"failed": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit code {r.returncode}"}
    m = json.loads((out / "metrics.json").read_text())
    return {"seconds": time.perf_counter() - t0, "iterations": m.get("iterations"), "gaussians": m.get("gaussians"),
            "psnr_test": m.get("psnr_test"), "ssim_test": m.get("ssim_test"), "out": str(out)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_video",
                   help="folder for the keyframes, the clip and the survey (reused)")
    p.add_argument("--train-minutes", type=float, default=None, help="also train the survey (RecGS) this long")
    p.add_argument("--soft", action="store_true", help="the soft, low-contrast clip (see the module) instead")
    p.add_argument("--keyframes", type=Path, default=ROOT / "out" / "bench" / "surveys" / "dive-networks",
                   help="--soft: the survey (with depth/) the clip is made from")
    p.add_argument("--seconds", type=float, default=None,
                   help="--soft: the clip's length (the same path, slower: 48 s is the survey's own pace)")
    p.add_argument("--video-args", default="", help="more arguments for the video command (e.g. '--step 0.2')")
    args = p.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    spec = SOFT if args.soft else SHARP
    if args.soft and args.seconds:
        spec = replace(SOFT, name=f"soft_{args.seconds:g}s_960p", seconds=args.seconds)
    keys = args.keyframes if args.soft else keyframes(args.work)
    clip, truth = make_clip(args.work, keys, spec)
    survey = args.work / ("survey" if spec is SHARP else f"survey-{spec.name}")
    done, wall = run_import(clip, survey, args.video_args.split())
    m = measure(survey, truth)
    steps = done["step_seconds"]
    sfm_s = steps["features"] + steps["matching"] + steps["mapping"]
    share = m["registered"] / m["chosen"]
    print()
    print(f"# Import Video: {clip.name} ({len(truth['frames'])} frames, {FPS} fps, "
          f"{spec.size[0]}x{spec.size[1]}; {truth['keyframes']} rendered keyframes)")
    print(f"frames chosen        {m['chosen']} of {done['frame_count']} (windows {m['stats']['windows']}, "
          f"near-duplicates {m['stats']['near_duplicates']}, dark {m['stats']['dark_windows']}, "
          f"thinned {m['stats'].get('thinned', 0)}; by {m['stats'].get('by', 'time')}); "
          f"written at {m['frame_size'][0]}x{m['frame_size'][1]}")
    print(f"  blurred among them {m['chosen_blurred']} (the clip: {m['blurred_in_clip']} of {len(truth['frames'])} "
          f"frames blurred); from the {spec.hover_seconds:g} s hover: {m['chosen_hover']}")
    print(f"time                 frame choice {steps['frames']:.1f} s, features {steps['features']:.1f} s, "
          f"matching {steps['matching']:.1f} s, mapping {steps['mapping']:.1f} s; "
          f"total {steps['frames'] + sfm_s:.1f} s (command wall time {wall:.1f} s)")
    print(f"registered           {m['registered']} of {m['chosen']} ({100 * share:.1f} %), {m['cameras']} camera(s), "
          f"{m['points']} points (median track {m['median_track']:.0f} frames)")
    print(f"views a point        median {m['median_views']:.0f} of the chosen frames see a point (true cameras)")
    print(f"camera centres       median {100 * m['centre_err_median']:.3f} %, max {100 * m['centre_err_max']:.3f} % "
          f"of the extent ({m['extent_m']:.2f} m); rotation median {m['rot_err_median_deg']:.3f} deg, "
          f"max {m['rot_err_max_deg']:.3f} deg")
    goals = [("frame choice + SfM < 10 min", steps["frames"] + sfm_s < GOAL_SECONDS),
             ("registered >= 95 %", share >= GOAL_REGISTERED),
             ("every camera centre within 1 % of the extent", m["centre_err_max"] <= GOAL_CENTRE)]
    for name, ok in goals:
        print(f"goal: {name:46s} {'met' if ok else 'NOT met'}")
    if args.train_minutes:
        res = train(survey, args.train_minutes)
        print(f"train --mode recgs --max-minutes {args.train_minutes:g}: {json.dumps(res)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
