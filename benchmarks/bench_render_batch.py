"""The plain-PyTorch rasterizer's batching on a device: tile size and pairs per chunk.

    python benchmarks/bench_render_batch.py SCENE_DIR [--gaussians 50000] [--device cuda]
        [--settings 4:18,16:18,16:22,16:24,triton] [--repeats 5]

The plain-PyTorch path (the one a GPU takes) tiles the image and composites it in chunks of
(pixel, Gaussian) pairs sized for a CPU's caches (tiles of 4 pixels, 2^18 pairs a chunk); on a
GPU every chunk is a handful of kernel launches, and the launches, not the arithmetic, take the
time. This renders one training view of a model built from the survey's sparse points (SH
degree 3) forward and backward at each setting (``TILE:LOG2_PAIRS``), each ended by the
device's synchronisation, and prints the median milliseconds, the chunks, the peak device
memory and the largest difference from the first setting's image and gradients (the settings
must give the same numbers: the binning changes, not the maths). The setting ``triton`` renders
with the compositing in Triton's fused kernels (one launch forward, one backward), against the
same first setting.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_threads import model  # noqa: E402
from recgs_addon.core.io.colmap import load_scene  # noqa: E402
from recgs_addon.core.render.rasterizer import render  # noqa: E402
from recgs_addon.core.train.data import view_tensors  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def one(params, cam, device, tile: int, pairs: int, path=False):
    """Image and gradients of one forward and backward at ``tile``, ``pairs`` on ``path``
    (``render(compiled=...)``); and the render's stats."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
    viewmat, K = view_tensors(cam, device)
    out = render(leaves["means"], leaves["log_scales"], leaves["quats"], leaves["logit_opacities"], leaves["sh"],
                 viewmat, K, cam.width, cam.height, sh_degree=3, tile_size=tile, chunk_pairs=pairs, compiled=path)
    (out.rgb.square().mean() + out.alpha.mean()).backward()
    return out.rgb.detach(), {k: v.grad for k, v in leaves.items()}, out.stats


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--settings", default="4:18,16:18,16:22,16:24")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    g = model(args.scene, args.gaussians)
    params = {"means": torch.as_tensor(g.means), "log_scales": torch.as_tensor(g.log_scales),
              "quats": torch.as_tensor(g.quats), "logit_opacities": torch.as_tensor(g.logit_opacities),
              "sh": torch.as_tensor(g.sh)}
    params = {k: v.float().to(device) for k, v in params.items()}
    cam = load_scene(args.scene).cameras[0]
    base = None
    for spec in args.settings.split(","):
        # TILE:LOG2_PAIRS on the plain-PyTorch path, or "triton": the compositing in Triton's kernels
        path = "triton" if spec == "triton" else False
        tile, log_pairs = (16, 0) if path else (int(x) for x in spec.split(":"))
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        one(params, cam, device, tile, 1 << log_pairs, path)   # warm-up
        times = []
        for _ in range(args.repeats):
            _sync(device)
            t = time.perf_counter()
            img, grads, stats = one(params, cam, device, tile, 1 << log_pairs, path)
            _sync(device)
            times.append(time.perf_counter() - t)
        diff = 0.0
        if base is None:
            base = (img, grads)
        else:
            # the image's and each gradient's largest difference, the gradients' in units of the
            # largest gradient of any parameter (one that is ~0 everywhere has no scale of its own)
            scale = max(float(v.abs().max()) for v in base[1].values())
            diff = max([float((img - base[0]).abs().max())]
                       + [float((grads[k] - base[1][k]).abs().max()) / max(scale, 1e-30) for k in grads])
        peak = (f", peak {torch.cuda.max_memory_allocated(device) / 2 ** 30:.2f} GiB" if device.type == "cuda"
                else "")
        what = f"{stats['path']:>6}, tile {tile:2d}" + ("" if path else f", 2^{log_pairs} pairs a chunk")
        print(f"{what}: {1000 * statistics.median(times):8.1f} ms forward and "
              f"backward, {stats['chunks']} chunks, {stats['pairs']:,} pairs{peak}; largest difference from the "
              f"first {diff:.2e}", flush=True)
    print(f"({args.gaussians:,} Gaussians, {cam.width}x{cam.height}, {args.device})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
