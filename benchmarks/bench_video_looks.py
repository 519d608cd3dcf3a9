"""Look frames through Import Video: a video-rate survey encoded as a clip, imported as a user
would, trained from its keyframes only, with its look frames, and plain; the held-out views
scored against ground truth at the generator's own poses.

    .venv/bin/python benchmarks/bench_video_looks.py [--survey out/bench/surveys/rows-video]
        [--work out/bench/video_looks] [--minutes 5] [--jobs 2] [--scale 4]

The survey is one that ``benchmarks/bench_caustics.py`` generates with look frames
(``rows-video``: keyframes a second apart and five video frames between two, 6 frames a
second, every one with its true pose). The clip holds its frames in time order, keyframes and
look frames alike, upscaled ``--scale`` times by FFmpeg's bicubic scaler and encoded with
libx264 (CRF 18) at the survey's frame rate; the survey's held-out keyframes (every 8th, as a
job holds them out) are left out of the clip, so that no run sees them (the clip's time
stamps keep the gap). ``python -m recgs_addon video`` imports the clip at its defaults (frames
by motion, SfM with pycolmap, look frames every 0.1 s placed by their features); each run then
trains the imported survey at the survey's own size (``--max-side``) for ``--minutes``:

    recgs         the defaults (look frames gathered where moving light is found)
    recgs-nolooks --looks off (the imported keyframes only)
    3dgs          plain 3DGS

Scoring. The imported cameras are aligned to the true ones by a similarity (Umeyama on the
camera centres of the imported frames, each matched to its source frame by its time), and
every run's model (``point_cloud.ply``) is rendered at the true held-out keyframes carried into
the SfM frame with their true intrinsics, and compared with ``clean/`` (held-out PSNR against
ground truth). The caustic-free training images (``decaustic/``) of imported frames that are
keyframes of the survey are scored against ``clean/`` too (targets).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_video import run_import, umeyama  # noqa: E402
from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.io.images import read_image  # noqa: E402
from recgs_addon.core.io.ply import read_gaussian_ply  # noqa: E402
from recgs_addon.core.model.cameras import quat_to_rotmat  # noqa: E402
from recgs_addon.core.render.rasterizer import render  # noqa: E402
from recgs_addon.core.train.data import holdout_split  # noqa: E402

METHODS = {
    "recgs": ["--mode", "recgs"],
    "recgs-nolooks": ["--mode", "recgs", "--looks", "off"],
    "3dgs": ["--mode", "3dgs"],
}
HOLDOUT_EVERY = 8


def source_frames(survey: Path) -> list[dict]:
    """Every frame of the survey in time order: name, folder, time, true pose (R, t)."""
    scene = load_scene(survey, check_images=False)
    times = {f["name"]: f["time_s"] for f in json.loads((survey / "frames.json").read_text())["frames"]}
    frames = [{"name": c.name, "folder": "images", "time_s": float(times[c.name]), "R": c.R, "t": c.t,
               "key": True} for c in scene.cameras]
    for lk in json.loads((survey / "looks.json").read_text())["looks"]:
        R = quat_to_rotmat(np.array(lk["qvec"], np.float64))
        frames.append({"name": lk["name"], "folder": "looks", "time_s": float(lk["time_s"]), "R": R,
                       "t": np.array(lk["tvec"], np.float64), "key": False})
    return sorted(frames, key=lambda f: f["time_s"])


def heldout_names(survey: Path) -> list[str]:
    names = sorted(c.name for c in load_scene(survey, check_images=False).cameras)
    return [names[i] for i in holdout_split(names, HOLDOUT_EVERY)[1]]


def make_clip(survey: Path, clip: Path, scale: int, held: set) -> dict:
    """The survey's frames but the held-out keyframes as an H.264 clip (made once)."""
    import av

    if clip.is_file():
        return json.loads(clip.with_suffix(".json").read_text())
    frames = [f for f in source_frames(survey) if f["name"] not in held]
    fps = json.loads((survey / "looks.json").read_text())["fps"]
    rate = Fraction(fps).limit_denominator(1000)
    first = read_image(survey / frames[0]["folder"] / frames[0]["name"])
    h, w = first.shape[:2]
    tmp = clip.with_suffix(".partial.mp4")
    t0 = time.perf_counter()
    with av.open(str(tmp), "w") as c:
        s = c.add_stream("libx264", rate=rate)
        s.width, s.height = w * scale, h * scale
        s.pix_fmt = "yuv420p"
        s.options = {"crf": "18", "preset": "veryfast"}
        s.codec_context.time_base = 1 / rate
        for f in frames:
            img = read_image(survey / f["folder"] / f["name"])
            img = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
            frame = av.VideoFrame.from_ndarray(img, format="rgb24").reformat(
                width=w * scale, height=h * scale, format="yuv420p", interpolation="BICUBIC")
            frame.pts = int(round(f["time_s"] * rate))
            frame.time_base = 1 / rate
            for packet in s.encode(frame):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)
    tmp.rename(clip)
    info = {"frames": len(frames), "fps": float(rate), "size": [w * scale, h * scale],
            "held_out": sorted(held), "seconds": round(time.perf_counter() - t0, 1)}
    clip.with_suffix(".json").write_text(json.dumps(info, indent=1))
    return info


def alignment(imported: Path, frames: list[dict]) -> dict:
    """Similarity from the imported (SfM) frame to the true one, from the camera centres of the
    imported frames matched to their source frames by time."""
    times = {f["name"]: f["time_s"] for f in json.loads((imported / "frames.json").read_text())["frames"]}
    src_t = np.array([f["time_s"] for f in frames])
    est, true, keys = [], [], {}
    for cam in load_scene(imported, check_images=False).cameras:
        j = int(np.argmin(np.abs(src_t - times[cam.name])))
        if abs(src_t[j] - times[cam.name]) > 0.02:
            continue
        est.append(cam.center)
        true.append(-frames[j]["R"].T @ frames[j]["t"])
        if frames[j]["key"]:
            keys[cam.name] = frames[j]["name"]
    est, true = np.array(est), np.array(true)
    scale, R, t = umeyama(est, true)
    err = np.linalg.norm(scale * est @ R.T + t - true, axis=1)
    extent = float(np.linalg.norm(true.max(0) - true.min(0)))
    return {"scale": scale, "R": R, "t": t, "matched": len(est), "keyframes": keys,
            "centre_err_median": float(np.median(err)) / extent, "centre_err_max": float(err.max()) / extent}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((np.clip(a, 0, 1) - b) ** 2)))


@torch.no_grad()
def score_model(ply: Path, survey: Path, held: list[str], al: dict) -> float:
    """Mean PSNR of the model rendered at the true held-out keyframes against clean/."""
    g = read_gaussian_ply(ply)
    p = [torch.from_numpy(x) for x in (g.means, g.log_scales, g.quats, g.logit_opacities, g.sh)]
    cams = {c.name: c for c in load_scene(survey, check_images=False).cameras}
    out = []
    for name in held:
        c = cams[name]
        # x_true = s R x_sfm + t, so the camera in the SfM frame is (R_c R, (R_c t + t_c) / s)
        view = np.eye(4)
        view[:3, :3] = c.R @ al["R"]
        view[:3, 3] = (c.R @ al["t"] + c.t) / al["scale"]
        r = render(*p, torch.tensor(view, dtype=torch.float32), torch.tensor(c.K, dtype=torch.float32),
                   c.width, c.height, background=torch.zeros(3))
        out.append(psnr(r.rgb.numpy(), read_image(survey / "clean" / name)))
    return float(np.mean(out))


def score_targets(run: Path, survey: Path, keys: dict) -> tuple[float, int] | None:
    """Mean PSNR of the caustic-free images of imported keyframes against clean/."""
    out = []
    for name, src in keys.items():
        f = run / "decaustic" / name
        cands = [f] + sorted((run / "decaustic").glob(Path(name).stem + ".*"))
        f = next((x for x in cands if x.is_file()), None)
        if f is None:
            continue
        clean = read_image(survey / "clean" / src)
        img = read_image(f, size=(clean.shape[1], clean.shape[0]))
        out.append(psnr(img, clean))
    return (float(np.mean(out)), len(out)) if out else None


def train(imported: Path, out: Path, args: list[str], minutes: float, max_side: int) -> subprocess.Popen:
    out.parent.mkdir(parents=True, exist_ok=True)
    log = open(out.parent / f"{out.name}.log", "w")
    return subprocess.Popen([sys.executable, "-m", "recgs_addon", "train", str(imported), "--out", str(out),
                             "--max-minutes", str(minutes), "--max-side", str(max_side), *args],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--survey", type=Path, default=ROOT / "out" / "bench" / "surveys" / "rows-video")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench" / "video_looks")
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--jobs", type=int, default=2, help="runs side by side")
    p.add_argument("--scale", type=int, default=4, help="the clip's size over the survey's")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--score-only", action="store_true", help="score the runs already in --work")
    a = p.parse_args(argv)
    if not (a.survey / "looks.json").is_file():
        sys.exit(f"bench_video_looks: {a.survey} has no looks.json (make it with benchmarks/bench_caustics.py "
                 "--surveys rows-video)")
    a.work.mkdir(parents=True, exist_ok=True)
    held = heldout_names(a.survey)
    clip = a.work / "clip.mp4"
    info = make_clip(a.survey, clip, a.scale, set(held))
    print(f"clip: {info['frames']} frames at {info['fps']:g} fps, {info['size'][0]}x{info['size'][1]} "
          f"({len(held)} held-out keyframes left out)", flush=True)
    imported = a.work / "survey"
    if not (imported / "sparse").is_dir():
        done, secs = run_import(clip, imported)
        (a.work / "import.json").write_text(json.dumps({"done": done, "seconds": secs}, indent=1))
    imp = json.loads((a.work / "import.json").read_text())
    looks = json.loads((imported / "looks.json").read_text())["looks"] if (imported / "looks.json").is_file() else []
    print(f"import: {imp['seconds']:.0f} s, {len(load_scene(imported, check_images=False).cameras)} frames "
          f"registered, {len(looks)} look frames kept", flush=True)
    frames = source_frames(a.survey)
    al = alignment(imported, frames)
    print(f"alignment: {al['matched']} frames, centre error median {100 * al['centre_err_median']:.2f} % "
          f"(max {100 * al['centre_err_max']:.2f} %) of the extent; {len(al['keyframes'])} imported frames "
          "are keyframes", flush=True)
    width = int(read_image(a.survey / "clean" / held[0]).shape[1])
    methods = [m for m in a.methods.split(",") if m]
    if not a.score_only:
        queue, running = list(methods), []
        while queue or running:
            while queue and len(running) < a.jobs:
                m = queue.pop(0)
                running.append((m, train(imported, a.work / m, METHODS[m], a.minutes, width)))
            time.sleep(2)
            for m, proc in [r for r in running if r[1].poll() is not None]:
                running.remove((m, proc))
                print(f"{m}: exit code {proc.returncode}", flush=True)
    rows = []
    for m in methods:
        run = a.work / m
        if not (run / "metrics.json").is_file():
            continue
        mt = json.loads((run / "metrics.json").read_text())
        ps = mt.get("passes") or {}
        lf = ps.get("look_frames") or {}
        tg = score_targets(run, a.survey, al["keyframes"]) if (run / "decaustic").is_dir() else None
        rows.append({"method": m, "heldout_gt": score_model(run / "point_cloud.ply", a.survey, held, al),
                     "targets": tg, "steps": mt.get("iterations"), "gaussians": mt.get("gaussians"),
                     "looks": ps.get("median_looks"), "look_frames": lf, "caustic_s": ps.get("seconds"),
                     "planned_s": (mt.get("plan") or {}).get("work_seconds"),
                     "peak_gb": mt.get("peak_resident_bytes", 0) / 1e9, "job_s": mt.get("job_seconds"),
                     "kept": (mt.get("candidates") or {}).get("kept"), "light": (mt.get("light") or {}).get("reason")})
    print("\n| run | held-out vs ground truth (dB) | targets (dB, frames) | steps | Gaussians | looks a point "
          "| look frames used (posed / interpolated / misplaced / near held-out) | caustic work (s, planned) "
          "| peak memory (GB) | job (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        lf = r["look_frames"]
        tg = f"{r['targets'][0]:.2f} ({r['targets'][1]})" if r["targets"] else "-"
        used = (f"{lf.get('used')} of {lf.get('listed')} ({lf.get('given', 0)} / {lf.get('interpolated', 0)} / "
                f"{lf.get('misplaced', 0)} / {lf.get('near_heldout', 0)})") if lf else "-"
        work = f"{r['caustic_s']:.0f} ({r['planned_s']:.0f})" if r["caustic_s"] and r["planned_s"] else "-"
        looks = f"{r['looks']:.1f}" if r["looks"] else "-"
        print(f"| {r['method']} | {r['heldout_gt']:.2f} | {tg} | {r['steps']:,} | {r['gaussians']:,} | {looks} "
              f"| {used} | {work} | {r['peak_gb']:.2f} | {r['job_s']:.1f} |")
    (a.work / "results.json").write_text(json.dumps({"clip": info, "import": imp, "rows": rows,
                                                       "alignment": {k: v for k, v in al.items()
                                                                     if k in ("matched", "centre_err_median",
                                                                              "centre_err_max")}},
                                                      indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
