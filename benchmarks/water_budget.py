"""Where a one-altitude water's true colour loses against its oracle: the water's own share.

    .venv/bin/python benchmarks/water_budget.py photos [--waters jerlov-5C,jerlov-I] [--base rows-72]
    .venv/bin/python benchmarks/water_budget.py fit --waters jerlov-5C [--rho 1.0] [--colours relit,clean,constant]
    .venv/bin/python benchmarks/water_budget.py seabed [--base rows-72]

* **photos**: every fourth photo of a battery item (``OUT/surveys/BASE+WATER``, made by
  ``bench_water.py --only battery``) taken out of the water with the true range of each pixel
  (the survey's saved depth) and, in turn, the generator's coefficients, the run's fitted ones
  (``OUT/water/battery/BASE+WATER/3dgs/metrics.json``), the fitted attenuation with the true
  veil, and the true attenuation with the fitted veil; PSNR of each against ``clean/``. The
  first row is what 8-bit photos allow; the second is the error a perfect model of the seabed
  would still carry with the run's water, which adds to the oracle's own error (an oracle at
  31.3 dB and a water at 33.3 dB make about 29.2 dB together).
* **fit**: the water fitted to the sparse points as a run fits it (``core/train/water.py``'s
  observations and ``fit_from_points``) from three kinds of point colour: the relit photos
  (``relit``: what a run sees); the base's clean photos with the generator's water applied to
  each observation at its range (``clean``: the seabed's own change from view to view, the
  water exact); each point's mean clean colour in every view, under that water (``constant``:
  what the model assumes). ``--rho`` replaces the generator's backscatter rate by that multiple
  of its attenuation (the fit ties the two where one altitude leaves the rate free).
* **seabed**: the base's clean photos (no water): each sparse point's linear colour regressed on
  its range over the views that see it, and those slopes regressed on the point's level (least
  squares, points seen from ranges x1.1 apart or more): how the seabed's own colour changes with
  range, in the form the water's takes (slope = -a x level + a V + V').
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))


def _coefficients(water: dict) -> dict:
    return {"a": np.asarray(water["attenuation_per_m"], np.float64), "b": np.asarray(water["backscatter_per_m"], np.float64),
            "B": np.asarray(water["veiling_light"], np.float64)}


def photos(survey: Path, run: Path, every: int = 4) -> dict:
    """See the module: PSNR (dB) against ``clean/`` of the photos taken out of the water by each set of
    coefficients."""
    import pycolmap
    from make_survey import linear_to_srgb8
    from relight_survey import _read, srgb8_to_linear
    from survey_water import ray_lengths
    truth = _coefficients(json.loads((survey / "survey.json").read_text())["water"])
    co = json.loads((run / "metrics.json").read_text())["medium"]["coefficients"]
    fit = {"a": np.asarray(co["attenuation"]), "b": np.asarray(co["backscatter"]), "B": np.asarray(co["veil"])}
    variants = {"true water": truth, "fitted water": fit, "fitted attenuation, true veil": dict(fit, b=truth["b"], B=truth["B"]),
                "true attenuation, fitted veil": dict(fit, a=truth["a"])}
    rec = pycolmap.Reconstruction(str(survey / "sparse" / "0"))
    images = sorted(rec.images.values(), key=lambda im: im.name)[::every]
    out = {}
    for name, c in variants.items():
        err = []
        for im in images:
            cam = rec.cameras[im.camera_id]
            fx, fy, cx, cy = cam.params[:4]
            depth = np.load(survey / "depth" / (Path(im.name).stem + ".npy"))
            rng = (depth * ray_lengths(cam.width, cam.height, fx, fy, cx, cy))[..., None]
            seen = srgb8_to_linear(_read(survey / "images" / im.name))
            with np.errstate(invalid="ignore", over="ignore"):
                j = (seen - c["B"] * -np.expm1(-c["b"] * rng)) / np.exp(-c["a"] * rng)
            j = np.where(np.isfinite(j), np.clip(j, 0.0, 1.0), 0.0)
            err.append(((linear_to_srgb8(j).astype(np.float64) - _read(survey / "clean" / im.name)) ** 2).mean())
        out[name] = 10 * math.log10(255.0 ** 2 / float(np.mean(err)))
    return out


def fit(survey: Path, base: Path, colours: str, rho: float | None) -> dict:
    """See the module: the points' fit from one kind of colour; coefficients against the generator's."""
    import torch
    from recgs_addon.core.model.colour import linear_to_srgb, srgb_to_linear
    from recgs_addon.core.train import water
    from recgs_addon.core.train.config import TrainConfig
    from recgs_addon.core.train.trainer import load_data
    truth = _coefficients(json.loads((survey / "survey.json").read_text())["water"])
    if rho is not None:
        truth["b"] = rho * truth["a"]
    data = load_data(survey if colours == "relit" else base, TrainConfig(), None if colours == "relit" else "clean")
    obs = water._observations(data)
    water._sample_colours(data, obs)
    length = water.range_profile(obs)["median_range"]
    if colours != "relit":
        lin = srgb_to_linear(torch.from_numpy(obs["colour"])).double().numpy()
        pt, n = obs["point"], len(obs["points"])
        if colours == "constant":
            count = np.maximum(np.bincount(pt, minlength=n), 1)
            lin = np.stack([np.bincount(pt, lin[:, c], n) / count for c in range(3)], 1)[pt]
        r = obs["range"][:, None]
        lin = lin * np.exp(-truth["a"] * r) + truth["B"] * -np.expm1(-truth["b"] * r)
        obs = dict(obs, colour=linear_to_srgb(torch.from_numpy(lin).clamp(0.0, 1.0)).float().numpy())
    got = water.fit_from_points(obs, length)
    f = got["fit"]
    veil_true = truth["B"] * -np.expm1(-truth["b"] * length)
    return {"colours": colours, "attenuation": np.round(f["attenuation"], 4).tolist(),
            "attenuation_error": np.round(np.asarray(f["attenuation"]) / truth["a"] - 1, 3).tolist(),
            "veil_at_median_range": np.round(f["veil_at_length"], 4).tolist(),
            "veil_error": np.round(np.asarray(f["veil_at_length"]) / veil_true - 1, 3).tolist(),
            "attenuation_spread": np.round((got.get("spread") or {}).get("attenuation", [np.nan] * 3), 4).tolist(),
            "rate_tied": got.get("rate_tied"), "median_range": round(length, 3)}


def seabed(base: Path) -> list[dict]:
    """See the module: per channel the slope's coefficient on the level and its value at level zero."""
    import torch
    from recgs_addon.core.model.colour import srgb_to_linear
    from recgs_addon.core.train import water
    from recgs_addon.core.train.config import TrainConfig
    from recgs_addon.core.train.trainer import load_data
    data = load_data(base, TrainConfig(), "clean")
    obs = water._observations(data)
    water._sample_colours(data, obs)
    lin = srgb_to_linear(torch.from_numpy(obs["colour"])).double().numpy()
    pt, r, n = obs["point"], obs["range"], len(obs["points"])
    count = np.bincount(pt, minlength=n)
    dr = r - (np.bincount(pt, r, n) / np.maximum(count, 1))[pt]
    den = np.bincount(pt, dr ** 2, n)
    near, far = np.full(n, np.inf), np.zeros(n)
    np.minimum.at(near, pt, r)
    np.maximum.at(far, pt, r)
    ok = (count >= 3) & (den > 0) & (far > 1.1 * near)
    rows = []
    for c in range(3):
        level = np.bincount(pt, lin[:, c], n) / np.maximum(count, 1)
        slope = np.bincount(pt, dr * (lin[:, c] - level[pt]), n) / np.where(den > 0, den, 1.0)
        w = np.sqrt(den[ok])
        coef = np.linalg.lstsq(np.stack([level[ok], np.ones(ok.sum())], 1) * w[:, None], slope[ok] * w, rcond=None)[0]
        rows.append({"channel": "RGB"[c], "per_level": round(float(coef[0]), 4), "at_level_zero": round(float(coef[1]), 4),
                     "points": int(ok.sum())})
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("photos", "fit", "seabed"))
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--base", default="rows-72")
    p.add_argument("--waters", default="coastal,clear,green,jerlov-I,jerlov-III,jerlov-1C,jerlov-3C,jerlov-5C,jerlov-7C")
    p.add_argument("--colours", default="relit,clean,constant", help="fit: which point colours (comma-separated)")
    p.add_argument("--rho", type=float, default=None, help="fit: the true backscatter rate over the attenuation")
    a = p.parse_args()
    base = a.out / "surveys" / a.base
    if a.what == "seabed":
        for row in seabed(base):
            print(json.dumps(row))
        return 0
    for w in a.waters.split(","):
        survey = a.out / "surveys" / f"{a.base}+{w}"
        if not (survey / "sparse" / "0").is_dir():
            sys.exit(f"water_budget: {survey} is missing (make it with benchmarks/bench_water.py --only battery)")
        if a.what == "photos":
            got = photos(survey, a.out / "water" / "battery" / survey.name / "3dgs")
            print(json.dumps({"water": w, **{k: round(v, 2) for k, v in got.items()}}), flush=True)
        else:
            for kind in a.colours.split(","):
                print(json.dumps({"water": w, "rho": a.rho, **fit(survey, base, kind, a.rho)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
