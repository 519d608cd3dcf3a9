"""The outside trial (2026-11-25): malformed inputs made from a real export and from a copy of
the sample survey, run through the command line as a user would, each outcome tallied.

    python tools/outside_trial.py WORKDIR [CASE_PREFIX ...]

Cases: P* ``info`` on PLY files, C* ``import`` on COLMAP surveys, T* a 30-step ``train``,
A* argument mistakes. Everything is written under WORKDIR (``data/sample`` is copied, never
changed); results go to ``WORKDIR/results-*.json``. A case expects an ``error`` (one
``error:`` line containing its ``blame``, a non-zero exit, no traceback), ``work`` (exit 0)
or ``warn`` (exit 0 with a warning). Verdicts: clear error, works, traceback, silently
accepted, wrong file blamed / none, refused (must work), hang (still running after the
time allowed: a limit ignored). All of it takes about 15 minutes on 2 cores.
"""
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(os.environ.get("REPO", Path(__file__).resolve().parents[1]))
PY = str(REPO / ".venv" / "bin" / "python")
SAMPLE = REPO / "data" / "sample"
WORK = Path(sys.argv[1])
ONLY = sys.argv[2:]
CASES = []


def case(cid, kind, expect, blame=None, note=""):
    """kind: info | import | train | cli. expect: error | work | warn."""
    def deco(fn):
        CASES.append(dict(id=cid, kind=kind, expect=expect, blame=blame, build=fn, note=note))
        return fn
    return deco


def run(argv, timeout=600):
    t = time.time()
    try:
        r = subprocess.run([PY, "-m", "recgs_addon", *argv], cwd=REPO, capture_output=True, text=True, timeout=timeout)
        return r.returncode, r.stdout, r.stderr, time.time() - t
    except subprocess.TimeoutExpired as e:
        dec = lambda b: b.decode(errors="replace") if isinstance(b, bytes) else (b or "")
        return "timeout", dec(e.stdout), dec(e.stderr), time.time() - t


# ---------------------------------------------------------------- sources
def export_ply():
    p = WORK / "export" / "point_cloud.ply"
    if not p.exists():
        rc, out, err, _ = run(["import", str(scene_copy("src_for_export")), "--out", str(WORK / "export")])
        assert rc == 0, err
    return p


def scene_copy(name):
    dst = WORK / "cases" / name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(SAMPLE, dst)
    return dst


def model(s):
    return s / "sparse" / "0"


def ply_parts():
    data = export_ply().read_bytes()
    head, body = data.split(b"end_header\n", 1)
    return head.decode().splitlines(), body


def write_ply(name, lines, body):
    p = WORK / "cases" / f"{name}.ply"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(("\n".join(lines) + "\nend_header\n").encode() + body)
    return p


def oiio():
    import OpenImageIO as o
    return o


def convert_images(folder, fn, ext=None):
    """Rewrite every image of ``folder`` through ``fn(array) -> (array, oiio type)``."""
    o = oiio()
    for p in sorted(folder.glob("*.png")):
        buf = o.ImageBuf(str(p))
        arr = np.asarray(buf.get_pixels(o.FLOAT))
        arr, fmt = fn(arr)
        dst = p.with_suffix(ext) if ext else p
        if arr.ndim == 2:
            arr = arr[:, :, None]
        spec = o.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
        out = o.ImageOutput.create(str(dst))
        assert out.open(str(dst), spec)
        out.write_image(np.ascontiguousarray(arr))
        out.close()
        if dst != p:
            p.unlink()


def rename_in_model(s, old, new):
    for f in model(s).glob("images.*"):
        f.write_bytes(f.read_bytes().replace(old.encode(), new.encode()))


# ---------------------------------------------------------------- PLY cases (info)
@case("P01", "info", "work")
def _(w):
    """intact export"""
    return [str(export_ply())]


@case("P02", "info", "error", "dup.ply")
def _(w):
    """a property name declared twice"""
    lines, body = ply_parts()
    i = lines.index("property float opacity")
    lines[i + 1] = "property float opacity"     # replace scale_0 by a second opacity
    return [str(write_ply("dup", lines, body))]


@case("P03", "info", "error", "short.ply")
def _(w):
    """vertex count short of the body"""
    lines, body = ply_parts()
    vi = next(i for i, l in enumerate(lines) if l.startswith("element vertex"))
    n = int(lines[vi].split()[2])
    lines[vi] = f"element vertex {n - 100}"
    return [str(write_ply("short", lines, body))]


@case("P04", "info", "error", "long.ply")
def _(w):
    """vertex count above the body (file truncated)"""
    lines, body = ply_parts()
    vi = next(i for i, l in enumerate(lines) if l.startswith("element vertex"))
    lines[vi] = f"element vertex {int(lines[vi].split()[2]) + 1}"
    return [str(write_ply("long", lines, body))]


@case("P05", "info", "error", "bigendian.ply")
def _(w):
    """big-endian header over little-endian data"""
    lines, body = ply_parts()
    lines[1] = "format binary_big_endian 1.0"
    return [str(write_ply("bigendian", lines, body))]


@case("P06", "info", "error", "cut.ply")
def _(w):
    """body cut mid-row"""
    lines, body = ply_parts()
    return [str(write_ply("cut", lines, body[:len(body) // 2 + 3]))]


@case("P07", "info", "error", "noend.ply")
def _(w):
    """header without end_header"""
    p = WORK / "cases" / "noend.ply"
    lines, _ = ply_parts()
    p.write_text("\n".join(lines) + "\n")
    return [str(p)]


@case("P08", "info", "error", "random.ply")
def _(w):
    """random bytes"""
    p = WORK / "cases" / "random.ply"
    p.write_bytes(np.random.default_rng(0).bytes(5000))
    return [str(p)]


@case("P09", "info", "error", "empty.ply")
def _(w):
    """empty file"""
    p = WORK / "cases" / "empty.ply"
    p.write_bytes(b"")
    return [str(p)]


@case("P10", "info", "error", "badtype.ply")
def _(w):
    """unknown property type"""
    lines, body = ply_parts()
    lines[lines.index("property float opacity")] = "property float16 opacity"
    return [str(write_ply("badtype", lines, body))]


@case("P11", "info", "error", "points.ply")
def _(w):
    """a plain coloured point cloud, not Gaussians"""
    import pycolmap
    rec = pycolmap.Reconstruction(str(model(SAMPLE)))
    p = WORK / "cases" / "points.ply"
    rec.export_PLY(str(p))
    return [str(p)]


@case("P12", "info", "warn", "somenan.ply")
def _(w):
    """some rows NaN (dropped with a warning)"""
    lines, body = ply_parts()
    arr = np.frombuffer(body, "<f4").copy().reshape(-1, sum(l.startswith("property") for l in lines))
    arr[:10, 0] = np.nan
    return [str(write_ply("somenan", lines, arr.tobytes()))]


@case("P13", "info", "error", "allnan.ply")
def _(w):
    """every row NaN"""
    lines, body = ply_parts()
    arr = np.frombuffer(body, "<f4").copy().reshape(-1, sum(l.startswith("property") for l in lines))
    arr[:, 0] = np.nan
    return [str(write_ply("allnan", lines, arr.tobytes()))]


@case("P14", "info", "work")
def _(w):
    """ASCII version of the export"""
    lines, body = ply_parts()
    k = sum(l.startswith("property") for l in lines)
    arr = np.frombuffer(body, "<f4").reshape(-1, k)
    lines[1] = "format ascii 1.0"
    text = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in arr) + "\n"
    return [str(write_ply("ascii", lines, text.encode()))]


@case("P15", "info", "error", "asciibad.ply")
def _(w):
    """ASCII with a garbage token"""
    lines, body = ply_parts()
    k = sum(l.startswith("property") for l in lines)
    arr = np.frombuffer(body, "<f4").reshape(-1, k)[:20]
    lines[1] = "format ascii 1.0"
    lines = [l if not l.startswith("element vertex") else "element vertex 20" for l in lines]
    rows = [" ".join(f"{v:.9g}" for v in row) for row in arr]
    rows[5] = rows[5].replace(" ", " x ", 1)
    return [str(write_ply("asciibad", lines, ("\n".join(rows) + "\n").encode()))]


@case("P16", "info", "error", "frest.ply")
def _(w):
    """f_rest count not a multiple of 3 (a property renamed)"""
    lines, body = ply_parts()
    # the export has SH degree 0: one f_rest property, by renaming nz
    lines[lines.index("property float nz")] = "property float f_rest_0"
    return [str(write_ply("frest", lines, body))]


@case("P17", "info", "error", "nofmt.ply")
def _(w):
    """no format line"""
    lines, body = ply_parts()
    del lines[1]
    return [str(write_ply("nofmt", lines, body))]


@case("P18", "info", "error", "hugecount.ply")
def _(w):
    """a count of 10^12"""
    lines, body = ply_parts()
    vi = next(i for i, l in enumerate(lines) if l.startswith("element vertex"))
    lines[vi] = "element vertex 1000000000000"
    return [str(write_ply("hugecount", lines, body))]


@case("P19", "info", "error", "missing.ply")
def _(w):
    """file does not exist"""
    return [str(WORK / "cases" / "missing.ply")]


@case("P20", "info", "error", "adir.ply")
def _(w):
    """a folder"""
    (WORK / "cases" / "adir.ply").mkdir(exist_ok=True)
    return [str(WORK / "cases" / "adir.ply")]


@case("P21", "info", "work")
def _(w):
    """CRLF header (Windows)"""
    lines, body = ply_parts()
    p = WORK / "cases" / "crlf.ply"
    p.write_bytes(("\r\n".join(lines) + "\r\nend_header\r\n").encode() + body)
    return [str(p)]


@case("P22", "info", "error", "facefirst.ply")
def _(w):
    """a face element before the vertices"""
    lines, body = ply_parts()
    vi = next(i for i, l in enumerate(lines) if l.startswith("element vertex"))
    lines[vi:vi] = ["element face 0", "property list uchar int vertex_indices"]
    return [str(write_ply("facefirst", lines, body))]


@case("P23", "info", "work", note="kept: a zero quaternion is no rotation, as in INRIA's code")
def _(w):
    """every rotation quaternion zero"""
    lines, body = ply_parts()
    names = [l.split()[2] for l in lines if l.startswith("property")]
    arr = np.frombuffer(body, "<f4").copy().reshape(-1, len(names))
    for c in ("rot_0", "rot_1", "rot_2", "rot_3"):
        arr[:, names.index(c)] = 0
    return [str(write_ply("zeroq", lines, arr.tobytes()))]


@case("P24", "info", "error", "bigscale.ply")
def _(w):
    """log-scales of 1e30 (finite, absurd)"""
    lines, body = ply_parts()
    names = [l.split()[2] for l in lines if l.startswith("property")]
    arr = np.frombuffer(body, "<f4").copy().reshape(-1, len(names))
    arr[:, names.index("scale_0")] = 1e30
    return [str(write_ply("bigscale", lines, arr.tobytes()))]


@case("P25", "info", "work", note="info reports 0 Gaussians")
def _(w):
    """a valid header with 0 vertices"""
    lines, body = ply_parts()
    vi = next(i for i, l in enumerate(lines) if l.startswith("element vertex"))
    lines[vi] = "element vertex 0"
    return [str(write_ply("zero", lines, b""))]


# ---------------------------------------------------------------- COLMAP cases (import)
def edit_rec(s, fn):
    import pycolmap
    rec = pycolmap.Reconstruction(str(model(s)))
    fn(rec)
    rec.write_binary(str(model(s)))


def to_text(s):
    import pycolmap
    rec = pycolmap.Reconstruction(str(model(s)))
    for f in model(s).glob("*.bin"):
        f.unlink()
    rec.write_text(str(model(s)))


def set_token(f, index, value):
    """Set token ``index`` of the first data line (not a comment) of the text file ``f``."""
    lines = f.read_text().splitlines()
    i = next(k for k, l in enumerate(lines) if l and not l.startswith("#"))
    t = lines[i].split()
    t[index] = value
    lines[i] = " ".join(t)
    f.write_text("\n".join(lines) + "\n")


@case("C01", "import", "work")
def _(w):
    """intact sample (binary, COLMAP 3.12 rigs/frames)"""
    return [str(scene_copy("C01"))]


@case("C02", "import", "work")
def _(w):
    """intact sample as a text model"""
    s = scene_copy("C02")
    to_text(s)
    return [str(s)]


@case("C03", "import", "error", "points3D.bin")
def _(w):
    """every 3D point NaN"""
    s = scene_copy("C03")
    def f(rec):
        for pid in rec.points3D:
            rec.points3D[pid].xyz = np.array([np.nan, np.nan, np.nan])
    edit_rec(s, f)
    return [str(s)]


@case("C04", "import", "warn", "points3D.bin")
def _(w):
    """some 3D points NaN (dropped with a warning)"""
    s = scene_copy("C04")
    def f(rec):
        for pid in list(rec.points3D)[:50]:
            rec.points3D[pid].xyz = np.array([np.nan, 0, 0])
    edit_rec(s, f)
    return [str(s)]


@case("C05", "import", "error", "cameras.bin")
def _(w):
    """NaN focal lengths"""
    s = scene_copy("C05")
    def f(rec):
        rec.cameras[1].params = [np.nan, np.nan, 128, 96]
    edit_rec(s, f)
    return [str(s)]


@case("C06", "import", "error", "view_003.png")
def _(w):
    """a NaN pose (frames.bin)"""
    import pycolmap
    s = scene_copy("C06")
    def f(rec):
        fr = rec.frames[rec.images[4].frame_id]
        fr.rig_from_world = pycolmap.Rigid3d(fr.rig_from_world.rotation, np.array([np.nan, 0.0, 1.0]))
    edit_rec(s, f)
    return [str(s)]


@case("C07", "import", "error", "images.bin")
def _(w):
    """two images with the same name (binary)"""
    s = scene_copy("C07")
    f = model(s) / "images.bin"
    f.write_bytes(f.read_bytes().replace(b"view_001.png", b"view_000.png"))
    return [str(s)]


@case("C08", "import", "error", "frames.bin")
def _(w):
    """truncated frames.bin"""
    s = scene_copy("C08")
    f = model(s) / "frames.bin"
    f.write_bytes(f.read_bytes()[:-30])
    return [str(s)]


@case("C09", "import", "error", "rigs.bin")
def _(w):
    """truncated rigs.bin"""
    s = scene_copy("C09")
    f = model(s) / "rigs.bin"
    f.write_bytes(f.read_bytes()[:-5])
    return [str(s)]


@case("C10", "import", "error", "cameras.bin")
def _(w):
    """0x0 camera"""
    s = scene_copy("C10")
    f = model(s) / "cameras.bin"
    d = bytearray(f.read_bytes())
    d[16:32] = struct.pack("<QQ", 0, 0)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C11", "import", "error", "view_002.png")
def _(w):
    """an image whose size differs from its camera's"""
    s = scene_copy("C11")
    o = oiio()
    p = s / "images" / "view_002.png"
    small = o.ImageBufAlgo.resize(o.ImageBuf(str(p)), roi=o.ROI(0, 128, 0, 96, 0, 1, 0, 3))
    small.write(str(p))
    return [str(s)]


@case("C12", "import", "error", "images.bin")
def _(w):
    """an image naming a missing camera (binary)"""
    s = scene_copy("C12")
    f = model(s) / "images.bin"
    d = bytearray(f.read_bytes())
    d[8 + 60:8 + 64] = struct.pack("<I", 7)    # first image's camera_id
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C13", "import", "error", "images.txt")
def _(w):
    """an image naming a missing camera (text)"""
    s = scene_copy("C13")
    to_text(s)
    set_token(model(s) / "images.txt", 8, "7")
    return [str(s)]


@case("C14", "import", "error", "cameras.bin")
def _(w):
    """unknown camera model id (binary)"""
    s = scene_copy("C14")
    f = model(s) / "cameras.bin"
    d = bytearray(f.read_bytes())
    d[12:16] = struct.pack("<i", 42)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C15", "import", "error", "cameras.txt")
def _(w):
    """unknown camera model name (text)"""
    s = scene_copy("C15")
    to_text(s)
    f = model(s) / "cameras.txt"
    f.write_text(f.read_text().replace("PINHOLE", "FANCY_LENS"))
    return [str(s)]


@case("C16", "import", "error", "cameras.txt")
def _(w):
    """NaN focal lengths (text)"""
    s = scene_copy("C16")
    to_text(s)
    set_token(model(s) / "cameras.txt", 4, "nan")
    return [str(s)]


@case("C17", "import", "error", "images.txt")
def _(w):
    """two images with the same name (text)"""
    s = scene_copy("C17")
    to_text(s)
    f = model(s) / "images.txt"
    f.write_text(f.read_text().replace("view_001.png", "view_000.png"))
    return [str(s)]


@case("C18", "import", "error", "images.txt")
def _(w):
    """a NaN pose (text)"""
    s = scene_copy("C18")
    to_text(s)
    set_token(model(s) / "images.txt", 5, "nan")
    return [str(s)]


@case("C19", "import", "error", "points3D.txt")
def _(w):
    """every 3D point NaN (text)"""
    s = scene_copy("C19")
    to_text(s)
    f = model(s) / "points3D.txt"
    out = []
    for l in f.read_text().splitlines():
        if l and not l.startswith("#"):
            t = l.split()
            t[1:4] = ["nan", "nan", "nan"]
            l = " ".join(t)
        out.append(l)
    f.write_text("\n".join(out) + "\n")
    return [str(s)]


@case("C20", "import", "error", "cameras.bin")
def _(w):
    """truncated cameras.bin"""
    s = scene_copy("C20")
    f = model(s) / "cameras.bin"
    f.write_bytes(f.read_bytes()[:-8])
    return [str(s)]


@case("C21", "import", "error", "images.bin")
def _(w):
    """truncated images.bin"""
    s = scene_copy("C21")
    f = model(s) / "images.bin"
    f.write_bytes(f.read_bytes()[:-1000])
    return [str(s)]


@case("C22", "import", "error", "points3D.bin")
def _(w):
    """truncated points3D.bin"""
    s = scene_copy("C22")
    f = model(s) / "points3D.bin"
    f.write_bytes(f.read_bytes()[:-1000])
    return [str(s)]


@case("C23", "import", "error", "images.bin")
def _(w):
    """images.bin count lies (says 25, holds 24)"""
    s = scene_copy("C23")
    f = model(s) / "images.bin"
    d = bytearray(f.read_bytes())
    d[0:8] = struct.pack("<Q", 25)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C24", "import", "error", "points3D.bin")
def _(w):
    """points3D.bin count lies (huge)"""
    s = scene_copy("C24")
    f = model(s) / "points3D.bin"
    d = bytearray(f.read_bytes())
    d[0:8] = struct.pack("<Q", 2 ** 62)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C25", "import", "error", "view_004.png")
def _(w):
    """an image file missing"""
    s = scene_copy("C25")
    (s / "images" / "view_004.png").unlink()
    return [str(s)]


@case("C26", "import", "error", "view_006.png")
def _(w):
    """an image file of random bytes"""
    s = scene_copy("C26")
    (s / "images" / "view_006.png").write_bytes(np.random.default_rng(1).bytes(3000))
    return [str(s)]


@case("C27", "import", "error", "view_007.png")
def _(w):
    """an empty image file"""
    s = scene_copy("C27")
    (s / "images" / "view_007.png").write_bytes(b"")
    return [str(s)]


@case("C28", "import", "work", note="accepted by import (header intact); training must stop cleanly")
def _(w):
    """a truncated PNG (header intact)"""
    s = scene_copy("C28")
    p = s / "images" / "view_005.png"
    p.write_bytes(p.read_bytes()[:3000])
    return [str(s)]


@case("C29", "import", "work")
def _(w):
    """16-bit PNG images"""
    s = scene_copy("C29")
    convert_images(s / "images", lambda a: (a, oiio().UINT16))
    return [str(s)]


@case("C30", "import", "work")
def _(w):
    """RGBA PNG images"""
    s = scene_copy("C30")
    convert_images(s / "images", lambda a: (np.concatenate([a, np.ones_like(a[..., :1])], -1), oiio().UINT8))
    return [str(s)]


@case("C31", "import", "work")
def _(w):
    """greyscale PNG images"""
    s = scene_copy("C31")
    convert_images(s / "images", lambda a: (a.mean(-1, keepdims=True), oiio().UINT8))
    return [str(s)]


@case("C32", "import", "work")
def _(w):
    """EXR images (float)"""
    s = scene_copy("C32")
    convert_images(s / "images", lambda a: (a, oiio().FLOAT), ".exr")
    convert_images(s / "clean", lambda a: (a, oiio().FLOAT), ".exr")
    for i in range(24):
        rename_in_model(s, f"view_{i:03d}.png", f"view_{i:03d}.exr")
    return [str(s)]


@case("C33", "import", "work")
def _(w):
    """JPEG images"""
    s = scene_copy("C33")
    convert_images(s / "images", lambda a: (a, oiio().UINT8), ".jpg")
    convert_images(s / "clean", lambda a: (a, oiio().UINT8), ".jpg")
    for i in range(24):
        rename_in_model(s, f"view_{i:03d}.png", f"view_{i:03d}.jpg")
    return [str(s)]


@case("C34", "import", "error", "images")
def _(w):
    """no images folder"""
    s = scene_copy("C34")
    shutil.rmtree(s / "images")
    return [str(s)]


@case("C35", "import", "error", "points3D.bin")
def _(w):
    """points3D.bin missing"""
    s = scene_copy("C35")
    (model(s) / "points3D.bin").unlink()
    return [str(s)]


@case("C36", "import", "error", "C36")
def _(w):
    """sparse/0 empty"""
    s = scene_copy("C36")
    for f in model(s).iterdir():
        f.unlink()
    return [str(s)]


@case("C37", "import", "error", "nowhere")
def _(w):
    """scene folder does not exist"""
    return [str(WORK / "cases" / "nowhere")]


@case("C38", "import", "error", "frames.bin")
def _(w):
    """a zero rotation quaternion in frames.bin"""
    s = scene_copy("C38")
    for name in ("frames.bin",):
        f = model(s) / name
        d = bytearray(f.read_bytes())
        d[8 + 8:8 + 8 + 32] = struct.pack("<4d", 0, 0, 0, 0)   # first frame's quaternion
        f.write_bytes(bytes(d))
    return [str(s)]


@case("C39", "import", "error", "cameras.bin")
def _(w):
    """a focal length of 0"""
    s = scene_copy("C39")
    def f(rec):
        rec.cameras[1].params = [0.0, 0.0, 128, 96]
    edit_rec(s, f)
    return [str(s)]


@case("C40", "import", "error", "cameras.txt")
def _(w):
    """0x0 camera (text)"""
    s = scene_copy("C40")
    to_text(s)
    f = model(s) / "cameras.txt"
    f.write_text(f.read_text().replace("PINHOLE 256 192", "PINHOLE 0 0"))
    return [str(s)]


@case("C41", "import", "error", "view_008.png")
def _(w):
    """an image that is a folder"""
    s = scene_copy("C41")
    (s / "images" / "view_008.png").unlink()
    (s / "images" / "view_008.png").mkdir()
    return [str(s)]


@case("C42", "import", "error", "points3D.txt")
def _(w):
    """text points3D.txt cut mid-line"""
    s = scene_copy("C42")
    to_text(s)
    f = model(s) / "points3D.txt"
    t = f.read_text()
    f.write_text(t[: len(t) // 2])
    return [str(s)]


@case("C43", "import", "error", "images.txt")
def _(w):
    """text images.txt missing its points line for the last image"""
    s = scene_copy("C43")
    to_text(s)
    f = model(s) / "images.txt"
    lines = f.read_text().splitlines()
    f.write_text("\n".join(lines[:-1]) + "\n")
    return [str(s)]


@case("C44", "import", "error", "frames.bin")
def _(w):
    """frames.bin: a frame names a missing rig"""
    s = scene_copy("C44")
    f = model(s) / "frames.bin"
    d = bytearray(f.read_bytes())
    d[8 + 4:8 + 8] = struct.pack("<I", 9)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C45", "import", "error", "rigs.bin")
def _(w):
    """rigs.bin: the rig's reference sensor is a missing camera"""
    s = scene_copy("C45")
    f = model(s) / "rigs.bin"
    d = bytearray(f.read_bytes())
    d[8 + 8 + 4:8 + 8 + 8] = struct.pack("<I", 5)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C46", "import", "error", "frames.bin")
def _(w):
    """frames.bin: a frame names a missing image"""
    s = scene_copy("C46")
    f = model(s) / "frames.bin"
    d = bytearray(f.read_bytes())
    # first frame: id u32, rig u32, pose 7 f64, n u32, then (type i32, sensor u32, data_id u64)
    d[8 + 68 + 8:8 + 68 + 16] = struct.pack("<Q", 99)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C47", "import", "error", "points3D.bin")
def _(w):
    """a point whose track names a missing image"""
    s = scene_copy("C47")
    f = model(s) / "points3D.bin"
    d = bytearray(f.read_bytes())
    # first point: id u64, xyz, rgb, err, track len u64, then (image_id u32, point2D_idx u32)
    d[8 + 51:8 + 55] = struct.pack("<I", 999)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C48", "import", "error", "images.bin")
def _(w):
    """an observation naming a missing 3D point"""
    s = scene_copy("C48")
    f = model(s) / "images.bin"
    d = bytearray(f.read_bytes())
    i = d.index(b"view_000.png\0") + 13 + 8      # first 2D point: x f64, y f64, point3D_id i64
    d[i + 16:i + 24] = struct.pack("<q", 10 ** 9)
    f.write_bytes(bytes(d))
    return [str(s)]


@case("C49", "import", "error", "C49")
def _(w):
    """the scene folder is a file"""
    p = WORK / "cases" / "C49"
    p.write_text("x")
    return [str(p)]


@case("C50", "import", "error", "images.bin", note="left: pycolmap reads poses from frames.bin; this copy is unused")
def _(w):
    """an Inf translation in images.bin's copy of a pose (frames.bin intact)"""
    s = scene_copy("C50")
    f = model(s) / "images.bin"
    d = bytearray(f.read_bytes())
    d[8 + 36:8 + 44] = struct.pack("<d", np.inf)
    f.write_bytes(bytes(d))
    return [str(s)]


# ---------------------------------------------------------------- training (train --iterations 30)
def train_args(s, out, *extra):
    return [str(s), "--out", str(out), "--iterations", "30", "--eager", *extra]


@case("T01", "train", "work")
def _(w):
    """intact sample"""
    return train_args(scene_copy("T01"), w / "out")


@case("T02", "train", "error", "view_005.png", note="one error line, exit 1, no litter, last checkpoint kept")
def _(w):
    """a truncated PNG that import accepts"""
    s = scene_copy("T02")
    p = s / "images" / "view_005.png"
    p.write_bytes(p.read_bytes()[:3000])
    return train_args(s, w / "out")


@case("T03", "train", "error", "view_005.png", note="checkpoints every step before it meets the bad image")
def _(w):
    """a truncated PNG met after checkpoints were written (--checkpoint-every 0)"""
    s = scene_copy("T03")
    p = s / "images" / "view_005.png"
    p.write_bytes(p.read_bytes()[:3000])
    return train_args(s, w / "out", "--checkpoint-every", "0", "--holdout-every", "0")


@case("T04", "train", "error", "view_008.png")
def _(w):
    """a truncated ground-truth PNG in clean/"""
    s = scene_copy("T04")
    p = s / "clean" / "view_008.png"
    p.write_bytes(p.read_bytes()[:3000])
    return train_args(s, w / "out")


@case("T05", "train", "work")
def _(w):
    """16-bit PNG images"""
    s = scene_copy("T05")
    convert_images(s / "images", lambda a: (a, oiio().UINT16))
    return train_args(s, w / "out")


@case("T06", "train", "work")
def _(w):
    """RGBA PNG images"""
    s = scene_copy("T06")
    convert_images(s / "images", lambda a: (np.concatenate([a, np.ones_like(a[..., :1])], -1), oiio().UINT8))
    return train_args(s, w / "out")


@case("T07", "train", "work")
def _(w):
    """greyscale PNG images"""
    s = scene_copy("T07")
    convert_images(s / "images", lambda a: (a.mean(-1, keepdims=True), oiio().UINT8))
    return train_args(s, w / "out")


@case("T08", "train", "work")
def _(w):
    """EXR images"""
    s = scene_copy("T08")
    convert_images(s / "images", lambda a: (a, oiio().FLOAT), ".exr")
    convert_images(s / "clean", lambda a: (a, oiio().FLOAT), ".exr")
    for i in range(24):
        rename_in_model(s, f"view_{i:03d}.png", f"view_{i:03d}.exr")
    return train_args(s, w / "out")


@case("T09", "train", "error", "view_003.exr")
def _(w):
    """an EXR image with NaN and Inf pixels"""
    s = scene_copy("T09")
    convert_images(s / "images", lambda a: (a, oiio().FLOAT), ".exr")
    shutil.rmtree(s / "clean")
    for i in range(24):
        rename_in_model(s, f"view_{i:03d}.png", f"view_{i:03d}.exr")
    o = oiio()
    p = s / "images" / "view_003.exr"
    a = np.asarray(o.ImageBuf(str(p)).get_pixels(o.FLOAT)).copy()
    a[10:20, 10:20] = np.nan
    a[30:40, 30:40] = np.inf
    out = o.ImageOutput.create(str(p))
    out.open(str(p), o.ImageSpec(a.shape[1], a.shape[0], 3, o.FLOAT))
    out.write_image(np.ascontiguousarray(a))
    out.close()
    return train_args(s, w / "out", "--holdout-every", "0")


@case("T10", "train", "warn")
def _(w):
    """some 3D points NaN"""
    s = scene_copy("T10")
    def f(rec):
        for pid in list(rec.points3D)[:50]:
            rec.points3D[pid].xyz = np.array([np.nan, 0, 0])
    edit_rec(s, f)
    return train_args(s, w / "out")


@case("T11", "train", "error", "cameras.bin")
def _(w):
    """NaN focal lengths"""
    s = scene_copy("T11")
    def f(rec):
        rec.cameras[1].params = [np.nan, np.nan, 128, 96]
    edit_rec(s, f)
    return train_args(s, w / "out")


@case("T12", "train", "error", "images.bin")
def _(w):
    """two images with the same name"""
    s = scene_copy("T12")
    f = model(s) / "images.bin"
    f.write_bytes(f.read_bytes().replace(b"view_001.png", b"view_000.png"))
    return train_args(s, w / "out")


@case("T13", "train", "error", "view_002.png")
def _(w):
    """a clean/ image of another size than its camera"""
    s = scene_copy("T13")
    o = oiio()
    p = s / "clean" / "view_002.png"
    small = o.ImageBufAlgo.resize(o.ImageBuf(str(p)), roi=o.ROI(0, 128, 0, 96, 0, 1, 0, 3))
    small.write(str(p))
    return train_args(s, w / "out")


@case("T14", "train", "error", "bad.ply")
def _(w):
    """--init-ply with a duplicated property"""
    lines, body = ply_parts()
    lines[lines.index("property float opacity") + 1] = "property float opacity"
    p = write_ply("bad", lines, body)
    return train_args(scene_copy("T14"), w / "out", "--init-ply", str(p))


@case("T15", "train", "work", note="kept: a zero quaternion is no rotation, as in INRIA's code")
def _(w):
    """--init-ply whose quaternions are all zero"""
    lines, body = ply_parts()
    names = [l.split()[2] for l in lines if l.startswith("property")]
    arr = np.frombuffer(body, "<f4").copy().reshape(-1, len(names))
    for c in ("rot_0", "rot_1", "rot_2", "rot_3"):
        arr[:, names.index(c)] = 0
    p = write_ply("zeroq", lines, arr.tobytes())
    return train_args(scene_copy("T15"), w / "out", "--init-ply", str(p))


@case("T16", "train", "error", "checkpoint.pt")
def _(w):
    """--resume from a truncated checkpoint"""
    out = w / "out"
    out.mkdir(parents=True)
    (out / "checkpoint.pt").write_bytes(b"PK\x03\x04" + b"\0" * 100)
    return train_args(scene_copy("T16"), out, "--resume")


@case("T17", "train", "error", "view_010.png")
def _(w):
    """--images folder missing one image"""
    s = scene_copy("T17")
    shutil.copytree(s / "clean", s / "alt")
    (s / "alt" / "view_010.png").unlink()
    return train_args(s, w / "out", "--images", "alt")


@case("T18", "train", "error", "view_010.png", note="ground truth is for scoring, but a named folder must be whole")
def _(w):
    """clean/ (ground truth) missing one image"""
    s = scene_copy("T18")
    (s / "clean" / "view_010.png").unlink()
    return train_args(s, w / "out")


# ---------------------------------------------------------------- CLI argument mistakes
def cli(cid, argv, blame, expect="error"):
    @case(cid, "cli", expect, blame)
    def _(w):
        sample = WORK / "cases" / "sample_copy"
        if not sample.exists():
            shutil.copytree(SAMPLE, sample)
        return [a.replace("SAMPLE", str(sample)).replace("EXPORT", str(export_ply())).replace("OUT", str(w / "out"))
                for a in argv]
    _.__doc__ = " ".join(argv)


cli("A01", [], "command")
cli("A02", ["frobnicate"], "frobnicate")
cli("A03", ["info"], "ply")
cli("A04", ["train", "SAMPLE"], "--out")
cli("A05", ["train", "SAMPLE", "--out", "OUT", "--iterations", "-5"], "iterations")
cli("A06", ["train", "SAMPLE", "--out", "OUT", "--iterations", "abc"], "iterations")
cli("A07", ["train", "SAMPLE", "--out", "OUT", "--budget", "abc"], "budget")
cli("A08", ["train", "SAMPLE", "--out", "OUT", "--budget", "-1"], "budget")
cli("A09", ["train", "SAMPLE", "--out", "OUT", "--downscale", "0"], "downscale")
cli("A10", ["train", "SAMPLE", "--out", "OUT", "--downscale", "1000"], "downscale")
cli("A11", ["train", "SAMPLE", "--out", "OUT", "--max-minutes", "nan"], "time limit")
cli("A12", ["train", "SAMPLE", "--out", "OUT", "--max-minutes", "-1"], "time limit")
cli("A13", ["train", "SAMPLE", "--out", "OUT", "--holdout-every", "-1"], "holdout")
cli("A14", ["train", "SAMPLE", "--out", "OUT", "--holdout-every", "1"], "every 1")
cli("A15", ["train", "SAMPLE", "--out", "OUT", "--images", "nonexistent"], "nonexistent")
cli("A16", ["train", "SAMPLE", "--out", "OUT", "--resume"], "checkpoint.pt")
cli("A17", ["train", "SAMPLE", "--out", "OUT", "--device", "cuda"], "cuda")
cli("A18", ["train", "SAMPLE", "--out", "SAMPLE/README.md", "--iterations", "5"], "README.md")
cli("A19", ["train", "SAMPLE", "--out", "OUT", "--checkpoint-every", "nan", "--iterations", "5"], "checkpoint-every")
cli("A20", ["train", "SAMPLE", "--out", "OUT", "--mode", "recgs", "--caustic-k", "4"], "odd")
cli("A21", ["train", "SAMPLE", "--out", "OUT", "--mode", "recgs", "--warmup", "-1"], "warmup")
cli("A22", ["train", "SAMPLE", "--out", "OUT", "--gt-images", "nonexistent"], "nonexistent")
cli("A23", ["train", "SAMPLE", "--out", "OUT", "--seed", "-1", "--iterations", "5"], "seed")
cli("A24", ["train", "SAMPLE", "--out", "OUT", "--seed", "100000000000000000000000"], "seed")
cli("A25", ["train", "SAMPLE", "--out", "OUT", "--iterations", "0"], "iterations")
cli("A26", ["train", "SAMPLE", "--out", "OUT", "--budget", "0"], "budget")
cli("A27", ["train", "SAMPLE", "--out", "OUT", "--sh-degree", "7"], "sh-degree")
cli("A28", ["train", "SAMPLE", "--out", "OUT", "--mode", "oracle", "--gt-images", "nonexistent"], "nonexistent")
cli("A29", ["train", "SAMPLE", "--out", "OUT", "--max-minutes", "inf", "--iterations", "5"], "max", expect="work")
cli("A30", ["train", "SAMPLE", "--out", "/proc/recgs_out", "--iterations", "5"], "/proc/recgs_out")
cli("A31", ["render", "missing.ply", "SAMPLE", "--out", "OUT"], "missing.ply")
cli("A32", ["render", "EXPORT", "SAMPLE", "--out", "OUT", "--names", "nope.png"], "nope.png")
cli("A33", ["render", "EXPORT", "SAMPLE", "--out", "OUT", "--downscale", "0"], "downscale")
cli("A34", ["import", "SAMPLE", "--out", "OUT", "--images", "nonexistent"], "nonexistent")
cli("A35", ["import", "SAMPLE", "--out", "SAMPLE/README.md"], "README.md")
cli("A36", ["sfm", "nonexistent", "--out", "OUT"], "nonexistent")
cli("A37", ["train", "SAMPLE", "--out", "OUT", "--checkpoint-every", "-5", "--iterations", "5"], "checkpoint-every")
cli("A38", ["train", "SAMPLE", "--out", "OUT", "--mode", "recgs", "--recurrence-tol", "nan"], "recurrence tol")
cli("A39", ["train", "SAMPLE", "--out", "OUT", "--mode", "recgs", "--robust-k", "-2"], "robust")
cli("A40", ["train", "SAMPLE", "--out", "OUT", "--images", "../../etc"], "etc")


# ---------------------------------------------------------------- run
def classify(c, rc, out, err, w):
    errs = [l for l in err.splitlines() if l.lower().lstrip().startswith(("error", "batch: error")) or ": error:" in l]
    warns = [l for l in err.splitlines() if "Warning" in l or "warning" in l.lower() or "dropped" in l]
    if rc == "timeout":
        return "hang"
    if "Traceback" in err:
        return "traceback"
    if rc == 0:
        if c["expect"] == "work":
            return "works"
        if c["expect"] == "warn":
            return "works with a warning" if warns else "silently accepted (warning expected)"
        return "accepted with a warning" if warns else "silently accepted"
    if c["expect"] == "work":
        return "refused (must work)"
    if not errs:
        return "non-zero exit, no error line"
    if c["blame"] and not any(c["blame"].lower() in l.lower() for l in errs):
        return "wrong file blamed / none"
    return "clear error"


def main():
    (WORK / "cases").mkdir(parents=True, exist_ok=True)
    results = []
    for c in CASES:
        if ONLY and not any(c["id"].startswith(p) for p in ONLY):
            continue
        w = WORK / "runs" / c["id"]
        if w.exists():
            shutil.rmtree(w)
        w.mkdir(parents=True)
        argv = c["build"](w)
        cmd = [c["kind"]] + argv if c["kind"] != "cli" else argv
        if c["kind"] == "import":
            cmd += ["--out", str(w / "out")]
        rc, out, err, dt = run(cmd, timeout=180 if c["kind"] == "cli" else 600)
        verdict = classify(c, rc, out, err, w)
        extra = {}
        o = w / "out"
        if c["kind"] == "train" and o.exists():
            extra["out_files"] = sorted(str(p.relative_to(o)) for p in o.rglob("*"))
            extra["tmp_left"] = [p for p in extra["out_files"] if ".tmp" in p]
        tail = [l for l in err.splitlines() if l.strip()][-3:]
        what = (c["build"].__doc__ or "").strip() + (f" ({c['note']})" if c["note"] else "")
        results.append(dict(id=c["id"], kind=c["kind"], what=what,
                            expect=c["expect"], rc=rc, verdict=verdict, seconds=round(dt, 1), stderr_tail=tail, **extra))
        print(f"{c['id']} {c['kind']:6s} {verdict:32s} rc={rc} {dt:5.1f}s  {results[-1]['what']}\n      "
              + "\n      ".join(t[:300] for t in tail), flush=True)
        if c["kind"] == "train" and "out_files" in extra:
            print(f"      out: {extra['out_files']}", flush=True)
    name = "results-" + ("-".join(ONLY) if ONLY else "all") + ".json"
    (WORK / name).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
