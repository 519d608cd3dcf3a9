#!/usr/bin/env bash
# The device check: one script a lent GPU machine runs from the repository root in under ten
# minutes, printing the figures the hardware goals are judged by.
#
#     PY=python3 bash benchmarks/device_check.sh [OUT]
#
# PY is a Python with a CUDA build of torch, numpy, numba and pycolmap (the device machine's
# own; .venv here is CPU-only). OUT (default: $OUT, else out/device) collects every log and
# metrics file. Parts, each under its own time limit so that one slow part leaves the others
# their time:
#   1. the machine: torch, CUDA, the GPU, the cores;
#   2. a training step at 50k and 500k Gaussians and 1280x960 (the sample survey scaled up), on
#      the CPU's cores (numba's path), on the GPU's plain-PyTorch path and on Triton's kernels
#      (the whole render: the trainer's choice there): seconds a step and peak GPU memory
#      (bench_threads.py);
#   3. one render's forward and backward on the GPU with the plain-PyTorch path's tiles and
#      chunks as sized for a CPU, and larger (bench_render_batch.py: the kernel launches), and
#      with Triton's kernels: the time and the largest difference of image and gradients;
#   4. the README's main job (the bundled dive survey, RecGS, two minutes) on the GPU and on
#      the CPU, one after the other: steps, held-out PSNR against the ground truth, Gaussians,
#      peak memory (the GPU job on Triton's kernels where they load, as a user's would be).
# The figures go to the benchmark record beside the 2-core machine's.
set -u
cd "$(dirname "$0")/.."
PY=${PY:-python3}
OUT=${1:-${OUT:-out/device}}
mkdir -p "$OUT"
CORES=$(nproc)
say() { echo "== $*"; }

say "machine"
"$PY" - <<'EOF' 2>&1 | tee "$OUT/machine.txt"
import os, platform, torch
print("python", platform.python_version(), "torch", torch.__version__, "cores", os.cpu_count())
print("cuda", torch.cuda.is_available(), torch.version.cuda,
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "-")
try:
    import triton
    print("triton", triton.__version__)
except ImportError:
    print("triton not installed")
EOF

say "a step at 1280x960 (sample survey scaled up)"
SAMPLE="$OUT/sample_1280"
[ -d "$SAMPLE/sparse" ] || timeout 40 "$PY" benchmarks/scale_survey.py data/sample "$SAMPLE" --width 1280 \
    > "$OUT/scale.log" 2>&1 || echo "scaling the sample failed: see $OUT/scale.log"
timeout 110 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 --threads "$CORES" --steps 4 \
    --densifying 2>&1 | tee "$OUT/steps_cpu.txt" | tail -n 12
timeout 90 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 --steps 6 --densifying \
    --device cuda 2>&1 | tee "$OUT/steps_cuda.txt" | tail -n 12
timeout 90 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 --steps 6 --densifying \
    --device cuda --gpu-path triton 2>&1 | tee "$OUT/steps_triton.txt" | tail -n 12

say "one render on the GPU: the plain-PyTorch path's batching (tile size : log2 pairs a chunk) and Triton's kernels"
timeout 60 "$PY" benchmarks/bench_render_batch.py "$SAMPLE" --gaussians 50000 --device cuda \
    --settings 4:18,16:22,triton --repeats 3 2>&1 | tee "$OUT/render_batch.txt" | tail -n 6
timeout 60 "$PY" benchmarks/bench_render_batch.py "$SAMPLE" --gaussians 500000 --device cuda \
    --settings 16:22,triton --repeats 3 2>&1 | tee "$OUT/render_batch_500k.txt" | tail -n 4

say "the README's job, two minutes, on the GPU and on the CPU"
for dev in cuda cpu; do
    rm -rf "$OUT/dive_$dev"
    timeout 140 "$PY" -m recgs_addon train data/dive --out "$OUT/dive_$dev" --mode recgs --max-minutes 2 \
        --device "$dev" > "$OUT/dive_$dev.log" 2>&1 || echo "the $dev job did not finish: see $OUT/dive_$dev.log"
    "$PY" - "$OUT/dive_$dev" "$dev" <<'EOF'
import json, sys
from pathlib import Path
m = Path(sys.argv[1]) / "metrics.json"
if not m.is_file():
    sys.exit(print(f"{sys.argv[2]}: no metrics"))
d = json.loads(m.read_text())
gb = lambda b: "-" if b is None else f"{b / 2 ** 30:.2f} GiB"
print(f"{sys.argv[2]}: {d['iterations']} steps in {d['seconds']} s ({d['iterations'] / max(d['seconds'], 1e-9):.1f} a second), "
      f"held-out {d.get('psnr_test_gt')} dB against the ground truth, {d['gaussians']} Gaussians, "
      f"peak memory {gb(d.get('peak_resident_bytes'))}, GPU {gb(d.get('peak_device_bytes'))}")
EOF
done
say "done: $OUT"
