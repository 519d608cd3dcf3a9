#!/usr/bin/env bash
# The device check: one script a lent GPU machine runs from the repository root in under ten
# minutes, printing the figures the hardware goals are judged by.
#
#     PY=python3 SURVEY=out/bench/surveys/rows-72 bash benchmarks/device_check.sh [OUT]
#
# PY is a Python with a CUDA build of torch, numpy, numba and pycolmap (the device machine's
# own; .venv here is CPU-only). SURVEY is a generated survey with ground truth (clean/), made
# here by benchmarks/bench_caustics.py and carried to the machine (rows-72 is 39 MB); without it
# the five-minute run is skipped and said. OUT (default: $OUT, else out/device) collects every
# log and metrics file. BUDGET (default 570) is the seconds the whole check may take: each part
# runs under its own time limit, in this order, and a part that no longer fits is skipped and
# said, so that a slow part leaves the most important figures their time:
#   1. the machine: torch, CUDA, the GPU, the cores;
#   2. a training step at 50k and 500k Gaussians and 1280x960 (the sample survey scaled up) on
#      two CPU cores (numba's path: the goals' reference) and on Triton's kernels (the trainer's
#      choice on a GPU): seconds a step and peak GPU memory (bench_threads.py);
#   3. the README's main job (the bundled dive survey, RecGS, two minutes) on the GPU (on
#      Triton's kernels where they load, as a user's would be): steps, held-out PSNR against the
#      ground truth, Gaussians, peak memory (the two-core figure is in the benchmark record, and
#      part 7 measures it here where time is left);
#   4. five minutes of RecGS on SURVEY on the GPU: the same figures;
#   5. the step of part 2 on the GPU's plain-PyTorch path;
#   6. one render's forward and backward on the GPU at 500k Gaussians, the plain-PyTorch path's
#      tiles and chunks against Triton's kernels (bench_render_batch.py: the time and the largest
#      difference of image and gradients);
#   7. the README's job on two CPU cores, on this machine.
# The figures go to the benchmark record beside the 2-core machine's.
set -u
cd "$(dirname "$0")/.."
PY=${PY:-python3}
OUT=${1:-${OUT:-out/device}}
SURVEY=${SURVEY:-}
BUDGET=${BUDGET:-570}
mkdir -p "$OUT"
START=$SECONDS
PIN=""                                   # two cores for the CPU's figures, where taskset is there
command -v taskset > /dev/null && PIN="taskset -c 0,1"
say() { echo "== $*"; }
# fits NEED: true where NEED more seconds fit in the budget; else says the part is skipped
fits() {
    local left=$((BUDGET - (SECONDS - START)))
    if [ "$left" -lt "$1" ]; then
        echo "skipped: needs about $1 s, $left s of the budget left"
        return 1
    fi
}
# job DIR LABEL: the figures of a train job's metrics.json
job() {
    "$PY" - "$1" "$2" <<'EOF'
import json, sys
from pathlib import Path
m = Path(sys.argv[1]) / "metrics.json"
if not m.is_file():
    sys.exit(print(f"{sys.argv[2]}: no metrics (see {Path(sys.argv[1]).parent})"))
d = json.loads(m.read_text())
gb = lambda b: "-" if b is None else f"{b / 2 ** 30:.2f} GiB"
print(f"{sys.argv[2]}: {d['iterations']} steps in {d['seconds']} s ({d['iterations'] / max(d['seconds'], 1e-9):.1f} a second), "
      f"job {d['job_seconds']} s, held-out {d.get('psnr_test_gt')} dB against the ground truth, {d['gaussians']} Gaussians, "
      f"peak memory {gb(d.get('peak_resident_bytes'))}, GPU {gb(d.get('peak_device_bytes'))}")
EOF
}

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

say "a step at 1280x960 (sample survey scaled up): two CPU cores, Triton's kernels"
SAMPLE="$OUT/sample_1280"
[ -d "$SAMPLE/sparse" ] || timeout 40 "$PY" benchmarks/scale_survey.py data/sample "$SAMPLE" --width 1280 \
    > "$OUT/scale.log" 2>&1 || echo "scaling the sample failed: see $OUT/scale.log"
fits 70 && $PIN timeout 70 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 \
    --threads 2 --steps 3 --densifying 2>&1 | tee "$OUT/steps_cpu2.txt" | tail -n 6
fits 60 && timeout 60 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 --steps 6 --densifying \
    --device cuda --gpu-path triton 2>&1 | tee "$OUT/steps_triton.txt" | tail -n 6

say "the README's job, two minutes, on the GPU"
if fits 135; then
    rm -rf "$OUT/dive_cuda"
    timeout 135 "$PY" -m recgs_addon train data/dive --out "$OUT/dive_cuda" --mode recgs --max-minutes 2 \
        --device cuda > "$OUT/dive_cuda.log" 2>&1 || echo "the job did not finish: see $OUT/dive_cuda.log"
    job "$OUT/dive_cuda" cuda
fi

say "five minutes of RecGS on a generated survey, on the GPU"
if [ -z "$SURVEY" ] || [ ! -d "$SURVEY/sparse" ]; then
    echo "skipped: no generated survey (SURVEY=out/bench/surveys/rows-72, carried to this machine)"
elif fits 320; then
    rm -rf "$OUT/survey_cuda"
    timeout 320 "$PY" -m recgs_addon train "$SURVEY" --out "$OUT/survey_cuda" --mode recgs --max-minutes 5 \
        --device cuda > "$OUT/survey_cuda.log" 2>&1 || echo "the job did not finish: see $OUT/survey_cuda.log"
    job "$OUT/survey_cuda" "cuda, $(basename "$SURVEY")"
fi

say "the step on the GPU's plain-PyTorch path"
fits 60 && timeout 60 "$PY" benchmarks/bench_threads.py "$SAMPLE" --gaussians 50000,500000 --steps 6 --densifying \
    --device cuda 2>&1 | tee "$OUT/steps_cuda.txt" | tail -n 6

say "one render on the GPU at 500k Gaussians: the plain-PyTorch path's batching (tile size : log2 pairs a chunk) and Triton's kernels"
fits 45 && timeout 45 "$PY" benchmarks/bench_render_batch.py "$SAMPLE" --gaussians 500000 --device cuda \
    --settings 16:22,triton --repeats 3 2>&1 | tee "$OUT/render_batch_500k.txt" | tail -n 4

say "the README's job, two minutes, on two CPU cores"
if fits 135; then
    rm -rf "$OUT/dive_cpu2"
    OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2 $PIN timeout 135 "$PY" -m recgs_addon train data/dive \
        --out "$OUT/dive_cpu2" --mode recgs --max-minutes 2 --device cpu > "$OUT/dive_cpu2.log" 2>&1 \
        || echo "the job did not finish: see $OUT/dive_cpu2.log"
    job "$OUT/dive_cpu2" "cpu, 2 cores"
fi
say "done in $((SECONDS - START)) s: $OUT"
