"""The user-facing paths on every device the machine has (the ``device`` fixture: CPU, plus CUDA where present).

* A PSF map of the bundled hybrid lens (default stop edge, with and without the DOE-field cache) on the device
  equals the CPU map (float64; CUDA's FFTs differ from MKL's in the last bits, hence 1e-10 of the peak).
* A tiny end-to-end training run (pre-stage, stage 1 with the replay and the quantised DOE, stage 2, evaluation,
  export) runs on the device with its modules there. On the CPU this is ``tests/test_training_e2e.py``.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.imaging import DOEFieldCache, psf_map

WAVELENGTHS = (0.53,)


@pytest.fixture(scope="module")
def cpu_map():
    hl = load_hybrid("hybrid_asphere")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return psf_map(hl, (1, 2), wavelengths=WAVELENGTHS, ks=32)


def test_psf_map_on_the_device_matches_cpu(device, cpu_map):
    hl = load_hybrid("hybrid_asphere").to(device)
    cache = DOEFieldCache(max_bytes=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        maps = [psf_map(hl, (1, 2), wavelengths=WAVELENGTHS, ks=32, cache=c) for c in (None, cache, cache)]
    for m in maps:
        assert m.psf.device.type == torch.device(device).type and m.psf.dtype == torch.float64
        err = float((m.psf.cpu() - cpu_map.psf).abs().max())
        assert err <= 1e-10 * float(cpu_map.psf.max()), err
        assert torch.isfinite(m.psf).all()


def test_training_runs_on_the_device(device, tiny_lens_file, tmp_path):
    if device == "cpu":
        pytest.skip("the CPU run is tests/test_training_e2e.py")
    from raywave.training.config import apply_overrides
    from raywave.training.trainer import Trainer
    from test_training_e2e import _cfg

    cfg = apply_overrides(_cfg(tmp_path, tiny_lens_file), [f"device={device}"])
    tr = Trainer(cfg, tmp_path / "run", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr.run()
        metrics = tr.evaluate()
        folder = tr.export()
    assert all(p.device.type == device for p in tr.net.parameters())
    assert all(p.device.type == device for p in tr.hl.parameters())
    scores = list(_numbers(metrics))
    assert scores and all(math.isfinite(v) for v in scores)
    assert (folder / "masks" / "masks.gds").exists()


def _numbers(tree):
    """The numbers in a nested dict/list (the evaluation's metrics)."""
    if isinstance(tree, dict):
        for v in tree.values():
            yield from _numbers(v)
    elif isinstance(tree, (list, tuple)):
        for v in tree:
            yield from _numbers(v)
    elif isinstance(tree, (int, float)):
        yield float(tree)
