"""The PSF does not depend on the FFT size of its window propagation (issue 43): a larger FFT grid than the smallest
one that keeps the circular convolution of the rolled-off kernel linear changes a PSF only by the kernel's tails
beyond its roll-off, which wrap around at the own size. Measured (benchmarks/fft_size_convergence.py,
benchmarks/results/fft_size_convergence_2026-11-29_xv_h43f.json), at ×1.25, ×1.5, ×2 (×4 on the asphere), the same at
every larger size: ≤ 6.4e-9 relative L1 on the four real lenses of tests/test_stop_edge_real_lenses.py at 0 / 0.7 /
1.0 field (the F/1.3 asphere on axis; the Cooke triplet on axis 1.06e-10, ≤ 6e-10 at its three wavelengths at full
field) and ≤ 2.8e-12 on the bundled asphere at 0–17.5°, while each PSF's error against its converged reference (6e-5
… 8e-4) moves by ≤ 2.2e-9 (that reference's own convergence: 1.9e-9). So a batch may run its sources on one common
FFT size (:data:`raywave.hybrid.batched.COMMON_FFT`). Fields the grid does not resolve (a SamplingWarning) are the
exception: their band covers the whole FFT grid and their PSFs move by up to 1e-2 (while 0.6–0.99 from the
reference)."""

import warnings

import torch

import raywave.hybrid.batched as batched
import raywave.hybrid.hybrid_lens as hybrid_lens
import raywave.wave.propagation.transfer as transfer
from raywave.assembly.build import load_hybrid
from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, load_lens

#: the largest change measured from the own FFT size (the Cooke triplet on axis, 1.06e-10), with room for rounding
BOUND = 1e-9
_PROPAGATE_GROUP = hybrid_lens.propagate_group


def _rel(a, b):
    return (a - b).abs().sum((-2, -1)) / b.abs().sum((-2, -1))


def test_a_strongly_aberrated_psf_is_converged_in_the_fft_size(monkeypatch):
    """The Cooke triplet on axis (the default edge, its default DOE plane: a 2235² window, own FFT 2560²) on a 1.25×
    larger FFT grid (3200²): 1.06e-10 relative L1 (the commit message of ded5369 had 2e-3)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid("cooke_triplet", fields=[[0.0, 0.0]], field_type="angle")
        wl = hl.lens.primary_wavelength
        with torch.no_grad():
            own = hl.psf((0.0, 0.0), wl, ks=32)
            monkeypatch.setattr(transfer, "FFT_SIZE_SCALE", 1.25)
            larger = hl.psf((0.0, 0.0), wl, ks=32)
    assert float(_rel(larger, own).max()) < BOUND


def test_the_fft_scale_hook_makes_the_size_larger_and_leaves_it_alone_at_one(monkeypatch):
    from raywave.wave.propagation.transfer import WindowSource, _geometry

    src = WindowSource((300, 280), (0.0, 0.0), (0.1, 0.05), 0.55, 2.0)
    own = _geometry(src, (41, 41), 1e-3, 0.5, 2.0).size
    monkeypatch.setattr(transfer, "FFT_SIZE_SCALE", 1.5)
    big = _geometry(src, (41, 41), 1e-3, 0.5, 2.0).size
    assert all(b >= 1.5 * o for b, o in zip(big, own))


def _asphere():
    """The bundled asphere's lens with a 6 mm blank DOE of 1 µm pixels at 0.7 mm (every source below resolved: no
    SamplingWarning; on a 4 µm grid the fields reach 2.4× the Nyquist limit and their PSFs are not converged in
    the FFT size: docs/ray-wave.md)."""
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    return HybridLens(lens, BlankDOE(6000, 1e-3), 0.7, sensor_pitch=3e-3)


#: field angles (deg) whose sources need different FFT sizes on their own: 7 batches of one FFT size each at
#: 0.53 / 0.47 µm (1215×1250 … 1350×1350), 2 with COMMON_FFT
FIELDS = [(0.0, 0.0), (0.0, 7.0), (5.0, 10.0), (0.0, 14.0)]


def _run(monkeypatch, common: bool, wavelengths=(0.53, 0.47)):
    monkeypatch.setattr(batched, "COMMON_FFT", common)
    sizes = []

    def spy(engine, batch, *a, **k):
        sizes.append(len(batch))
        return _PROPAGATE_GROUP(engine, batch, *a, **k)

    monkeypatch.setattr(hybrid_lens, "propagate_group", spy)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        psf = _asphere().psf(FIELDS, list(wavelengths), ks=24)
    return psf, sizes


def test_common_fft_batches_are_fewer_and_give_the_own_size_psfs(monkeypatch):
    own, own_batches = _run(monkeypatch, False)
    common, common_batches = _run(monkeypatch, True)
    assert sum(own_batches) == sum(common_batches) == len(FIELDS) * 2
    assert own.shape == (len(FIELDS), 2, 24, 24)
    assert len(common_batches) == 2 < len(own_batches)
    assert float(_rel(common, own).max()) < BOUND


def test_common_fft_batches_stay_within_the_byte_budget(monkeypatch):
    """A budget below one source's FFT grid: one source per batch (never an empty batch)."""
    monkeypatch.setattr(batched, "BATCH_BYTES", 1)
    _, sizes = _run(monkeypatch, True, (0.53,))
    assert sizes == [1] * len(FIELDS)



def test_an_accelerator_shares_fft_sizes_between_resolved_sources_only(monkeypatch):
    """On an accelerator (forced here on the CPU) the resolved sources of a wavelength share batches on a common FFT
    size (2 batches instead of 7, within the FFT-size bound of the own-size PSFs), while fields the pitch does not
    resolve (the Cooke triplet on a 4 µm grid: their bands reach the grid's highest frequencies, where a shared FFT
    size moves the PSF by 7.5e-5 of its 0.18 peak) keep their own sizes: their PSFs are the CPU's bit for bit."""
    own, own_batches = _run(monkeypatch, False)
    monkeypatch.setattr(batched, "_accelerator", lambda planned: bool(planned))
    shared, shared_batches = _run(monkeypatch, False)
    assert len(shared_batches) == 2 < len(own_batches) and sum(shared_batches) == len(FIELDS) * 2
    assert float(_rel(shared, own).max()) < BOUND
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        hl = load_hybrid(bundled_lens_path("cooke_triplet"), doe_pitch=4e-3, sensor_pitch=4e-3, stop_edge="doe")
        fields, wl = [(0.0, 0.0), (0.0, 14.0)], [hl.lens.primary_wavelength]
        accel = hl.psf(fields, wl, ks=24)
        monkeypatch.setattr(batched, "_resolved", lambda *a: True)
        forced = hl.psf(fields, wl, ks=24)
        monkeypatch.setattr(batched, "_accelerator", lambda planned: False)
        cpu = hl.psf(fields, wl, ks=24)
    assert torch.equal(accel, cpu)
    assert float((forced - cpu).abs().max()) > 1e-5  # sharing would have moved them
