#!/usr/bin/env python3
"""Build the extension zips, one per platform, with the Python wheels the add-on needs bundled.

    python scripts/build_extension.py                 fetch wheels, write the manifest's lists, build dist/*.zip
    python scripts/build_extension.py --check         fail if the manifest's lists are not what PINS gives
    python scripts/build_extension.py --no-build      fetch wheels and write the manifest only
    python scripts/build_extension.py --blender PATH  build with a Blender binary (default: the bpy module)

What is bundled is decided here, in PINS/PLATFORMS/PYTHONS, and nowhere else: the script
downloads each pinned wheel for every platform and Python (``pip download --only-binary
--no-deps``, into a cache outside the repository), hard-links the chosen files into
``./wheels/`` (git-ignored, excluded from the walk in the manifest's ``[build]``, so only the
listed wheels enter a zip), rewrites the ``platforms`` and ``wheels`` lists of
``blender_manifest.toml`` between their marker comments, and runs Blender's own builder with
``--split-platforms``. Blender installs from a zip only the wheels whose platform and Python
tags match the running Blender (bl_pkg ``_extensions_wheel_filter_for_this_system``), so one
zip serves Blender 4.2-5.0 (Python 3.11) and 5.1+ (Python 3.13) of its platform.

numpy is never bundled: every Blender ships it, and the wheels of all extensions share one
``site-packages`` where a second numpy would shadow Blender's. The pinned wheels need nothing
else (their ``Requires-Dist`` is numpy, plus extras we do not use); :func:`check_requires`
fails the build if a new pin brings a dependency that is not listed here.
"""
from __future__ import annotations

import argparse
import email.parser
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "blender_manifest.toml"
WHEEL_DIR = ROOT / "wheels"
DEFAULT_CACHE = Path(os.environ.get("RECGS_WHEEL_CACHE", Path.home() / ".cache" / "recgs" / "wheels"))

#: Python versions of the supported Blenders: 4.2 LTS-5.0 use 3.11, 5.1 and later 3.13.
PYTHONS = ("3.11", "3.13")
#: Blender platform -> pip ``--platform`` tags accepted for it (pip also accepts older macOS
#: versions than the one named). Blender 4.2-5.x need macOS 11.2; glibc 2.28 on Linux.
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                  "manylinux2014_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-x64": ("macosx_11_0_x86_64",),
    "macos-arm64": ("macosx_11_0_arm64",),
}
#: Distribution -> version, for the import / preview / export path (torch is not bundled: the
#: training engine is installed on request, see recgs_addon/engine_install.py).
PINS = {
    "pycolmap": "4.2.1",
    "OpenImageIO": "3.0.21.0",
}
#: (distribution, platform) -> (version, pip platform tags) where the pin has no wheel:
#: pycolmap publishes macOS wheels for macOS 14+ on arm64 only since 3.13, and none for Intel
#: Macs after 3.12.5 (macOS 13+), measured with `pip download` on 2026-11-24. 3.12.5 (Linux
#: wheel, same sources) reads binary/text models and undistorts OPENCV/SIMPLE_RADIAL surveys
#: exactly as 4.2.1 does through core/io/colmap.py; its SfM (core/capture/sfm.py) is not yet checked.
OVERRIDES: dict[tuple[str, str], tuple[str, tuple[str, ...]]] = {
    ("pycolmap", "macos-arm64"): ("4.2.1", ("macosx_14_0_arm64",)),
    ("pycolmap", "macos-x64"): ("3.12.5", ("macosx_13_0_x86_64",)),
}
#: Requirements of the bundled wheels that Blender itself provides.
PROVIDED_BY_BLENDER = {"numpy"}

_BEGIN, _END = "# -- begin: written by scripts/build_extension.py", "# -- end: written by scripts/build_extension.py"


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def wheel_tags(filename: str) -> tuple[str, str, str, str, str]:
    """(name, version, python tag, abi tag, platform tag) of a wheel file name."""
    parts = filename[:-4].split("-")
    return parts[0], parts[1], parts[-3], parts[-2], parts[-1]


def blender_platforms(wheel_platform: str) -> set[str]:
    """Blender platforms of a wheel's platform tag (dotted compound tags included), as Blender's
    builder and installer read them: manylinux*_x86_64 -> linux-x64, win_amd64 -> windows-x64,
    macosx_*_x86_64 / _arm64 / _universal2 -> macos-x64 / macos-arm64 / both; ``any`` -> all."""
    out = set()
    for tag in wheel_platform.split("."):
        if tag == "any":
            out |= set(PLATFORMS)
        elif tag.startswith("manylinux") and tag.endswith("_x86_64"):
            out.add("linux-x64")
        elif tag == "win_amd64":
            out.add("windows-x64")
        elif tag.startswith("macosx_"):
            for arch, names in (("_x86_64", {"macos-x64"}), ("_arm64", {"macos-arm64"}),
                                ("_universal2", {"macos-x64", "macos-arm64"})):
                if tag.endswith(arch):
                    out |= names
    return out


def _macos_version(tag: str) -> tuple[int, int]:
    m = re.match(r"macosx_(\d+)_(\d+)_", tag)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def _matches(filename: str, dist: str, version: str, py: str, platform: str,
             pip_platforms: tuple[str, ...]) -> bool:
    """A wheel of ``dist==version`` for CPython ``py`` on Blender ``platform``, no newer macOS
    than ``pip_platforms`` allow."""
    name, ver, pytag, abi, plat = wheel_tags(filename)
    cp = "cp" + py.replace(".", "")
    if _norm(name) != _norm(dist) or ver != version or pytag != cp or abi not in (cp, "abi3"):
        return False
    if platform not in blender_platforms(plat):
        return False
    newest = max(_macos_version(t) for t in pip_platforms)
    return all(_macos_version(t) <= newest for t in plat.split("."))


def fetch(dist: str, version: str, py: str, platform: str, pip_platforms: tuple[str, ...], cache: Path) -> Path:
    """The cached wheel of ``dist==version`` for CPython ``py`` on Blender ``platform`` (pip
    tags ``pip_platforms``), downloaded when missing."""
    def found():
        return sorted(f for f in cache.glob("*.whl")
                      if _matches(f.name, dist, version, py, platform, pip_platforms))

    if not found():
        cache.mkdir(parents=True, exist_ok=True)
        cp = "cp" + py.replace(".", "")
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
               "--python-version", py, "--implementation", "cp", "--abi", cp, "--dest", str(cache)]
        for p in pip_platforms:
            cmd += ["--platform", p]
        r = subprocess.run(cmd + [f"{dist}=={version}"], capture_output=True, text=True)
        if r.returncode != 0 or not found():
            err = "\n".join(ln for ln in r.stderr.splitlines() if "is ignored" not in ln)
            raise SystemExit(f"build_extension: no wheel of {dist}=={version} for Python {py} on {platform} "
                             f"({'/'.join(pip_platforms)}):\n{err.strip()[-800:]}")
    return found()[-1]


def check_requires(wheel: Path, bundled: set[str]) -> None:
    """Fail when the wheel needs a distribution that is neither bundled nor in Blender."""
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        msg = email.parser.Parser().parsestr(z.read(meta).decode("utf-8"))
    for req in msg.get_all("Requires-Dist") or []:
        if "extra ==" in req:
            continue
        name = _norm(re.split(r"[ ;<>=!~\[(]", req.strip(), maxsplit=1)[0])
        if name not in bundled and name not in {_norm(n) for n in PROVIDED_BY_BLENDER}:
            raise SystemExit(f"build_extension: {wheel.name} requires {req!r}, which is not bundled; "
                             "add it to PINS")


def select_wheels(cache: Path) -> list[Path]:
    """Every wheel to bundle (cached, fetched when missing), sorted by file name."""
    wheels = set()
    for platform, tags in PLATFORMS.items():
        for dist, version in PINS.items():
            ver, ptags = OVERRIDES.get((dist, platform), (version, tags))
            for py in PYTHONS:
                wheels.add(fetch(dist, ver, py, platform, ptags, cache))
    bundled = {_norm(d) for d in PINS}
    for w in wheels:
        check_requires(w, bundled)
    return sorted(wheels, key=lambda p: p.name)


def check_manifest() -> list[str]:
    """Problems of the manifest's ``platforms``/``wheels`` against PINS, from file names only
    (no download): each platform and Python has exactly the pinned wheel of each distribution,
    nothing else is listed, no numpy, every listed file is under ./wheels/."""
    import tomllib

    data = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    problems = []
    if list(data.get("platforms", [])) != list(PLATFORMS):
        problems.append(f"platforms is {data.get('platforms')}, expected {list(PLATFORMS)}")
    listed = list(data.get("wheels", []))
    used = set()
    for platform, tags in PLATFORMS.items():
        for dist, version in PINS.items():
            ver, ptags = OVERRIDES.get((dist, platform), (version, tags))
            for py in PYTHONS:
                hits = [w for w in listed if _matches(w.rsplit("/", 1)[-1], dist, ver, py, platform, ptags)]
                if len(hits) != 1:
                    problems.append(f"{dist}=={ver} cp{py} {platform}: {len(hits)} wheels listed")
                used.update(hits)
    for w in listed:
        if not w.startswith("./wheels/"):
            problems.append(f"{w}: not under ./wheels/")
        if _norm(wheel_tags(w.rsplit("/", 1)[-1])[0]) in {_norm(n) for n in PROVIDED_BY_BLENDER}:
            problems.append(f"{w}: Blender ships this distribution; never bundle it")
        elif w not in used:
            problems.append(f"{w}: not in PINS")
    return problems


def manifest_block(wheels: list[Path]) -> str:
    lines = [_BEGIN + " (edit PINS there, not here)",
             "platforms = [" + ", ".join(f'"{p}"' for p in PLATFORMS) + "]",
             "wheels = ["]
    lines += [f'  "./wheels/{w.name}",' for w in wheels]
    lines += ["]", _END]
    return "\n".join(lines)


def write_manifest(block: str, check: bool) -> bool:
    """Put ``block`` between the markers of the manifest (before ``[permissions]`` the first
    time). Returns whether the manifest already held it; with ``check``, never writes."""
    text = MANIFEST.read_text(encoding="utf-8")
    m = re.search(re.escape(_BEGIN) + r".*?" + re.escape(_END), text, flags=re.S)
    if m:
        new = text[:m.start()] + block + text[m.end():]
    else:
        i = text.index("[permissions]")
        new = text[:i] + block + "\n\n" + text[i:]
    if new == text:
        return True
    if not check:
        MANIFEST.write_text(new, encoding="utf-8")
    return False


def link_wheels(wheels: list[Path]) -> None:
    """``./wheels/`` holds exactly ``wheels`` (hard links into the cache where possible)."""
    WHEEL_DIR.mkdir(exist_ok=True)
    keep = {w.name for w in wheels}
    for f in WHEEL_DIR.iterdir():
        if f.name not in keep:
            f.unlink()
    for w in wheels:
        dst = WHEEL_DIR / w.name
        if dst.exists() and dst.stat().st_size == w.stat().st_size:
            continue
        dst.unlink(missing_ok=True)
        try:
            os.link(w, dst)
        except OSError:
            shutil.copy2(w, dst)


def builder_command(blender: str | None) -> list[str]:
    """Blender's ``extension build`` command: a Blender binary's, or the bpy module's script."""
    if blender:
        return [blender, "--factory-startup", "--command", "extension", "build"]
    code = ("import bpy, os; print(os.path.join(bpy.utils.system_resource('SCRIPTS'), "
            "'addons_core', 'bl_pkg', 'cli', 'blender_ext.py'))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    script = r.stdout.strip().splitlines()[-1] if r.returncode == 0 and r.stdout.strip() else ""
    if not script or not Path(script).is_file():
        raise SystemExit("build_extension: no Blender builder: pass --blender PATH or run with a Python "
                         f"that has the bpy module\n{r.stderr[-600:]}")
    return [sys.executable, script, "build"]


def build(blender: str | None, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("recgs-*.zip"):
        old.unlink()
    cmd = builder_command(blender) + ["--split-platforms", "--source-dir", str(ROOT), "--output-dir", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"build_extension: the builder failed ({' '.join(cmd)}):\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    return sorted(out.glob("recgs-*.zip"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only check that the manifest lists what PINS gives")
    ap.add_argument("--no-build", action="store_true", help="fetch wheels and write the manifest, do not build")
    ap.add_argument("--blender", help="a Blender binary to build with (default: the bpy module of this Python)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"wheel cache (default {DEFAULT_CACHE})")
    ap.add_argument("--out", type=Path, default=ROOT / "dist", help="output folder of the zips")
    args = ap.parse_args(argv)

    if args.check:   # file names only: no download
        problems = check_manifest()
        for msg in problems:
            print("build_extension: " + msg)
        print("build_extension: manifest " + ("differs from PINS: run scripts/build_extension.py --no-build"
                                              if problems else "matches PINS"))
        return 1 if problems else 0
    wheels = select_wheels(args.cache)
    link_wheels(wheels)
    if not write_manifest(manifest_block(wheels), check=False):
        print(f"build_extension: wrote platforms and {len(wheels)} wheels into {MANIFEST.name}")
    if args.no_build:
        return 0
    for z in build(args.blender, args.out):
        n = sum(1 for name in zipfile.ZipFile(z).namelist() if name.endswith(".whl"))
        print(f"{z.relative_to(ROOT) if z.is_relative_to(ROOT) else z}  {z.stat().st_size / 2**20:6.1f} MiB  {n} wheels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
