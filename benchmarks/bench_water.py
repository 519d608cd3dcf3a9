"""Water benchmark: true colour under attenuation and backscatter, side by side.

    .venv/bin/python benchmarks/bench_water.py --out out/bench [--minutes 5] [--only runs|decisions|step|identify|passes]

* **runs**: on ``dive-water`` (green coastal water, ranges about 1.5-5 m, no caustics) plain 3DGS,
  3DGS with the water model, and the oracle (plain 3DGS on the true-colour images); on
  ``dive-water-networks`` (the same water with sharp caustic networks) also RecGS without and
  with the water; on ``dive-water-clear`` (clear ocean water, another seabed) the first three; on
  the surveys flown level at one altitude (``level-*``) the same, with RecGS and the water under
  light: caustic networks in the coastal water (``level-reef-networks``) and a softer wave
  pattern in the clear water (``level-reef-clear-waves``). Each run gets the same wall-clock
  limit, two at a time on one thread each.
  Scores: held-out PSNR of the true-colour render against the true colour (``clean/``), of the
  true-colour photos (``truecolour/``) where the run made them, Gaussians, steps, and the fitted
  coefficients against the generator's.
* **decisions**: what ``auto`` decides before training on every survey at hand, and why; what
  the survey pins of the water, and the sparse points' fit against the generator's water.
* **step**: seconds a training step takes with and without the water (the same model, blocks
  of steps alternated in one process).
* **identify**: how well the photos of ``dive-water`` determine each coefficient. (1) Given the
  true colour and the true range of every pixel (what no method has), least squares per channel
  in linear light on 3,000 pixels a view; (2) from the sparse points as training starts (each
  point's true colour unknown), the points' fit and its spread over refits against the
  generator's; (3) the darkest pixels per range (Sea-thru's backscatter estimate) against the
  generator's veil at that range.

* **passes**: RecGS with the water on ``dive-water-networks``, with and without the pass
  estimator's water correction (each frame compared at its own range; without it, the frames'
  colours as seen), side by side: what the correction adds on its own.

* **pixels**: on a survey flown at one altitude (``--surveys``, default ``level-reef-water``), what
  the survey pins kept from the sparse points through training (the default) against the veil
  trained from every pixel (``veil-trained``) or everything (``all-trained``, ``--pixel-runs``),
  from the same start, side by side.

* **battery**: waters at one altitude. Each base (``--bases``: lawnmower rows flown at 2.5 m,
  ``rows-72`` over sand and a few rocks, ``rows-reef`` over a reef) is relit under each water
  (``--waters``: tools/survey_water.py's types, Jerlov's among them) by tools/relight_survey.py,
  from its clean photos and (``--caustics``) from its photos under moving light; each item trains
  at the defaults (``--mode 3dgs``, under light ``--mode recgs``), and each base's oracle once
  (3DGS on ``clean/``, the true colour). Per item: held-out true colour against ``clean/`` and
  its gap to the oracle, what the water decision said, and the fitted attenuation, backscatter
  rate, veil and veil at the median range against the generator's, per channel.

Surveys come from benchmarks/bench_caustics.py (generated once into OUT/surveys).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_caustics import run_method, survey_dir  # noqa: E402

#: (survey, run name, method, extra options)
RUNS = [
    ("dive-water", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water", "oracle", "oracle", ["--medium", "off"]),
    ("dive-water-networks", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water-networks", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water-networks", "recgs", "recgs", ["--medium", "off"]),
    ("dive-water-networks", "recgs+water", "recgs", ["--medium", "auto"]),
    ("dive-water-networks", "oracle", "oracle", ["--medium", "off"]),
    ("dive-water-clear", "plain", "3dgs", ["--medium", "off"]),
    ("dive-water-clear", "water", "3dgs", ["--medium", "auto"]),
    ("dive-water-clear", "oracle", "oracle", ["--medium", "off"]),
    # flown level at one altitude (bench_caustics.py's LEVEL surveys)
    ("level-reef-water", "water", "3dgs", ["--medium", "auto"]),
    ("level-reef-water", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-water", "plain", "3dgs", ["--medium", "off"]),
    ("level-reef-clear", "water", "3dgs", ["--medium", "auto"]),
    ("level-reef-clear", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-clear", "plain", "3dgs", ["--medium", "off"]),
    ("level-reef-networks", "recgs+water", "recgs", ["--medium", "auto"]),
    ("level-reef-networks", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-networks", "water", "3dgs", ["--medium", "auto"]),
    ("level-reef-networks", "plain", "3dgs", ["--medium", "off"]),
    ("level-reef-clear-waves", "recgs+water", "recgs", ["--medium", "auto"]),
    ("level-reef-clear-waves", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-clear-waves", "plain", "3dgs", ["--medium", "off"]),
    # the reef lower and looking further ahead behind a bright, slowly building veil
    ("level-reef-green", "water", "3dgs", ["--medium", "auto"]),
    ("level-reef-green", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-green", "plain", "3dgs", ["--medium", "off"]),
    ("level-reef-green-networks", "recgs+water", "recgs", ["--medium", "auto"]),
    ("level-reef-green-networks", "water", "3dgs", ["--medium", "auto"]),
    ("level-reef-green-networks", "oracle", "oracle", ["--medium", "off"]),
    ("level-reef-green-networks", "plain", "3dgs", ["--medium", "off"]),
    ("level-water", "water", "3dgs", ["--medium", "auto"]),
    ("level-water", "oracle", "oracle", ["--medium", "off"]),
]
DECISION_SURVEYS = ["dive-water", "dive-water-networks", "dive-water-clear", "level-water", "level-reef-water",
                    "level-reef-green", "level-reef-green-networks",
                    "level-reef-clear", "level-reef-networks", "level-reef-clear-waves", "dive-none", "dive-networks", "sample-none", "networks",
                    "dive-lamp"]


def _rel_errors(fitted: dict, truth: dict) -> dict:
    pairs = {"attenuation": "attenuation_per_m", "backscatter": "backscatter_per_m", "veil": "veiling_light"}
    return {k: [round(abs(f - t) / t, 3) for f, t in zip(fitted[k], truth[v])] for k, v in pairs.items()}


def runs(out: Path, minutes: float, surveys: list[str] | None = None) -> None:
    jobs = []
    for survey, name, method, extra in RUNS:
        if surveys and survey not in surveys:
            continue
        scene = survey_dir(out, survey)
        jobs.append((survey, name, scene, out / "water" / survey / name, method, extra))
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda j: run_method(j[2], j[3], j[4], minutes, j[5], threads=1), jobs))
    rows = []
    for (survey, name, scene, _, _, _), m in zip(jobs, results):
        meta = json.loads((scene / "survey.json").read_text())
        med = m.get("medium") or {}
        row = {"survey": survey, "run": name, "psnr_true": m.get("psnr_test_gt"),
               "psnr_truecolour_photos": m.get("psnr_truecolour_gt"), "psnr_captured": m.get("psnr_test_captured"),
               "gaussians": m.get("gaussians"), "steps": m.get("iterations"), "seconds": m.get("seconds"),
               "water": med.get("reason")}
        if med.get("coefficients") and meta.get("water"):
            row["coefficient_errors"] = _rel_errors(med["coefficients"], meta["water"])
            row["coefficients"] = {k: [round(v, 4) for v in med["coefficients"][k]]
                                   for k in ("attenuation", "backscatter", "veil")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    (out / "water" / ("runs.json" if not surveys else f"runs-{'+'.join(surveys)}.json")).write_text(
        json.dumps(rows, indent=1))
    print("\n| survey | run | true colour, held-out (dB) | true-colour photos (dB) | Gaussians | steps |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"| {r['survey']} | {r['run']} | {f(r['psnr_true'])} | {f(r['psnr_truecolour_photos'])} | "
              f"{r['gaussians']:,} | {r['steps']:,} |")


#: The battery's waters (tools/survey_water.py) and bases (benchmarks/bench_caustics.py).
BATTERY_WATERS = "coastal,clear,green,jerlov-I,jerlov-III,jerlov-1C,jerlov-3C,jerlov-5C,jerlov-7C"
BATTERY_BASES = "rows-72"


def relit(out: Path, base: str, water: str, light: bool) -> Path:
    """Base survey ``base`` under ``water`` (from its photos under moving light with ``light``),
    made once by tools/relight_survey.py into ``OUT/surveys/BASE+WATER[+light]``."""
    import subprocess
    d = out / "surveys" / f"{base}+{water}{'+light' if light else ''}"
    if not (d / "sparse" / "0").is_dir():
        src = survey_dir(out, base)
        subprocess.run([sys.executable, str(ROOT / "tools" / "relight_survey.py"), str(src), str(d), "--water", water,
                        "--from", "images" if light else "clean"], check=True, stdout=subprocess.DEVNULL)
    return d


def battery(out: Path, minutes: float, bases: list[str], waters: list[str], lights: list[bool]) -> list[dict]:
    """See the module: ``--only battery``."""
    import numpy as np

    jobs = []
    for base in bases:
        jobs.append((base, None, False, survey_dir(out, base), "oracle", out / "water" / "battery" / base / "oracle"))
        for water in waters:
            for light in lights:
                scene = relit(out, base, water, light)
                jobs.append((base, water, light, scene, "recgs" if light else "3dgs",
                             out / "water" / "battery" / scene.name / ("recgs" if light else "3dgs")))
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda j: run_method(j[3], j[5], j[4], minutes, ["--medium", "auto"], threads=1),
                                jobs))
    oracle = {j[0]: m.get("psnr_test_gt") for j, m in zip(jobs, results) if j[1] is None}
    rows = []
    for (base, water, light, scene, method, _), m in zip(jobs, results):
        if water is None:
            continue
        truth = json.loads((scene / "survey.json").read_text())["water"]
        med = m.get("medium") or {}
        row = {"base": base, "water": water, "light": light, "method": method, "psnr_true": m.get("psnr_test_gt"),
               "oracle": oracle[base], "steps": m.get("iterations"), "gaussians": m.get("gaussians"),
               "job_over_limit": round(m["job_seconds"] / (60 * minutes), 3), "modelled": bool(med.get("kept")),
               "reason": med.get("reason"), "rate_tied": med.get("rate_tied"),
               "caustics": bool((m.get("light") or {}).get("caustics"))}
        if med.get("coefficients"):
            co = med["coefficients"]
            row["coefficients"] = {k: [round(v, 4) for v in co[k]] for k in ("attenuation", "backscatter", "veil")}
            row["errors"] = {k: [round(f / t - 1, 3) for f, t in zip(co[k], truth[v])] for k, v in
                             (("attenuation", "attenuation_per_m"), ("backscatter", "backscatter_per_m"),
                              ("veil", "veiling_light"))}
            r0 = float(co["length"])   # the veil at the survey's median range, which one altitude pins best
            at = lambda v, b: np.asarray(v) * -np.expm1(-np.asarray(b) * r0)   # noqa: E731
            row["errors"]["veil_at_median_range"] = np.round(
                at(co["veil"], co["backscatter"]) / at(truth["veiling_light"], truth["backscatter_per_m"]) - 1, 3).tolist()
        rows.append(row)
        print(json.dumps(row), flush=True)
    (out / "water" / "battery.json").write_text(json.dumps(rows, indent=1))
    pct = lambda v: "-" if v is None else " / ".join(f"{100 * x:+.0f}" for x in v)   # noqa: E731
    f = lambda v: "-" if v is None else f"{v:.2f}"   # noqa: E731
    print("\n| base | water | light | true colour (dB) | oracle | gap | steps | attenuation (%) | veil at the median "
          "range (%) | veil (%) | backscatter (%) | rate tied |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        e = r.get("errors") or {}
        gap = None if r["psnr_true"] is None or r["oracle"] is None else r["oracle"] - r["psnr_true"]
        print(f"| {r['base']} | {r['water']} | {'yes' if r['light'] else 'no'} | {f(r['psnr_true'])} | {f(r['oracle'])} | "
              f"{f(gap)} | {r['steps']:,} | {pct(e.get('attenuation'))} | {pct(e.get('veil_at_median_range'))} | "
              f"{pct(e.get('veil'))} | {pct(e.get('backscatter'))} | "
              f"{'' if not r['rate_tied'] else ', '.join('rgb'[c] for c, t in enumerate(r['rate_tied']) if t)} |")
    return rows


def decisions(out: Path, surveys: list[str] | None = None) -> None:
    from recgs_addon.core.caustics.build import make_method
    from recgs_addon.core.caustics.config import CausticConfig
    from recgs_addon.core.train.config import preset

    for name in surveys or DECISION_SURVEYS:
        scene = survey_dir(out, name)
        t = time.perf_counter()
        tr = make_method(scene, preset("default", medium="auto"), CausticConfig(mode="3dgs")).trainer  # as a job does
        info = tr.medium_info
        row = {"survey": name, "modelled": tr.medium is not None, "seconds": round(time.perf_counter() - t, 1),
               "range_spread": round(info.get("range_spread", 0), 3), "prefit": info.get("prefit"),
               "reason": info["reason"], "lamp": tr.lamp is not None, "cues": info.get("cues"),
               "pinning": {k: v for k, v in (info.get("pinning") or {}).items() if k != "z"},
               "under_light": info.get("prefit_under_light")}
        meta = json.loads((scene / "survey.json").read_text()) if (scene / "survey.json").is_file() else {}
        if info.get("prefit_fit") and meta.get("water"):
            truth = meta["water"]
            row["points_fit"] = {k: [round(v, 4) for v in info["prefit_fit"][k]] for k in ("attenuation", "backscatter", "veil")}
            row["points_fit_errors"] = _rel_errors(info["prefit_fit"], truth)
        print(json.dumps(row), flush=True)


def step_cost(out: Path, steps: int = 60, blocks: int = 4, grown=(600, 2500)) -> None:
    """Seconds a step with the water against without, on one model (dive-water, after each of
    ``grown`` plain steps, so the model has grown), blocks alternated."""
    import torch

    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer

    scene = survey_dir(out, "dive-water")
    tr = make_trainer(scene, preset("default", medium="on", eval_every=10**9))
    water = (tr.medium, tr.medium_optimizer)
    for until in grown:
        tr.medium, tr.medium_optimizer = None, None
        while tr.step < until:
            tr.train_step()
        times = {"water": [], "plain": []}
        for b in range(blocks):
            for name in ("plain", "water") if b % 2 == 0 else ("water", "plain"):
                tr.medium, tr.medium_optimizer = water if name == "water" else (None, None)
                t = time.perf_counter()
                for _ in range(steps):
                    tr.train_step()
                times[name].append((time.perf_counter() - t) / steps)
        w, p = sum(times["water"]) / blocks, sum(times["plain"]) / blocks
        print(json.dumps({"after_steps": until, "gaussians": int(tr.params["means"].shape[0]),
                          "threads": torch.get_num_threads(), "path": tr.compiler.compiled(),
                          "seconds_per_step_plain": round(p, 4), "seconds_per_step_water": round(w, 4),
                          "ratio": round(w / p, 3)}), flush=True)


def identify(out: Path, survey: str = "dive-water", per_view: int = 3000, steps: int = 6000) -> None:
    """See the module: ``--only identify``."""
    import numpy as np
    import torch

    from recgs_addon.core.io.images import read_image
    from recgs_addon.core.model.colour import srgb_to_linear
    from recgs_addon.core.model.medium import ray_lengths
    from recgs_addon.core.train import water
    from recgs_addon.core.train.config import preset
    from recgs_addon.core.train.trainer import make_trainer

    scene = survey_dir(out, survey)
    meta = json.loads((scene / "survey.json").read_text())
    truth, k = meta["water"], meta["intrinsics"]
    gen = [np.array(truth[n]) for n in ("attenuation_per_m", "backscatter_per_m", "veiling_light")]
    rl = ray_lengths(k["width"], k["height"], k["fx"], k["fy"], k["cx"], k["cy"]).numpy().reshape(-1)
    rs = np.random.default_rng(0)
    seen, true, rng = [], [], []
    for path in sorted((scene / "images").glob("*.png")):
        pick = rs.choice(rl.size, per_view, replace=False)
        for dst, img in ((seen, read_image(path)), (true, read_image(scene / "clean" / path.name))):
            dst.append(srgb_to_linear(torch.from_numpy(img.reshape(-1, 3)[pick]).double()))
        rng.append(torch.from_numpy((np.load(scene / "depth" / f"{path.stem}.npy").reshape(-1) * rl)[pick]).double())
    seen, true, rng = torch.cat(seen), torch.cat(true), torch.cat(rng)
    fitted = []
    for c in range(3):
        p = torch.log(torch.tensor([0.3, 0.3, 0.05], dtype=torch.float64)).requires_grad_()
        opt = torch.optim.LBFGS([p], max_iter=500, tolerance_change=1e-16, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            att, back, veil = p.exp()
            loss = 1e6 * ((true[:, c] * torch.exp(-att * rng) + veil * (1 - torch.exp(-back * rng)) - seen[:, c]) ** 2).mean()
            loss.backward()
            return loss
        for _ in range(3):
            opt.step(closure)
        fitted.append(p.detach().exp().numpy())
    fitted = np.array(fitted).T
    print(json.dumps({"part": "given the true colour and range", "pixels": int(rng.numel()),
                      "relative_error": {n: np.round(np.abs(fitted[i] / gen[i] - 1), 4).tolist()
                                         for i, n in enumerate(("attenuation", "backscatter", "veil"))}}), flush=True)

    tr = make_trainer(scene, preset("default", medium="off", eval_every=10**9))
    obs = water._observations(tr.data)
    water._sample_colours(tr.data, obs)
    fit = water.fit_from_points(obs, water.range_profile(obs)["median_range"])
    print(json.dumps({"part": "from the sparse points", "fit": {k: np.round(v, 4).tolist() for k, v in fit["fit"].items()},
                      "spread": {k: np.round(v, 4).tolist() for k, v in fit["spread"].items()},
                      "relative_error": _rel_errors(fit["fit"], truth)}), flush=True)

    r = rng.numpy()
    edges = np.percentile(r, np.linspace(2, 98, 9))
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (r >= lo) & (r < hi)
        mid = float(r[sel].mean())
        veil_at = gen[2] * (1 - np.exp(-gen[1] * mid))
        dark = np.percentile(seen.numpy()[sel], 0.5, axis=0)
        print(json.dumps({"part": "darkest 0.5 % of pixels", "range": round(mid, 2),
                          "over_generator_veil": np.round(dark / veil_at, 2).tolist()}), flush=True)


#: Run by ``passes``: the train command with the pass estimator's water correction left out.
_NO_PASS_WATER = """
import sys
from recgs_addon.core.caustics import passes
for name in ("light_statistics", "pass_estimates", "pass_targets"):
    def dry(*a, _f=getattr(passes, name), **k):
        k["water"] = None
        return _f(*a, **k)
    setattr(passes, name, dry)
from recgs_addon.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _side_by_side(scene: Path, dest: Path, runs: dict, options: list[str]) -> dict:
    """The train command on ``scene`` once per ``runs`` entry (name -> the interpreter's
    arguments before ``train``), all at once on one thread each, into ``dest / name``; each
    run's metrics by name."""
    import os
    import subprocess

    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    procs = {}
    for name, head in runs.items():
        cmd = [sys.executable, *head, "train", str(scene), "--out", str(dest / name), *options]
        procs[name] = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                       env=env)
    metrics = {}
    for name, proc in procs.items():
        err = proc.communicate()[1]
        if proc.returncode != 0:
            raise SystemExit(f"{name} failed:\n{err[-2000:]}")
        metrics[name] = json.loads((dest / name / "metrics.json").read_text())
    return metrics


def pass_water(out: Path, minutes: float) -> None:
    """See the module: ``--only passes``."""
    runs = {"corrected": ["-m", "recgs_addon"], "uncorrected": ["-c", _NO_PASS_WATER]}
    metrics = _side_by_side(survey_dir(out, "dive-water-networks"), out / "water" / "passes", runs,
                            ["--mode", "recgs", "--estimator", "passes", "--medium", "auto", "--max-minutes",
                             str(minutes)])
    for name, m in metrics.items():
        print(json.dumps({"run": name, "true_colour_held_out": m.get("psnr_test_gt"),
                          "true_colour_photos": m.get("psnr_truecolour_gt"), "steps": m["iterations"],
                          "gaussians": m["gaussians"], "estimator": m.get("estimator"),
                          "passes": {k: v for k, v in (m.get("passes") or {}).items() if k != "share_per_frame"}}),
              flush=True)


#: Run by ``pixels``: the train command with a module constant of core/train/water.py changed.
_VARIANT = """
import sys
from recgs_addon.core.train import water
water.{} = {}
from recgs_addon.cli import main
sys.exit(main(sys.argv[1:]))
"""
#: name -> how the train command runs: the default, the veil trained, nothing kept from the points
_PIXEL_RUNS = {"points-kept": ["-m", "recgs_addon"],
               "veil-trained": ["-c", _VARIANT.format("KEEP_VEIL", "False")],
               "all-trained": ["-c", _VARIANT.format("PINNED", "-1.0")]}


def pixels(out: Path, minutes: float, survey: str = "level-reef-water", runs=("points-kept", "veil-trained")) -> None:
    """See the module: ``--only pixels``."""
    scene = survey_dir(out, survey)
    truth = json.loads((scene / "survey.json").read_text())["water"]
    metrics = _side_by_side(scene, out / "water" / "pixels" / survey, {n: _PIXEL_RUNS[n] for n in runs},
                            ["--mode", "3dgs", "--density", "adc", "--medium", "auto", "--max-minutes", str(minutes)])
    for name, m in metrics.items():
        coef = (m.get("medium") or {}).get("coefficients")
        print(json.dumps({"run": name, "survey": survey, "true_colour_held_out": m.get("psnr_test_gt"),
                          "true_colour_photos": m.get("psnr_truecolour_gt"), "steps": m["iterations"],
                          "gaussians": m["gaussians"],
                          "coefficient_errors": _rel_errors(coef, truth) if coef else None}), flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--only", choices=("runs", "decisions", "step", "identify", "passes", "pixels", "battery"),
                   default=None)
    p.add_argument("--bases", default=BATTERY_BASES, help="battery: the base surveys (comma-separated)")
    p.add_argument("--waters", default=BATTERY_WATERS, help="battery: the waters (comma-separated)")
    p.add_argument("--caustics", choices=("no", "yes", "both"), default="no",
                   help="battery: the waters over the clean photos, over the photos under moving light, or both")
    p.add_argument("--pixel-runs", default="points-kept,veil-trained", help="pixels: which (comma-separated)")
    p.add_argument("--surveys", default="", help="runs and decisions: these surveys only (comma-separated)")
    a = p.parse_args()
    surveys = [x for x in a.surveys.split(",") if x] or None
    if a.only in (None, "decisions"):
        decisions(a.out, surveys)
    if a.only in (None, "step"):
        step_cost(a.out)
    if a.only in (None, "identify"):
        identify(a.out)
    if a.only in (None, "runs"):
        runs(a.out, a.minutes, surveys)
    if a.only in (None, "passes"):
        pass_water(a.out, a.minutes)
    if a.only == "battery":   # its own runs (an hour and more): asked for by name only
        battery(a.out, a.minutes, a.bases.split(","), a.waters.split(","),
                {"no": [False], "yes": [True], "both": [False, True]}[a.caustics])
    if a.only in (None, "pixels"):
        for survey in surveys or ["level-reef-water"]:
            pixels(a.out, a.minutes, survey, a.pixel_runs.split(","))
    return 0


if __name__ == "__main__":
    sys.exit(main())
