"""Relight a generated survey without rendering it again: a lamp on the camera, vignetting and
water put over its ``clean/`` photos in numpy, from the depth it saved.

``tools/make_survey.py`` renders a seabed with Cycles (minutes a frame on two cores); a survey
made with ``--save-depth`` keeps every frame's true depth beside its evenly lit truth
(``clean/``), which is all ``tools/survey_lamp.py`` and ``tools/survey_water.py`` need. This
writes a new survey from such a one, in seconds: the same cameras, ``clean/`` and depth, the
photos (``images/``) lit as the options say, and the sparse points coloured from them as SfM
would (each point's mean 8-bit colour over the frames that see it, nearest pixel). The lamp and
the water are those of ``make_survey.py`` (same options, same conventions: ``clean/`` is the
seabed evenly lit out of the water, equal to the photo where the lamp's axis meets the seabed
at the nominal range); one more, ``--lamp-offset``, moves the lamp from the camera.

    .venv/bin/python tools/relight_survey.py out/bench/surveys/rows-looks OUT --lamp --lamp-beam 15

The source's caustics are not carried over (``clean/`` has none) unless ``--from images`` relights
the source's own photos (the caustic light falls on the seabed before the water acts on it);
its look frames are not carried over.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
TOOLS_DIR = Path(__file__).resolve().parent
for p in (REPO_ROOT, TOOLS_DIR):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from make_survey import lamp_light, lamp_range, linear_to_srgb8, write_png  # noqa: E402
from survey_lamp import LAMP_OFFSET  # noqa: E402
from survey_water import WATER_TYPES, apply_water, ray_lengths, water_coefficients  # noqa: E402


def srgb8_to_linear(img: np.ndarray) -> np.ndarray:
    s = np.asarray(img, np.float64) / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def _read(path: Path) -> np.ndarray:
    import OpenImageIO as oiio
    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.UINT8)
    if px is None or buf.has_error:
        raise RuntimeError(f"cannot read {path}: {buf.geterror()}")
    return np.asarray(px)[..., :3]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("source", type=Path, help="a survey made by tools/make_survey.py with --save-depth")
    p.add_argument("out", type=Path, help="the new survey's folder (must not exist)")
    p.add_argument("--lamp", action="store_true", help="light each photo by a lamp beside the camera")
    p.add_argument("--lamp-beam", type=float, default=25.0, help="the lamp's beam half-width (degrees)")
    p.add_argument("--lamp-tilt", type=float, default=8.0, help="the lamp's axis, tilted down in the image (degrees)")
    p.add_argument("--lamp-offset", default=",".join(f"{v:g}" for v in LAMP_OFFSET),
                   help="the lamp's place from the camera centre, 'x,y,z' metres in camera axes (x right, y down)")
    p.add_argument("--vignette", type=float, default=0.0, help="the lens's fall-off (1 + s rho^2)^-2")
    p.add_argument("--from", dest="source_photos", choices=("clean", "images"), default="clean",
                   help="the photos relit: the evenly lit truth (clean/, default) or the source's own photos "
                        "(images/: its caustics kept, under the water as caustic light is)")
    p.add_argument("--water", choices=("none",) + tuple(WATER_TYPES), default="none")
    p.add_argument("--water-attenuation", default="")
    p.add_argument("--water-backscatter", default="")
    p.add_argument("--water-colour", default="")
    a = p.parse_args(argv)
    a.water_model = water_coefficients(a.water, a.water_attenuation, a.water_backscatter, a.water_colour)
    a.lamp_offset = tuple(float(v) for v in a.lamp_offset.split(","))
    if len(a.lamp_offset) != 3:
        p.error("--lamp-offset takes 'x,y,z'")
    return a


def main(argv=None) -> int:
    import pycolmap
    args = parse_args(argv)
    src, out = args.source.resolve(), args.out.resolve()
    meta = json.loads((src / "survey.json").read_text())
    if not (src / "depth").is_dir() or not (src / "clean").is_dir():
        sys.exit(f"relight_survey: {src} has no depth/ or clean/ (make it with --save-depth and clean views)")
    if out.exists():
        sys.exit(f"relight_survey: {out} exists")
    (out / "images").mkdir(parents=True)
    for name in ("clean", "depth"):
        shutil.copytree(src / name, out / name)
    for name in ("frames.json",):
        if (src / name).exists():
            shutil.copy2(src / name, out / name)
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    par = meta["parameters"]
    args.altitude, args.pitch = par["altitude"], par["pitch"]   # the nominal range (lamp_range)
    r0 = lamp_range(args)
    col_sum = {pid: np.zeros(3) for pid in rec.points3D}
    col_n = {pid: 0 for pid in rec.points3D}
    ranges = []
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        fx, fy, cx, cy = cam.params[:4]
        w, h = cam.width, cam.height
        depth = np.load(src / "depth" / (Path(img.name).stem + ".npy"))
        lin = srgb8_to_linear(_read(src / args.source_photos / img.name))
        if args.lamp or args.vignette:
            lin = lin * lamp_light(args, SimpleNamespace(width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy), depth)
        if args.water_model is not None:
            rng = depth * ray_lengths(w, h, fx, fy, cx, cy)
            lin = apply_water(lin, rng, args.water_model)
            fin = rng[np.isfinite(rng)]
            if fin.size:
                ranges.append((float(np.percentile(fin, 1)), float(np.percentile(fin, 99))))
        photo = linear_to_srgb8(lin)
        write_png(out / "images" / img.name, photo)
        for p2 in img.points2D:
            if p2.has_point3D():
                u = min(max(int(math.floor(p2.xy[0])), 0), w - 1)
                v = min(max(int(math.floor(p2.xy[1])), 0), h - 1)
                col_sum[p2.point3D_id] += photo[v, u]
                col_n[p2.point3D_id] += 1
    for pid, pt in rec.points3D.items():
        if col_n[pid]:
            pt.color = np.round(col_sum[pid] / col_n[pid]).astype(np.uint8)
    (out / "sparse" / "0").mkdir(parents=True)
    rec.write(str(out / "sparse" / "0"))
    relit = {"from": str(src), "photos": args.source_photos, "lamp": args.lamp, "beam_deg": args.lamp_beam,
             "tilt_deg": args.lamp_tilt, "offset_m": list(args.lamp_offset), "vignette": args.vignette, "nominal_range_m": r0,
             "water": args.water_model}
    meta["relit"] = relit
    meta["lamp"] = None if not (args.lamp or args.vignette) else {
        "lamp": args.lamp, "beam_deg": args.lamp_beam, "tilt_deg": args.lamp_tilt, "offset_m": list(args.lamp_offset),
        "vignette": args.vignette, "nominal_range_m": r0}
    if args.water_model is not None:
        meta["water"] = dict(args.water_model, range_m=[min(r[0] for r in ranges), max(r[1] for r in ranges)]
                             if ranges else None)
    (out / "survey.json").write_text(json.dumps(meta, indent=1))
    (out / "README.md").write_text(
        f"# A relit survey (tools/relight_survey.py)\n\nFrom `{src.name}`: its cameras, sparse points, depth and "
        f"`clean/` (the seabed evenly lit, out of the water); `images/` relit: {json.dumps(relit)}.\n")
    print(f"relight_survey: {len(rec.images)} photos relit into {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
