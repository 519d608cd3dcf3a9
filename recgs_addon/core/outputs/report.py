"""Markdown + PNG reports (no bpy): one per training run (``write_run_report``) and one per
benchmark (``write_benchmark_report``, used by benchmarks/bench_caustics.py)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..caustics.config import CAUSTIC_MODES
from ..io.atomic import atomic_path
from ..io.images import read_image
from ..model.colour import srgb_to_linear
from ..train.plan import MIN_PASSES, coverage_advice
from . import plot


def _f(v, digits=2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _statistic(p: dict) -> str:
    """The pass estimator's statistic in words (a run from before the choice used the floor)."""
    return {"field": "each frame's light modelled, then the colour"}.get(p.get("statistic"), "the floor of the light")


def _passes_row(p: dict) -> str:
    """What the pass estimator cost and drew on, in one table cell."""
    if p.get("overrun"):
        return f"none made: {p['overrun']}"
    if p.get("share") is None:
        return f"none made: moving light of {p.get('light_std')} log units measured between frames ({p.get('seconds')} s)"
    looks = f", {p['median_looks']:g} independent looks" if p.get("median_looks") is not None else ""
    return (f"{p.get('seconds')} s (geometry, gathers and references, once); {100 * p.get('share', 0):.0f} % of "
            f"the training pixels from the passes (median {p.get('median_passes'):g} passes a pixel{looks}; "
            f"{_statistic(p)}), the rest low-pass; moving light "
            f"{p.get('light_std')} log units, frames under {p.get('pass_seconds')} s apart one pass"
            + (f", its decorrelation time {p['light_seconds']:g} s" if p.get("light_seconds") else "")
            + (f"; the passes abstained on {100 * p['abstained']:.1f} % of the covered pixels, whose depth is "
               "ambiguous (repetitive texture, grazing views)" if p.get("abstained") else "")
            + _looks_text(p.get("look_frames")))


def _looks_text(lk: Optional[dict]) -> str:
    """The look frames' part of the passes' cell: what was read, placed and used, and what it gave."""
    if not lk:
        return ""
    if lk.get("reason"):
        return f"; look frames: {lk['listed']} listed, none used ({lk['reason']})"
    dropped = [f"{lk[k]} {what}" for k, what in (("missing", "missing from looks/"),
                                                   ("unplaced", "with no keyframes close in time to place them by"),
                                                   ("near_heldout", "nearest a held-out keyframe"),
                                                   ("thinned", "beyond what the time limit fits"),
                                                   ("misplaced", "not lining up with their keyframe"))
               if lk.get(k)]
    placed = ", ".join(f"{lk[k]} {what}" for k, what in (("given", "posed in looks.json"),
                                                           ("interpolated", "placed between keyframes")) if lk.get(k))
    before = lk.get("median_looks_keyframes")
    return (f"; look frames: {lk.get('used', 0)} of {lk['listed']} gathered from ({placed or 'none placed'}"
            + (f"; left out: {', '.join(dropped)}" if dropped else "") + f"; {lk.get('seconds', 0):g} s)"
            + (f", the keyframes alone {before:g} independent looks" if before is not None else ""))


def write_run_report(out: Path, metrics: dict, method=None, examples: int = 3) -> Path:
    """``OUT/report.md`` with PNGs under ``OUT/report/``: held-out PSNR against time, the change
    of C per recurrence, triptychs (captured / caustic-free / ground truth) and caustic maps."""
    out = Path(out)
    rd = out / "report"
    cfg = metrics.get("config", {})
    lines = [f"# RecGS run: mode `{cfg.get('mode', '3dgs')}`", "",
             "| quantity | value |", "|---|---|"]
    rows = [("stopped because", metrics.get("reason")), ("iterations", metrics.get("iterations")),
            ("seconds", metrics.get("seconds")), ("Gaussians", metrics.get("gaussians")),
            ("SH degree", metrics.get("sh_degree")),
            ("held-out PSNR vs captured (dB)", _f(metrics.get("psnr_test_captured", metrics.get("psnr_test")))),
            ("held-out PSNR vs the run's caustic-free references (dB)",
             _f(metrics.get("psnr_test")) if metrics.get("psnr_test_captured") not in (None, metrics.get("psnr_test"))
             else None),
            ("held-out PSNR vs ground truth (dB)", _f(metrics.get("psnr_test_gt"))),
            ("held-out SSIM vs ground truth", _f(metrics.get("ssim_test_gt"), 4)),
            ("training images as captured, PSNR vs ground truth (dB)", _f(metrics.get("psnr_captured_gt"))),
            ("caustic-free training images, PSNR vs ground truth (dB)", _f(metrics.get("psnr_decaustic_gt"))),
            ("true-colour training images, PSNR vs ground truth (dB)", _f(metrics.get("psnr_truecolour_gt"))),
            ("light", (metrics.get("light") or {}).get("reason")),
            ("lamp", (metrics.get("lamp") or {}).get("reason") if (metrics.get("lamp") or {}).get("mode", "off") != "off"
             else None),
            ("water", (metrics.get("medium") or {}).get("reason")),
            ("burned-in overlay", (metrics.get("overlay") or {}).get("share") and metrics["overlay"]["reason"]),
            ("caustic estimator", metrics.get("estimator") and
             f"{metrics['estimator']} ({metrics.get('estimator_why', '')})"),
            ("caustic filter size k", metrics.get("caustic_k")),
            ("targets from the passes", metrics.get("passes") and _passes_row(metrics["passes"])),
            ("seconds, job (command to report)", metrics.get("job_seconds")),
            ("caustic estimate dropped", metrics.get("caustics_dropped")),
            ("model kept at the end", metrics.get("candidates") and
             f"{metrics['candidates']['kept']} ({metrics['candidates']['why']})"),
            ("model kept from step (best on the held-out photos)", metrics.get("best_step")),
            ("colour gain restored (R, G, B)", metrics.get("colour_gain"))]
    lines += [f"| {k} | {v} |" for k, v in rows if v not in (None, "-")]
    hist = metrics.get("history", [])
    if hist:
        series = [("vs captured photos", [h["iteration"] for h in hist], [h.get("psnr_captured", h["psnr"]) for h in hist])]
        if any("psnr_gt" in h for h in hist):
            series.append(("vs ground truth", [h["iteration"] for h in hist], [h.get("psnr_gt") for h in hist]))
        plot.line_chart(rd / "psnr.png", series, title="Held-out PSNR", xlabel="step", ylabel="dB")
        lines += ["", "## Held-out PSNR over the steps", "",
                  "Against the held-out photos as captured (caustics and all: what the run can see) and, where "
                  "the survey has it, against ground truth. A model that takes in each view's caustics falls "
                  "on both.", "", "![held-out PSNR](report/psnr.png)"]
        # what each second and each Gaussian bought (the model holds only what the views justify)
        score = [h.get("psnr_gt", h.get("psnr_captured", h["psnr"])) for h in hist]
        what = "ground truth" if any("psnr_gt" in h for h in hist) else "captured photos"
        for key, name, label in (("elapsed", "psnr_time", "seconds"), ("gaussians", "psnr_size", "Gaussians")):
            pts = [(h[key], v) for h, v in zip(hist, score) if h.get(key) is not None and v is not None]
            if pts:
                plot.line_chart(rd / f"{name}.png", [(f"vs {what}", [x for x, _ in pts], [y for _, y in pts])],
                                title=f"Held-out PSNR against {label}", xlabel=label, ylabel="dB")
        compile_info = metrics.get("compile") or {}
        fast = "numba's kernels" if compile_info.get("numba") == "ready" else "the compiled path"
        when = (f" The rasterizer took {fast} from step {compile_info['switched_at']} (eager before)."
                if compile_info.get("switched_at") is not None else "")
        lines += ["", f"Held-out PSNR (against {what}) against training time and against model size: "
                  f"speed and size next to their error.{when}", "",
                  "![PSNR against time](report/psnr_time.png) ![PSNR against Gaussians](report/psnr_size.png)"]
    cov = metrics.get("coverage")
    if cov and cov.get("points"):
        hist_c = cov["histogram"]
        plot.line_chart(rd / "coverage.png", [("seabed points", list(range(len(hist_c))), hist_c)],
                        title="Training views that see each seabed point", xlabel="views (30 = 30 or more)",
                        ylabel="points")
        lines += ["", "## Coverage: views per seabed point", "",
                  f"Each point of the model's surface is seen by a median of {cov['median_views']:g} training views "
                  f"in {cov['median_passes']:g} passes (frames less than a second apart count as one pass: they saw "
                  f"nearly the same light). {100 * cov['share_below']['5']:.0f} % of the points are seen by fewer "
                  "than 5 views.", ""]
        looks = cov.get("median_looks")
        if looks:
            lines += [f"Counted as independent looks at the light (frames whose light had time to change count "
                      f"whole, frames that saw nearly the same light share one): a median of {looks:.1f} a point.", ""]
        if (looks or cov["median_passes"]) < MIN_PASSES and cfg.get("mode") in CAUSTIC_MODES:
            lines += [coverage_advice(cov["median_views"], looks or cov["median_passes"]) + ".", ""]
        lines += ["![coverage](report/coverage.png)"]
    sup = metrics.get("view_support")
    if sup:
        hist_v = sup["histogram"]
        plot.line_chart(rd / "view_support.png", [("Gaussians", list(range(len(hist_v))), hist_v)],
                        title="Training views that carry each Gaussian", xlabel="views (10 = 10 or more)",
                        ylabel="Gaussians")
        lines += ["", "## Where the caustics go: views per Gaussian", "",
                  f"Median {sup['median_views']:.0f} training views carry a Gaussian (blending weight of at least "
                  f"one pixel); {100 * sup['share_le2']:.0f} % are carried by 2 or fewer, whose colours are "
                  f"fitted to the light of those few photos.", "", "![view support](report/view_support.png)"]
        needless = (metrics.get("density") or {}).get("needless", 0)
        if needless:
            lines += ["", f"Training removed {needless:,} Gaussians that no view needed (under "
                      f"{cfg.get('density', {}).get('prune_weight', 0.25):g} pixel of every view that drew them) "
                      "and grew others where the error was."]
    lines += _light_section(metrics.get("light"), cfg.get("mode"), metrics.get("lamp") or {})
    lines += _water_section(metrics.get("medium") or {})
    lines += _water_example(out, rd, method)
    rec = metrics.get("recurrences", [])
    if rec:
        plot.line_chart(rd / "c_change.png", [("mean |dC| / mean |C|", [r["recurrence"] for r in rec],
                                               [r["c_change"] for r in rec])],
                        title="Change of the caustic estimate", xlabel="recurrence", ylabel="relative change",
                        log_y=True)
        lines += ["", "## Recurrences", "", "![C change](report/c_change.png)", "",
                  "| recurrence | iteration | seconds | change of C | mean abs C | held-out PSNR after its steps (dB) "
                  "| scored against |", "|---|---|---|---|---|---|---|"]
        against = {"references": "the held-out frames' references from the passes",
                   "captured": "the held-out photos as captured"}
        lines += [f"| {r['recurrence']} | {r['iteration']} | {r['elapsed']} | {r['c_change']:.4f} | "
                  f"{r['mean_abs_c']:.4f} | {_f(r.get('psnr_heldout'))} | "
                  f"{against.get(r.get('heldout_vs'), '-') if r.get('psnr_heldout') is not None else '-'} |"
                  for r in rec]
    data = None if method is None else method.data
    if data is not None and data.train_ids and method.takes_light_off():
        ids = data.train_ids[:: max(1, len(data.train_ids) // examples)][:examples]
        lines += ["", "## Examples (training views)", ""]
        for i in ids:
            name = Path(data.scene.cameras[i].name).stem
            image = data.view(i, 1)[1].cpu().numpy()
            free = method.decaustic_image(i).cpu().numpy()
            gt = data.gt_view(i)
            ims, labels = [image, modelled_light(image, free), free], ["captured", "light taken out", "caustic-free"]
            if gt is not None:
                ims.append(gt.cpu().numpy())
                labels.append("ground truth")
            plot.labelled_strip(rd / f"triptych_{name}.png", ims, labels)
            cmap = image - free
            strip = [plot.signed_map(cmap)]
            lbl = ["caustic estimate C"]
            if gt is not None:
                true_c = image - gt.cpu().numpy()
                span = float(np.percentile(np.abs(true_c), 99)) or 1.0
                strip = [plot.signed_map(cmap, span), plot.signed_map(true_c, span)]
                lbl = ["caustic estimate C", "true I - ground truth"]
            plot.labelled_strip(rd / f"caustic_{name}.png", strip, lbl)
            lines += [f"![{name}](report/triptych_{name}.png)", "", f"![{name} caustics](report/caustic_{name}.png)", ""]
            lines += _supplied(metrics.get("passes") or {}, data.scene.cameras[i].name)
    elif data is not None and cfg.get("mode") in CAUSTIC_MODES:
        lines += ["", "No light was taken off the photos, so they are caustic-free as they are: the run wrote no "
                  "caustic maps and no caustic-free copies of them (`decaustic/`).", ""]
    path = out / "report.md"
    with atomic_path(path, "report") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def modelled_light(photo: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The light a run took out of a photo, as an image: the grey ratio of the photo to its
    caustic-free image in linear light, on a log scale (mid-grey: none; white: twice the light
    or more; black: half or less)."""
    def grey(x):
        return srgb_to_linear(torch.from_numpy(np.clip(x, 0, 1))).mean(-1).numpy()

    ratio = (grey(photo) + 0.01) / (grey(free) + 0.01)
    return np.repeat(plot.signed_map(np.log2(ratio)[..., None], 1.0), 3, -1)


def _supplied(p: dict, name: str) -> list[str]:
    """Which estimate supplied a training view's caustic-free pixels."""
    share = (p.get("share_per_frame") or {}).get(name)
    if share is None:
        return []
    return [f"{100 * share:.0f} % of this view's pixels from the passes that saw them ({_statistic(p)}), "
            f"{100 * (1 - share):.0f} % from its own low-pass estimate.", ""]


def _light_section(light: Optional[dict], mode: Optional[str], lamp: dict) -> list[str]:
    """What light the survey showed before training (core/caustics/light.py), and what the run
    did with it."""
    if not light or not light.get("pairs"):
        return []
    pct = lambda v: f"{100 * (math.exp(v) - 1):.0f} %"   # noqa: E731
    if mode == "recgs":
        did = ("Caustics were found, and the run removed them." if light["caustics"] else
               "No caustics were found, so the run trained plain 3DGS on the photos.")
    else:
        did = ("Caustics were found: `--mode recgs` (the panel's RecGS) removes them." if light["caustics"] else
               "No caustics were found.")
    if lamp.get("kept"):
        did += " The light fixed to the camera was modelled with the Gaussians, which hold the seabed evenly lit."
    return ["", "## Light: caustics, or light fixed to the camera", "",
            f"Before training, {light['pairs']} pairs of frames that see the same seabed were compared: "
            "how a seabed point's brightness changes from one frame to the other, split into light fixed to "
            "the camera (a pattern over the image and a fall-off with range: a lamp, vignetting), each frame's "
            "exposure, and light that moves over the seabed (caustics). " + did, "",
            "| part of the light | spread between frames |", "|---|---|",
            f"| moving over the seabed (caustics), frames taken from nearly the same place | {pct(light['moving'])} "
            f"({100 * light['share']:.0f} % of the differences) |",
            *([f"| ... frames far apart (misregistration and gloss grow there) | {pct(light['moving_far'])} |",
               f"| the survey's noise floor for it | {pct(light['floor'])} |"] if "floor" in light else []),
            f"| fixed to the camera (over the frame) | {pct(light['camera'])} |",
            f"| exposure (frame to frame) | {pct(light['exposure'])} |", "",
            f"{light['reason'][0].upper() + light['reason'][1:]}."
            + (f" What decided: {light['decided_by']}." if light.get("decided_by") and light["caustics"] else "")]


def _water_prior(medium: dict) -> list[str]:
    """Which channels' attenuation came from the photos and which from natural water's locus."""
    prior = medium.get("prior") or {}
    if "source" not in prior:
        return []
    names = ("red", "green", "blue")
    filled = [f"{n} {v:.3f} +- {e:.3f} ({src})" for n, v, e, src in
              zip(names, prior["values"], prior["values_spread"], prior["source"]) if src != "photos"]
    text = (f"The attenuation the survey pins is most like Jerlov's water type {prior['name']} "
            f"({prior['misfit']:.1f} standard deviations from it, the natural waters' locus with the fit's error bars)")
    text += (f"; where the survey leaves a colour loose or free, training starts it from there: {', '.join(filled)}."
             if filled else ".")
    return ["", text]


def _water_rate_tied(medium: dict) -> list[str]:
    """Which channels' backscatter rate the survey left free and the fit tied to the attenuation."""
    tied = [n for n, t in zip(("red", "green", "blue"), medium.get("rate_tied") or []) if t]
    if not tied:
        return []
    return ["", f"The survey leaves the backscatter rate of {', '.join(tied)} free (seen from one range, a "
                "brighter veil that builds up more slowly fits as well): it is tied to that channel's attenuation, "
                "as in the textbook model of the water, and its veil's error bar covers a rate twice or half that."]


def _rgb3(v) -> str:
    return " / ".join(f"{x:.3f}" for x in v)


def _water_section(medium: dict) -> list[str]:
    """The fitted water: coefficients per channel (and what the sparse points gave before training)."""
    coef = medium.get("coefficients")
    if not coef:   # not modelled: why, and what the survey pins of it
        if not medium.get("pinning"):
            return []
        left = medium.get("coefficients_left_out") if medium.get("as_seen") else None
        if left:   # trained, then left out at the end: what it was
            head = [f"Trained, then left out: {medium.get('reason', '')}. The water it had (per scene unit, red / "
                    f"green / blue): attenuation {_rgb3(left['attenuation'])}, backscatter "
                    f"{_rgb3(left['backscatter'])}, veil {_rgb3(left['veil'])}."]
        else:
            head = [f"Not modelled: {medium.get('reason', '')}."]
        return ["", "## The water", ""] + head + _water_pinning(medium)
    lines = ["", "## The water", "",
             "Fitted with the Gaussians, which hold the seabed's true colour; `medium.json` has the numbers and "
             "`truecolour/` the photos taken out of the water. Per scene unit (metres where the survey's poses "
             f"are in metres), red / green / blue; {medium.get('reason', '')}.", "",
             "| | attenuation | backscatter | veil (linear) |", "|---|---|---|---|",
             f"| fitted | {_rgb3(coef['attenuation'])} | {_rgb3(coef['backscatter'])} | {_rgb3(coef['veil'])} |"]
    pre = medium.get("prefit_coefficients")
    if pre:
        lines.append(f"| from the sparse points, before training | {_rgb3(pre['attenuation'])} | "
                     f"{_rgb3(pre['backscatter'])} | {_rgb3(pre['veil'])} |")
    lines += (_water_pinning(medium) + _water_prior(medium) + _water_rate_tied(medium) + _water_under_light(medium)
              + _water_kept(medium))
    if medium.get("cues"):
        lines += ["", "Where the fit disagrees with what natural waters and seabeds look like (said, not overruled):", ""]
        lines += [f"- {c[0].upper() + c[1:]}." for c in medium["cues"]]
    if medium.get("range_p5_p95"):
        lo, hi = medium["range_p5_p95"]
        lines += ["", f"Ranges seen: {lo:.2f} to {hi:.2f} (5th to 95th percentile); each point is seen from "
                      f"ranges a median x{medium['range_spread']:.2f} apart."]
    return lines


def _water_pinning(medium: dict) -> list[str]:
    """What the survey pins of the water (core/train/water.py's ``pinning``): a line per coefficient."""
    pins, fit, spread = medium.get("pinning"), medium.get("prefit_fit"), medium.get("prefit_spread")
    lines = []
    if pins and fit and spread:
        lines += ["", "What the survey's ranges pin (the sparse points' fit +- its error bar, the spread of refits on "
                      "points drawn again or the Gauss-Newton error, whichever is larger; pinned within 10 %, loose "
                      "within 30 %, else free):", "",
                  "| | red | green | blue |", "|---|---|---|---|"]
        names = {"attenuation": "attenuation", "veil_at_length": "veil at the median range",
                 "backscatter": "backscatter", "veil": "veil"}
        for key, name in names.items():
            cells = [f"{v:.3f} +- {e:.3f} ({p})" for v, e, p in zip(fit[key], spread[key], pins[key])]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _water_under_light(medium: dict) -> list[str]:
    """Whether the sparse points' fit measured the caustics' light (core/model/medium_fit.py)."""
    under = medium.get("prefit_under_light")
    if not under or "light_noise" not in under:
        return []
    light, noise = under["light_noise"]
    plain = _rgb3(under.get("plain_attenuation", []))
    if under.get("under_light"):
        return ["", f"The photos hold moving light (caustics): the points' fit measured it, a grey gain on the seabed "
                    f"from view to view ({light:.2f} log units, {light / max(noise, 1e-9):.0f} times the photos' own "
                    f"noise), instead of taking it for noise; taken for noise, the attenuation read {plain}."]
    return ["", f"The photos hold moving light, but it moves the points' colours by {light:.2f} log units, "
                f"{light / max(noise, 1e-9):.1f} times the photos' own noise: too little to measure the water by, "
                "so the points' fit takes it for noise."]


def _water_kept(medium: dict) -> list[str]:
    """Which channels' attenuation (and veil) training kept from the sparse points."""
    names = ("red", "green", "blue")
    kept = medium.get("attenuation_kept") or ([True] * 3 if medium.get("attenuation_from_points") else None)
    if not (kept and any(kept)):
        return []
    veil = [n for n, k in zip(names, medium.get("veil_kept") or []) if k]
    return ["", f"The attenuation of {', '.join(n for n, k in zip(names, kept) if k)}"
                + (f" and the veil of {', '.join(veil)}" if veil else "")
                + (" are" if veil else " is") + " the sparse points' (pinned by the survey, and their ranges are exact); training fitted the "
                  "rest from every pixel."]


def _water_example(out: Path, rd: Path, method) -> list[str]:
    """A training photo as captured beside its true colour (``truecolour/``) and, where the
    survey has it, the ground truth."""
    data = None if method is None else method.data
    if data is None or not data.train_ids or not (out / "truecolour").is_dir():
        return []
    i = data.train_ids[len(data.train_ids) // 2]
    name = Path(data.scene.cameras[i].name).stem
    path = out / "truecolour" / f"{name}.png"
    if not path.is_file():
        return []
    true = read_image(path)
    ims, labels = [data.view(i, 1)[1].cpu().numpy(), true], ["as captured", "true colour"]
    gt = data.gt_view(i)
    if gt is not None:
        ims.append(gt.cpu().numpy())
        labels.append("ground truth")
    plot.labelled_strip(rd / f"water_{name}.png", ims, labels)
    return ["", f"![{name}: as captured and in true colour](report/water_{name}.png)"]


#: A decision between two models whose ground-truth scores differ by less than this is right
#: either way (two 5-minute runs of the same method differ by about this much).
DECISION_TIE_DB = 0.1


def gap_recovered(row: dict) -> dict:
    """(method - 3dgs) / (oracle - 3dgs) of held-out PSNR against ground truth, for every RecGS
    method of a survey's row of runs (where the oracle beats plain)."""
    try:
        p3, po = row["3dgs"]["psnr_test_gt"], row["oracle"]["psnr_test_gt"]
    except (KeyError, TypeError):
        return {}
    if p3 is None or po is None or po - p3 <= 1e-6:
        return {}
    return {m: (r["psnr_test_gt"] - p3) / (po - p3) for m, r in row.items()
            if m.startswith("recgs") and r and r.get("psnr_test_gt") is not None}


def decision_right(candidates: dict) -> Optional[bool]:
    """Whether a RecGS run kept the better of its two models by ground truth (None where the
    survey has none)."""
    a, b = candidates["recgs"].get("psnr_gt"), candidates["plain"].get("psnr_gt")
    if a is None or b is None:
        return None
    kept, other = (a, b) if candidates["kept"] == "recgs" else (b, a)
    return kept >= other - DECISION_TIE_DB


def write_benchmark_report(out: Path, surveys: Sequence[str], methods: Sequence[str], results: dict,
                           notes: Optional[list[str]] = None) -> Path:
    """``results[survey][method]`` = run metrics (metrics.json). Writes ``OUT/benchmark.md`` with
    one table and one PNG per survey of held-out PSNR (vs ground truth) against time."""
    out = Path(out)
    lines = ["# Caustic-removal benchmark", "",
             "Held-out PSNR / SSIM against the clean ground truth (dB), Gaussians (k = thousands), steps, "
             "time to the end of the run (s), PSNR of the caustic-free training images against ground "
             "truth (dB), and the RecGS gap recovered = (recgs - 3dgs) / (oracle - 3dgs). Views / passes per "
             "point: the median training views that see a point of the model's surface, and the passes among "
             "them (frames less than a second apart count as one); photos: the training photos as captured "
             "against ground truth (dB).", ""]
    head = "| survey | views / passes per point | photos | " + " | ".join(methods) + " | gap recovered |"
    lines += [head, "|" + "---|" * (len(methods) + 4)]
    for s in surveys:
        row = results.get(s, {})
        cov = next((r.get("coverage") for r in row.values() if r and r.get("coverage")), None)
        views = f"{cov['median_views']:g} / {cov['median_passes']:g}" if cov and cov.get("points") else "-"
        photos = next((r.get("psnr_captured_gt") for r in row.values() if r and r.get("psnr_captured_gt")), None)
        cells = [views, _f(photos)]
        for m in methods:
            r = row.get(m)
            if not r:
                cells.append("-")
                continue
            cell = f"{_f(r.get('psnr_test_gt'))} dB / {_f(r.get('ssim_test_gt'), 3)}"
            if r.get("gaussians") is not None:
                cell += f", {r['gaussians'] / 1000:.1f}k G, {r.get('iterations')} steps"
            cell += f", {_f(r.get('seconds'), 0)} s"
            if r.get("psnr_decaustic_gt") is not None:
                cell += f", train {_f(r['psnr_decaustic_gt'])}"
            cells.append(cell)
        gap = ", ".join(f"{m}: {g:.2f}" for m, g in gap_recovered(row).items()) or "-"
        lines.append(f"| {s} | " + " | ".join(cells) + f" | {gap} |")
    decisions = [(s, m, r["candidates"]) for s in surveys for m, r in results.get(s, {}).items()
                 if r and (r.get("candidates") or {}).get("kept")]
    if decisions:
        right = [decision_right(c) for _, _, c in decisions]
        known = [x for x in right if x is not None]
        lines += ["", "## Never worse than plain: the end-of-run decisions", "",
                  "Each RecGS run ends by keeping its caustic-free model or the plain model it started "
                  "from, judged on the held-out photos as captured. Held-out PSNR of both against ground "
                  f"truth (dB); right = the kept model within {DECISION_TIE_DB} dB of the better one.", "",
                  f"Right {sum(known)} of {len(known)}.", "",
                  "| survey | method | kept | recgs (gt) | plain (gt) | right | why |", "|---|---|---|---|---|---|---|"]
        for (s, m, c), ok in zip(decisions, right):
            lines.append(f"| {s} | {m} | {c['kept']} | {_f(c['recgs'].get('psnr_gt'))} | {_f(c['plain'].get('psnr_gt'))} | "
                         f"{'-' if ok is None else ('yes' if ok else '**no**')} | {c.get('why', '')} |")
    for s in surveys:
        runs = [(m, results.get(s, {}).get(m)) for m in methods]
        runs = [(m, [x for x in r["history"] if x.get("psnr_gt") is not None]) for m, r in runs if r and r.get("history")]
        if not runs:
            continue
        for key, label in (("psnr_gt", "PSNR (dB)"), ("ssim_gt", "SSIM")):
            plot.line_chart(out / f"{key.split('_')[0]}_time_{s}.png",
                            [(m, [x["elapsed"] for x in h], [x.get(key) for x in h]) for m, h in runs],
                            title=f"{s}: held-out {label.split()[0]} vs ground truth", xlabel="seconds", ylabel=label)
        lines += ["", f"## {s}", "", f"![{s} PSNR](psnr_time_{s}.png) ![{s} SSIM](ssim_time_{s}.png)", "",
                  "Held-out PSNR against ground truth at the last evaluation before 1, 2 and 5 minutes:", "",
                  "| method | 1 min | 2 min | 5 min |", "|---|---|---|---|"]
        for m, h in runs:
            at = [max((x for x in h if x["elapsed"] <= t), key=lambda x: x["elapsed"], default=None) for t in (60, 120, 300)]
            lines.append(f"| {m} | " + " | ".join(_f(x["psnr_gt"]) if x else "-" for x in at) + " |")
    if notes:
        lines += ["", "## Notes", ""] + notes
    path = out / "benchmark.md"
    with atomic_path(path, "report") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path
