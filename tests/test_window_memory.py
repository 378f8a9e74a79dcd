"""The field window's memory estimate (issue 47, class A): bytes per simulation sample by construction path and by
whether autograd keeps a graph (raywave.hybrid.coherent.geometry.WINDOW_BYTES, measured by
benchmarks/window_memory.py), and a PSF's measured peak memory within what the estimate admits."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from raywave.hybrid.coherent.geometry import WINDOW_BYTES, check_window_memory, window_bytes_per_sample
from raywave.utils.errors import MEMORY_LIMIT_ENV, MemoryLimitError

ROOT = Path(__file__).resolve().parents[1]


def test_the_estimate_follows_the_path_and_the_graph(monkeypatch):
    """A graph costs more than none on every path; None reads the grad mode; the exact construction's carry costs
    the most; the refusal names the window; an unknown path is a ValueError naming the paths."""
    for step in ("fresnel", "cut", "asm", "fallback"):
        assert WINDOW_BYTES[(step, True)] > WINDOW_BYTES[(step, False)]
        with torch.no_grad():
            assert window_bytes_per_sample(step) == WINDOW_BYTES[(step, False)]
        with torch.enable_grad():
            assert window_bytes_per_sample(step) == WINDOW_BYTES[(step, True)]
    assert max(WINDOW_BYTES.values()) == WINDOW_BYTES[("asm", True)]
    n = 1000  # 10⁶ samples: admitted without a graph at the Fresnel step's bytes, refused with one
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(n * n * WINDOW_BYTES[("fresnel", False)]))
    check_window_memory(n, n, 1e-3, step="fresnel", graph=False)
    with pytest.raises(MemoryLimitError, match=r"the 1000×1000-sample DOE-plane field"):
        check_window_memory(n, n, 1e-3, step="fresnel", graph=True)
    with pytest.raises(ValueError, match="'fresnel', 'cut', 'asm' or 'fallback'"):
        window_bytes_per_sample("field")


# one process, its peak resident memory (VmHWM, reset before each PSF) above its memory before the PSF, against
# the samples of the largest window the PSF's checks saw; eager kernels (RAYWAVE_COMPILE=0: no compile time)
CHILD = r"""
import json, sys, warnings
import torch
torch.set_num_threads(1)
import raywave.hybrid.coherent.geometry as g
from raywave.doe import BlankDOE
from raywave.doe.params import Binary2DOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, load_lens

def status(key):
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) * 1024 for line in fh if line.startswith(key + ":"))

seen, orig = [], g.check_window_memory
def spy(ny, nx, p, *a, **kw):
    seen.append(int(ny) * int(nx))
    return orig(ny, nx, p, *a, **kw)
for mod in list(sys.modules.values()):
    if mod is not None and getattr(mod, "check_window_memory", None) is orig:
        mod.check_window_memory = spy
lens = load_lens(bundled_lens_path("asphere_hk51"))
out = []  # a 6 mm DOE 0.7 mm behind the lens; on axis a 2510² window (0.5 µm pixels), the cut edge's 2375² (0.35 µm)
for graph, step, pitch in ((False, "fresnel", 5e-4), (False, "cut", 3.5e-4), (True, "fresnel", 5e-4)):
    n = round(6.0 / pitch)
    doe = Binary2DOE(torch.zeros(2, dtype=torch.float64), 3.0, (n, n), pitch) if graph else BlankDOE(n, pitch)
    kw = dict(edge_step="fresnel") if step == "fresnel" else dict(stop_edge="doe")
    hl = HybridLens(lens, doe, 0.7, sensor_pitch=3e-3, **kw)
    seen.clear()
    base = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    with warnings.catch_warnings(), torch.set_grad_enabled(graph):
        warnings.simplefilter("ignore")
        r = hl.psf_result((0.0, 0.0), 0.53, ks=32)
        if graph:
            (r.psf * torch.rand_like(r.psf)).sum().backward()
    out.append(dict(graph=graph, step=step, samples=max(seen), extra=status("VmHWM") - base))
    del r, hl, doe
print(json.dumps(out))
"""


#: what a PSF holds whatever its window (its rays and traces; with gradients their graph): benchmarks/window_memory.py's
#: intercepts are 0.02 – 0.41 GiB; the estimate's margin holds them on large windows, not on 6·10⁶ samples
FIXED = 128 * 2**20


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="needs Linux's peak-RSS reset")
def test_a_psf_stays_within_what_its_window_estimate_admits():
    """The whole extra peak of a PSF (the window, the rays, the propagation to the sensor, and with gradients the
    backward) is below its largest window's samples × the estimate's bytes plus :data:`FIXED`, without a graph (the
    Fresnel step and the cut edge: 66 and 72 B a sample measured, within the bytes alone) and with one (the lens's
    parameters and a BINARY_2 DOE's coefficients requiring grad: 162 B a sample with the fixed part)."""
    env = {**os.environ, "RAYWAVE_COMPILE": "0", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop(MEMORY_LIMIT_ENV, None)
    res = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    rows = json.loads(res.stdout.strip().splitlines()[-1])
    for row in rows:
        assert row["samples"] > 5e6, row  # a window large enough to carry the peak
        est = row["samples"] * WINDOW_BYTES[(row["step"], row["graph"])] + FIXED
        assert row["extra"] < est, (row, est)
