"""Make a full-size copy of a survey: every photo resized to ``--width`` (aspect kept) and
written as JPEG, the COLMAP cameras rescaled to match, the sparse points as they are. What an
artist's camera gives (12-24 MP) from a small generated survey, for the memory and time
benchmarks (``bench_survey_size.py``).

    .venv/bin/python benchmarks/scale_survey.py data/sample out/big/sample_23mp --width 5600
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def scale_survey(src: Path, dst: Path, width: int, quality: int = 92, folders=("images",)) -> dict:
    """Write ``dst`` (images/ as JPEG of ``width`` px, sparse/0 rescaled); returns a summary."""
    import OpenImageIO as oiio
    import pycolmap

    from recgs_addon.core.io.colmap import find_model_dir
    from recgs_addon.core.io.frames import read_frame_times, write_frame_times

    rec = pycolmap.Reconstruction(str(find_model_dir(src)))
    (dst / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    names = {}
    for cam_id, cam in rec.cameras.items():
        s = width / cam.width
        cam.rescale(int(round(cam.width * s)), int(round(cam.height * s)))
        rec.cameras[cam_id] = cam
    for img in rec.images.values():
        names[img.name] = Path(img.name).with_suffix(".jpg").name
        img.name = names[img.name]
    rec.write_binary(str(dst / "sparse" / "0"))
    t = time.perf_counter()
    for folder in folders:
        if not (src / folder).is_dir():
            continue
        (dst / folder).mkdir(parents=True, exist_ok=True)
        for old, new in names.items():
            buf = oiio.ImageBuf(str(src / folder / old))
            spec = buf.spec()
            h = int(round(spec.height * width / spec.width))
            big = oiio.ImageBufAlgo.resize(buf, filtername="triangle", roi=oiio.ROI(0, width, 0, h, 0, 1, 0, 3))
            if big.has_error:
                raise SystemExit(f"{src / folder / old}: {big.geterror()}")
            big.set_write_format(oiio.UINT8)
            big.specmod().attribute("Compression", f"jpeg:{quality}")
            if not big.write(str(dst / folder / new)):
                raise SystemExit(f"{dst / folder / new}: {big.geterror()}")
    times = read_frame_times(src)
    if times is not None:   # a video survey's frame times, under the new names
        write_frame_times(dst, {names[n]: t for n, t in times.items() if n in names}, source=str(src))
    size = sum(p.stat().st_size for p in (dst / "images").iterdir())
    return {"images": len(names), "width": width, "seconds": round(time.perf_counter() - t, 1),
            "megabytes": round(size / 2 ** 20, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    p.add_argument("--width", type=int, default=5600)
    p.add_argument("--quality", type=int, default=92)
    p.add_argument("--clean", action="store_true", help="scale clean/ (ground truth) too")
    a = p.parse_args(argv)
    print(scale_survey(a.src, a.dst, a.width, a.quality, ("images", "clean") if a.clean else ("images",)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
