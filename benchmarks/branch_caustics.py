"""What the recurrences themselves do: several caustic variants branched from one shared warm-up.

    .venv/bin/python benchmarks/branch_caustics.py SURVEY OUT [--variants 3dgs,lowpass,lf,l2] [--iterations 4000]

Trains plain 3DGS until RecGS's warm-up rule ends it (saved as OUT/warmup.pt, reused after),
then trains each variant on from that same state to ``--iterations`` and writes OUT/VARIANT.json:
the final held-out PSNR / SSIM against ground truth (SURVEY/clean), the step of the kept
(best) model, the caustic-free training images' PSNR beside the photos', and the held-out
history after the warm-up. Since the warm-up is shared, differences are the variants' alone
(benchmarks/RESULTS.md#caustics-branching-mild).
"""
import argparse
import json
import sys
import time
from pathlib import Path
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.caustic_estimators.methods import register  # noqa: E402
from recgs_addon.core.caustics.build import make_method  # noqa: E402
from recgs_addon.core.caustics.config import CausticConfig  # noqa: E402
from recgs_addon.core.train.config import preset  # noqa: E402
from recgs_addon.core.train.losses import psnr  # noqa: E402

register()   # the light-field variants
VARIANTS = {
    "3dgs": dict(mode="3dgs"),
    "lowpass": dict(mode="recgs"),
    "lf": dict(mode="recgs", estimator="lightfield"),
    "l2": dict(mode="recgs", fit_loss="l2"),
    "lfl2": dict(mode="recgs", estimator="lightfield", fit_loss="l2"),
    "trim": dict(mode="recgs", robust_k=1.5),
}

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=2500)
    ap.add_argument("--variants", default="3dgs,lowpass,lf,l2,lfl2")
    ap.add_argument("--extra", default="")  # k=v,k=v caustic overrides for all variants
    a = ap.parse_args(argv)
    out = Path(a.out); out.mkdir(parents=True, exist_ok=True)
    gt = str(Path(a.scene) / "clean")
    cfg = preset("default", iterations=a.iterations, downscale=a.downscale, strategy="adc")
    extra = dict(kv.split("=") for kv in a.extra.split(",") if kv)
    def cc(**kw):
        kw = {**kw}
        for k, v in extra.items():
            f = CausticConfig.__dataclass_fields__[k]
            kw[k] = type(f.default)(v)
        return CausticConfig(**kw)
    wpath = out / "warmup.pt"
    t0 = time.time()
    if not wpath.exists():
        m = make_method(a.scene, cfg, cc(mode="recgs"), gt_images=gt)
        m.run(should_stop=lambda: m.stage == "warmup" and m._due())
        torch.save(m.state_dict(), wpath)
        print(f"warm-up ended at step {m.trainer.step} ({time.time()-t0:.0f}s), {len(m.trainer.params['means'])} Gaussians", flush=True)
    state = torch.load(wpath, weights_only=False)
    for name in a.variants.split(","):
        res = out / f"{name}.json"
        if res.exists():
            print(name, json.loads(res.read_text())); continue
        t = time.time()
        kw = VARIANTS[name]
        m = make_method(a.scene, preset("default", iterations=a.iterations, downscale=a.downscale, strategy="adc"), cc(**kw), gt_images=gt)
        if kw["mode"] == "3dgs":
            m.trainer.load_state_dict(state)
        else:
            m.load_state_dict(state)
        reason = m.run()
        ev = m.trainer.evaluate()
        r = {"psnr_gt": round(ev.get("psnr_gt", 0), 3), "ssim_gt": round(ev.get("ssim_gt", 0), 4), "gaussians": len(m.trainer.params["means"]),
             "steps": m.trainer.step, "best_step": m.trainer.best_step, "reason": reason, "secs": round(time.time() - t)}
        if kw["mode"] == "recgs":
            ids = m.data.train_ids
            r["decaustic"] = round(float(np.mean([psnr(m.decaustic_image(i).clamp(0, 1), m.data.gt_view(i)) for i in ids])), 3)
            r["photos"] = round(float(np.mean([psnr(m.data.view(i)[1], m.data.gt_view(i)) for i in ids])), 3)
            r["recurrences"] = m.recurrence; r["dropped"] = m.drop_reason
            r["light_gain"] = m.summary().get("light_gain")
        r["history"] = [(h["iteration"], round(h.get("psnr_gt", 0), 2), round(h.get("psnr_captured", 0), 2), h.get("phase")) for h in m.trainer.history if h["iteration"] > 2000]
        res.write_text(json.dumps(r))
        print(name, r, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
