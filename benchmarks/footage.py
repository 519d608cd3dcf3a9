"""The battery of real footage: public clips and photos filmed by others, kept outside the
project in ``../shared/footage/`` beside the repository (``RECGS_FOOTAGE`` moves it; CI has it
too; nothing of it is committed here). Each item is imported as a new user would: a clip
through Import Video (``python -m recgs_addon video``), a folder of photos through structure
from motion (``python -m recgs_addon sfm``), at the defaults, once, into ``OUT/real/NAME``.

None of the items shows sunlight caustics; each folder's SOURCE file says what it shows and its
licence.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]

#: name: (path under the footage folder, "video" or "photos", what it shows)
BATTERY = {
    "wreck-lamp": ("mosaic_library/aqualoc_snippet.mp4", "video",
                   "an ROV over an amphora wreck, deep water, lit only by its lamp, greyscale, 968x608"),
    "auv-seabed": ("mosaic_library/sparus_snippet.mp4", "video",
                   "a flat seabed seen from above by an AUV, strong green water, 384x288"),
    "pool-tiles": ("subvo_pool_b/images", "photos",
                   "a tiled pool floor seen forward and down from a crawler, indoor light, a time stamp burned in, "
                   "36 photos 1280x720"),
    "reef-transect": ("deepreefmap_demo_input/demo_input.mp4", "video",
                      "a coral reef transect filmed by a diver's GoPro, oblique to down-looking, diffuse daylight, "
                      "1280x720"),
}


def footage_dir() -> Path:
    """Where the battery lies: ``RECGS_FOOTAGE``, else ``../shared/footage`` beside the repository."""
    return Path(os.environ.get("RECGS_FOOTAGE") or ROOT.parent / "shared" / "footage")


def missing(name: str) -> Optional[str]:
    """Why item ``name`` cannot be used here (None: it can)."""
    src = footage_dir() / BATTERY[name][0]
    return None if src.exists() else f"{src}: not here (the battery of real footage lies in ../shared/footage)"


def real_survey(out: Path, name: str) -> Path:
    """Item ``name`` imported at the defaults into ``OUT/real/NAME`` (once; a survey made
    before is used as it is)."""
    rel, kind, _ = BATTERY[name]
    d = Path(out) / "real" / name
    if not (d / "sparse" / "0").is_dir():
        why = missing(name)
        if why:
            raise FileNotFoundError(why)
        cmd = "video" if kind == "video" else "sfm"
        extra = ["--overwrite"] if kind == "video" else ["--link"]
        subprocess.run([sys.executable, "-m", "recgs_addon", cmd, str(footage_dir() / rel), "--out", str(d), *extra],
                       cwd=ROOT, check=True, capture_output=True)
    return d
