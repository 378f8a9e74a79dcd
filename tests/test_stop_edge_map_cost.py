"""Issue 47's cost bar on maps: the default stop edge's extra work cut without moving its PSFs.

* a CPU batch's padded input stack stays under :data:`raywave.hybrid.batched.STACK_BYTES` (larger arrays are mapped
  fresh from the kernel on every allocation), with the PSFs of one unbounded batch bit for bit;
* the node grid reaches :data:`raywave.hybrid.coherent.accurate.NODE_MARGIN_ZONES` beyond the ripple band, and a
  construction whose grid cuts the band (:func:`~raywave.hybrid.coherent.accurate._band_at_grid_edge`) traces again
  with the wide margin: the PSF of the wide grid to the rounding of the rays' aiming.
"""

import warnings

import numpy as np
import pytest
import torch

import raywave.hybrid.batched as batched
import raywave.hybrid.coherent.accurate as acc
from raywave.assembly.build import load_hybrid
from raywave.imaging import psf_map
from raywave.lens.build import bundled_lens_path


@pytest.fixture(scope="module")
def default_lens():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


def _map(hl):
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return psf_map(hl, (2, 2), wavelengths=(0.53, 0.66), ks=32, progress=False).psf.numpy()


def test_cpu_batches_keep_their_input_stack_small_with_the_same_psfs(default_lens, monkeypatch):
    sizes = []
    real = batched.padded_stack

    def spy(envs, shape):
        sizes.append((len(envs), len(envs) * shape[0] * shape[1] * 16))
        return real(envs, shape)

    monkeypatch.setattr(batched, "padded_stack", spy)
    monkeypatch.setattr(batched, "STACK_BYTES", 2**23)  # 8 MiB: the bundled asphere's windows one or two a batch
    small = _map(default_lens)
    assert sizes and all(n == 1 or b <= 2**23 for n, b in sizes)
    few = len(sizes)
    sizes.clear()
    monkeypatch.setattr(batched, "STACK_BYTES", 2**62)  # unbounded: the batches of before
    whole = _map(default_lens)
    assert len(sizes) < few
    np.testing.assert_array_equal(small, whole)


def test_stack_cut_keeps_order_and_bounds():
    class Fd:
        def __init__(self, shape):
            self.grid = type("G", (), {"shape": shape})()

    class Pl:
        def __init__(self, shape):
            self.fd = Fd(shape)

    group = [Pl((1000, 1000)), Pl((900, 1100)), Pl((10, 10)), Pl((3000, 3000))]
    parts = batched._stack_cut(group)
    assert [p for part in parts for p in part] == group
    for part in parts:
        ny = max(p.fd.grid.shape[0] for p in part)
        nx = max(p.fd.grid.shape[1] for p in part)
        assert len(part) == 1 or len(part) * ny * nx * 16 <= batched.STACK_BYTES


def test_a_grid_that_cuts_the_band_traces_again_with_the_wide_margin(default_lens, monkeypatch):
    """A margin far too small (the band cut) falls back to the wide grid: the same PSF as the wide margin itself."""
    calls = []
    real = acc._band_at_grid_edge

    def spy(b, nd, maps):
        out = real(b, nd, maps)
        calls.append(out)
        return out

    monkeypatch.setattr(acc, "_band_at_grid_edge", spy)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        monkeypatch.setattr(acc, "NODE_MARGIN_ZONES", acc.NODE_MARGIN_WIDE)
        wide = default_lens.psf_result((0.0, 10.0), 0.53, ks=32).psf
        assert calls == [False]
        calls.clear()
        monkeypatch.setattr(acc, "NODE_MARGIN_ZONES", -4.0)  # the band cut by the grid
        cut = default_lens.psf_result((0.0, 10.0), 0.53, ks=32).psf
        assert calls == [True]  # the trimmed grid checked; the wide one traced without a check
        calls.clear()
        monkeypatch.setattr(acc, "NODE_MARGIN_ZONES", 0.0)  # the default: holds the band
        trimmed = default_lens.psf_result((0.0, 10.0), 0.53, ks=32).psf
        assert calls == [False]
    assert torch.equal(cut, wide)  # the wide grid's own construction
    # a smaller grid of the same nodes: the PSF to the rounding of the rays' aiming (another coarse start)
    assert float((trimmed - wide).abs().max()) <= 1e-12
