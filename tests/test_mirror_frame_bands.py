"""Issue 47: a mirror image propagated in its source's frame (raywave.hybrid.mirror.FrameBands): the window-to-window
propagation commutes with the mirror, the Nyquist line's mirror being the +Nyquist frequency; a map's mirror images
read their source's transfer function (evaluated once a family) and give the PSFs of their own frames to rounding."""

import warnings

import pytest
import torch

import raywave.hybrid.hybrid_lens as hybrid_lens
from raywave.assembly.build import load_hybrid
from raywave.doe import PixelDOE
from raywave.hybrid.mirror import FrameBands, _frame_freqs, _framed_source, _mirrored_lines
from raywave.imaging import psf_map
from raywave.lens.build import bundled_lens_path
from raywave.wave.propagation.batch import (BatchTransfer, OwnBand, WindowBatch, WindowSource, batch_transfer,
                                            propagate_batch)
from raywave.wave.propagation.kernels import BandView, SharedBand, TransferBand, transfer_params
from raywave.wave.propagation.transfer import _geometry

WAVELENGTHS = (0.66, 0.53, 0.47)


def _framed_transfer(wb: WindowBatch, t: BatchTransfer, flips: tuple) -> BatchTransfer:
    """``t`` (one source) in the source's mirrored frame: its lines mirrored, its own parameters mirrored, the
    Nyquist line at +Nyquist (what FrameBands.framed does for a family's member)."""
    (my, mx), (px, py) = t.size, t.pitch
    part = t.parts[0]
    cols, rows = _mirrored_lines(part.cols, mx, flips[0]), _mirrored_lines(part.rows, my, flips[1])
    fx = _frame_freqs(torch.fft.fftfreq(mx, d=px, dtype=torch.float64), cols, flips[0])
    fy = _frame_freqs(torch.fft.fftfreq(my, d=py, dtype=torch.float64), rows, flips[1])
    p = transfer_params(_geometry(_framed_source(wb.sources[0], flips, wb), wb.out_shape, wb.pitch, wb.margin,
                                  wb.guard))
    band = OwnBand(torch.tensor(rows), torch.tensor(cols), TransferBand(fx, fy, torch.tensor(p, dtype=torch.float64)))
    return BatchTransfer(t.size, t.rows, t.cols, None, None, t.wave, t.pitch, t.batch, (band,))


@pytest.mark.parametrize("flips", [(True, False), (False, True), (True, True)])
def test_propagation_in_the_mirrored_frame_equals_its_own(flips):
    """A source whose band holds the Nyquist line along each axis (a steep carrier; the FFT grid even): its
    envelope flipped, propagated with the mirrored geometry's transfer function and flipped back equals its own
    propagation to rounding (1e-13 of the peak); with the Nyquist line at −Nyquist instead (the line's index
    mirrored, not its frequency) it does not."""
    torch.manual_seed(0)
    src = WindowSource((90, 70), (-0.31, 0.12), (-0.52, 0.33), 0.5, 0.6, 1.0, (-0.35, 0.3))
    wb = WindowBatch((src,), (25, 25), 2e-3)
    t = batch_transfer(wb)
    my, mx = t.size
    assert my % 2 == 0 and mx % 2 == 0 and mx // 2 in t.parts[0].cols.tolist() and my // 2 in t.parts[0].rows.tolist()
    u = torch.randn(90, 70, dtype=torch.complex128)
    own = propagate_batch(wb.field(u[None]), wb.out_grids(), wb.distances(), transfer=t).envelope[0]
    dims = [d for d, on in ((-1, flips[0]), (-2, flips[1])) if on]
    framed = propagate_batch(wb.field(u.flip(dims)[None]), wb.out_grids(), wb.distances(),
                             transfer=_framed_transfer(wb, t, flips)).envelope[0].flip(dims)
    assert float((framed - own).abs().max()) < 1e-13 * float(own.abs().max())
    naive = _framed_transfer(wb, t, flips)
    v = naive.parts[0].values
    v.fx, v.fy = (torch.fft.fftfreq(m, d=2e-3, dtype=torch.float64)[naive.parts[0].cols if a == 0 else
                                                                     naive.parts[0].rows]
                  for a, m in ((0, mx), (1, my)))
    wrong = propagate_batch(wb.field(u.flip(dims)[None]), wb.out_grids(), wb.distances(),
                            transfer=naive).envelope[0].flip(dims)
    assert float((wrong - own).abs().max()) > 1e-6 * float(own.abs().max())


def test_band_view_reads_the_shared_evaluation():
    """A BandView's blocks are the shared array's lines at its positions (views of runs, gathers elsewhere) and
    equal a TransferBand on those lines."""
    fx = torch.linspace(-300.0, 300.0, 41, dtype=torch.float64)
    fy = torch.linspace(-250.0, 250.0, 33, dtype=torch.float64)
    p = torch.tensor([1886.79, 2.9, -200.0, 100.0, -0.05, 0.15, -0.4, 0.6, 0.08, -0.2, 0.6, 0.08], dtype=torch.float64)
    shared = SharedBand(fx, fy, p)
    cols, rows = [0, 1, 2, 3, 7, 8, 40], list(range(5, 30))
    view = BandView(shared, cols, rows)
    ref = TransferBand(fx[cols], fy[rows], p)
    scale = float(ref.full().abs().max())
    for c0, c1 in ((0, 4), (3, 7), (0, 7)):
        assert view.block(c0, c1).shape == (c1 - c0, 25)
        assert float((view.block(c0, c1) - ref.block(c0, c1)).abs().max()) <= 1e-14 * scale
    assert view.shape == (25, 7) and float((view.full() - ref.full()).abs().max()) <= 1e-14 * scale


def _maps(hl, n: int):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return psf_map(hl, (n, n), wavelengths=WAVELENGTHS, ks=32, progress=False).psf


class _Unshared(FrameBands):
    def frames(self, batch):
        return None


@pytest.mark.parametrize("edge,n", [("default", 2), ("doe", 2),
                                    pytest.param("default", 4, marks=pytest.mark.slow),
                                    pytest.param("doe", 4, marks=pytest.mark.slow)])
def test_map_with_shared_transfer_functions_matches_each_frame(edge, n, monkeypatch):
    """The bundled asphere's n×n×3 maps (every source one of a family of four mirror images): their PSFs with the
    families' transfer functions shared (one evaluation a family) equal those propagated each in its own frame to
    the rounding of the images' window positions (≤ 9e-16 mm), and with a random pixel DOE phase (each image's
    phasors flipped into the frame) too: bound 5e-12 relative L1 (ks 32; measured on the 4×4×3 maps, blank / pixel
    DOE: default edge 9.6e-13 / 1.34e-12, DOE-plane edge 3.2e-13 / 1.24e-12, max |ΔPSF| ≤ 1.9e-13 of the peak;
    ks 64, blank: 2.5e-13 / 1.1e-13)."""
    with torch.no_grad():
        hl = load_hybrid(bundled_lens_path("hybrid_asphere"), **({} if edge == "default" else {"stop_edge": "doe"}))
        torch.manual_seed(1)
        rough = hl.with_doe(PixelDOE(torch.rand(*hl.doe.shape, dtype=torch.float64) * 6.0, hl.doe.pitch,
                                     aperture=hl.doe.aperture))
        for lens in (hl, rough):
            evals = []
            seen = SharedBand.columns

            def counted(self):
                evals.append(self._t is None)
                return seen(self)

            monkeypatch.setattr(SharedBand, "columns", counted)
            new = _maps(lens, n)
            monkeypatch.setattr(SharedBand, "columns", seen)
            assert sum(evals) == n * n * 3 // 4 and len(evals) > sum(evals)  # one evaluation a family
            monkeypatch.setattr(hybrid_lens, "FrameBands", _Unshared)
            old = _maps(lens, n)
            monkeypatch.undo()
            rel = ((new - old).abs().sum((-2, -1)) / old.abs().sum((-2, -1))).max()
            print(f"{edge} {n}x{n}x3 {'pixel DOE' if lens is rough else 'blank DOE'}: max rel L1 {float(rel):.3g}, "
                  f"max |dPSF| / peak {float((new - old).abs().max() / old.abs().max()):.3g}")
            assert float(rel) < 5e-12
