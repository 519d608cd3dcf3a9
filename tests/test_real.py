"""Real footage end to end (the battery in ../shared/footage beside the repository,
benchmarks/footage.py: clips and photos filmed by others, no caustics): imported at the
defaults (Import Video, or structure from motion for a folder of photos), then caustic removal
as a new user asks for it. The job must find no caustics and train plain (the caustic-free
images are the photos: no other frame's pieces, no seams), say so in its report, and model the
light fixed to the camera where the footage shows one (the lamp-lit wreck) without taking its
fall-off for the water. An item not here is skipped, and says where it was looked for."""
import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from benchmarks.footage import BATTERY, footage_dir, missing

pytest.importorskip("av")
pytest.importorskip("pycolmap")


def _footage(name):
    why = missing(name)
    if why:
        pytest.skip(why)
    return footage_dir() / BATTERY[name][0]


def _run(*args, timeout=900):
    r = subprocess.run([sys.executable, "-m", "recgs_addon", *map(str, args)], cwd=ROOT, capture_output=True,
                       text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def _clip_to_recgs(tmp_path, name, iterations, *train_args):
    survey, out = tmp_path / name, tmp_path / f"{name}-out"
    if BATTERY[name][1] == "video":
        r = _run("video", _footage(name), "--out", survey)
        assert "a short clip" in r.stderr and "registered" in r.stderr
        frames = json.loads((survey / "frames.json").read_text())["frames"]
        assert len(frames) >= 18
    else:
        r = _run("sfm", _footage(name), "--out", survey, "--link")
        assert "registered" in r.stderr
    r = _run("train", survey, "--out", out, "--mode", "recgs", "--iterations", iterations, *train_args)
    return survey, out, json.loads((out / "metrics.json").read_text()), r.stderr


def _no_caustics(survey, out, m, log):
    import torch

    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.train.data import as_float

    assert m["light"]["caustics"] is False and "no caustics found" in m["caustics_dropped"], m["caustics_dropped"]
    assert "light: no caustics found" in log and "training as plain 3DGS" in log
    assert "No caustics were found, so the run trained plain 3DGS" in (out / "report.md").read_text()
    assert m["recurrences"] == [] and m.get("candidates") is None
    # the photos are caustic-free as they are: no copies of them, no zero caustic maps, and none
    # of their writing kept in the reserve (the job's outputs cost what plain's do)
    assert not (out / "decaustic").exists() and not (out / "caustic").exists()
    assert "no caustic-free copies of them" in (out / "report.md").read_text()
    written = [p for d in ("renders", "truecolour") if (out / d).is_dir() for p in (out / d).iterdir()]
    assert m["reserve_writes"] == len(written) > 0, m["reserve_writes"]


def test_a_seabed_filmed_by_an_auv_trains_plain_and_says_why(tmp_path):
    """22 frames of a rocky seabed in murky water, 384x288: every frame registered, no caustics."""
    survey, out, m, log = _clip_to_recgs(tmp_path, "auv-seabed", 150)
    _no_caustics(survey, out, m, log)
    assert m["psnr_test"] > 20


@pytest.mark.slow
def test_a_lamp_lit_wreck_is_not_caustics_and_its_lamp_is_modelled(tmp_path):
    """An ROV over a wreck lit by its own lamp: no caustics, the lamp modelled, the water left
    alone (the lamp's fall-off is not attenuation)."""
    survey, out, m, log = _clip_to_recgs(tmp_path, "wreck-lamp", 120)
    _no_caustics(survey, out, m, log)
    assert m["lamp"]["kept"] and "lamp: modelled" in log, m["lamp"]
    assert m["light"]["explained"] > 0.8 and m["light"]["camera"] > 0.3
    assert not m["medium"]["kept"], m["medium"]
    assert (out / "lamp.json").is_file() and any((out / "truecolour").glob("*.png"))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pool-tiles", "reef-transect"])
def test_tiles_and_a_reef_are_not_caustics(tmp_path, name):
    """A tiled pool floor seen forward from a crawler (repetitive texture, grazing views, a time
    stamp burned in) and a diver's reef transect (relief, parallax): what differs between their
    frames is misregistration that grows with the baseline, not light; the job trains plain at a
    lower resolution (a quick check)."""
    survey, out, m, log = _clip_to_recgs(tmp_path, name, 60, "--max-side", "480")
    _no_caustics(survey, out, m, log)
    assert m["light"]["moving"] < m["light"]["floor"], m["light"]
