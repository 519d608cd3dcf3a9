"""Make the user guide's pictures from the product itself, headless.

    .venv/bin/python tools/make_doc_images.py [--job out/dive] [--survey data/dive] [--panels-only]

``--job`` is the output folder of the README's main job (``recgs_addon/batch.py data/dive --out
out/dive --mode recgs ...``); run that first. Writes to ``docs/images/``:

* ``guide_decaustic.png``: one training frame as photographed, with its caustics removed by the
  job, and (when the survey has ``clean/``) the ground truth, side by side;
* ``guide_caustic_map.png``: that frame's caustic map (grey = none, brighter = light taken out);
* ``guide_preview.png``: the trained Gaussian object of the job's ``scene.blend``, rendered by
  EEVEE with the add-on's preview from a held-out frame's camera, beside that frame's photo;
* ``guide_coverage.png`` and ``guide_view_support.png``: the job report's charts of views per
  seabed point and views per Gaussian.

and rewrites the panel figures of ``docs/user_guide.md`` (the blocks between
``<!-- panel STATE -->`` and ``<!-- /panel -->``) from ``tools/panel_snapshot.py``, with the
repository's path replaced by ``/path/to``. ``--panels-only`` does only that (a few seconds).
``tests/test_docs.py`` fails when the guide's panel figures and the sidebar disagree.
"""
from __future__ import annotations

import argparse
import re
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

GUIDE = ROOT / "docs" / "user_guide.md"
IMAGES = ROOT / "docs" / "images"
PANEL_BLOCK = re.compile(r"(<!-- panel (\w+) -->\n```\n)(.*?)(```\n<!-- /panel -->)", re.S)
GAP = 4  # pixels between pictures set side by side


def side_by_side(images: list[np.ndarray], gap: int = GAP) -> np.ndarray:
    """RGB float images of one height in a row, ``gap`` white pixels apart."""
    h = images[0].shape[0]
    if any(im.shape[0] != h for im in images):
        raise ValueError(f"images of different heights: {[im.shape for im in images]}")
    parts = []
    for i, im in enumerate(images):
        if i:
            parts.append(np.ones((h, gap, 3), np.float32))
        parts.append(np.asarray(im, np.float32)[..., :3])
    return np.concatenate(parts, axis=1)


def panel_snapshots(scene: Path) -> dict[str, str]:
    """The sidebar as text after importing ``scene``, idle and while a job runs, with the
    repository's path written as ``/path/to``."""
    from tools.panel_snapshot import snapshots

    out = snapshots(scene, ["idle", "running"])
    return {k: v.replace(str(ROOT), "/path/to") + "\n" for k, v in out.items()}


def guide_panels(text: str) -> dict[str, str]:
    """The panel figures the guide holds, by state."""
    return {m.group(2): m.group(3) for m in PANEL_BLOCK.finditer(text)}


def update_guide(text: str, panels: dict[str, str]) -> str:
    def repl(m):
        state = m.group(2)
        if state not in panels:
            raise KeyError(f"docs/user_guide.md: no snapshot for panel state {state!r}")
        return m.group(1) + panels[state] + m.group(4)
    return PANEL_BLOCK.sub(repl, text)


def frame_pictures(job: Path, survey: Path) -> str:
    """Photo | caustic-free | ground truth, and the caustic map, of the middle training frame."""
    from recgs_addon.core.io.images import read_image, write_image

    names = sorted(p.name for p in (job / "decaustic").glob("*.png"))
    if not names:
        raise SystemExit(f"{job / 'decaustic'}: no caustic-free images (run the README's main job first)")
    name = names[len(names) // 2]
    photo = read_image(survey / "images" / name)
    row = [photo, read_image(job / "decaustic" / name)]
    clean = survey / "clean" / name
    if clean.is_file():
        row.append(read_image(clean))
    write_image(IMAGES / "guide_decaustic.png", np.clip(side_by_side(row), 0, 1))
    cmap = job / "train" / "caustic" / (Path(name).stem + ".exr")
    if cmap.is_file():
        c = read_image(cmap)[..., :3]
        write_image(IMAGES / "guide_caustic_map.png", np.clip(0.5 + 2.0 * c, 0, 1))
    return name


def preview_picture(job: Path, survey: Path, samples: int = 8) -> str:
    """EEVEE's render of the job's Gaussian object from a held-out camera, beside the photo."""
    import bpy

    from recgs_addon import blender as addon
    from recgs_addon.blender import preview
    from recgs_addon.core.io.images import read_image, write_image

    held = sorted((job / "train" / "renders").glob("*.png"))
    if not held:
        raise SystemExit(f"{job / 'train' / 'renders'}: no held-out renders (run the README's main job first)")
    name = held[len(held) // 2].name
    bpy.ops.wm.open_mainfile(filepath=str(job / "scene.blend"))
    addon.register()
    try:
        scene = bpy.context.scene
        obj = next(o for o in scene.objects if o.type == "MESH" and "f_dc_0" in o.data.attributes)
        scene.camera = bpy.data.objects[name]
        preview.ensure_preview(obj, mode="ELLIPSOIDS")
        preview.match_trainer_colour(scene)
        preview.use_eevee(scene, samples)
        scene.render.image_settings.file_format = "PNG"
        tmp = IMAGES / ".preview_render.png"
        scene.render.filepath = str(tmp)
        bpy.ops.render.render(write_still=True)
        render = read_image(tmp)[..., :3]
        tmp.unlink()
    finally:
        addon.unregister()
    photo = read_image(survey / "images" / name)
    write_image(IMAGES / "guide_preview.png", np.clip(side_by_side([render, photo]), 0, 1))
    return name


def report_charts(job: Path) -> list[str]:
    copied = []
    for pattern, target in (("coverage.png", "guide_coverage.png"), ("view_support.png", "guide_view_support.png")):
        found = sorted((job / "report").glob(pattern))
        if found:
            shutil.copyfile(found[0], IMAGES / target)
            copied.append(f"{found[0].name} -> {target}")
    return copied


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--job", type=Path, default=ROOT / "out" / "dive")
    ap.add_argument("--survey", type=Path, default=ROOT / "data" / "dive")
    ap.add_argument("--panel-scene", type=Path, default=ROOT / "data" / "dive",
                    help="survey imported before the panel is drawn")
    ap.add_argument("--panels-only", action="store_true")
    ap.add_argument("--samples", type=int, default=8, help="EEVEE render samples of the preview picture")
    args = ap.parse_args(argv)
    GUIDE.write_text(update_guide(GUIDE.read_text(), panel_snapshots(args.panel_scene)))
    print(f"updated the panel figures in {GUIDE.relative_to(ROOT)}")
    if args.panels_only:
        return 0
    IMAGES.mkdir(parents=True, exist_ok=True)
    print("frame:", frame_pictures(args.job, args.survey))
    print("charts:", ", ".join(report_charts(args.job)) or "none found")
    print("preview from the camera of", preview_picture(args.job, args.survey, args.samples))
    return 0


if __name__ == "__main__":
    sys.exit(main())
