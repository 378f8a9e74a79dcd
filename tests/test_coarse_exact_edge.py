"""The exact stop-edge construction on a coarser lattice (issue 46's cost; raywave.hybrid.coherent.exit_pupil
``asm_coarsening``, ``CoarseLattice``): the field built and propagated m× coarser than the DOE's grid where the wave's
own bandwidth allows, then Fourier-upsampled to the DOE pitch (:func:`raywave.wave.field.fourier_upsample`).

Checked against independent references: the upsampling against analytic band-limited signals, and the coarse
construction's PSF against the wave-optics truth of tests/wave_truth.py (two ideal lenses, no rays, no exit pupil).
"""

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from wave_truth import two_ideal_lenses_psf  # noqa: E402

import raywave.hybrid.coherent.exit_pupil as EP  # noqa: E402
from raywave.doe import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.wave.field import fourier_upsample  # noqa: E402

F64 = torch.float64


@pytest.mark.parametrize("ny,nx,m", [(9, 12, 3), (10, 7, 2), (16, 16, 4), (5, 6, 1)])
def test_fourier_upsampling_interpolates_a_band_limited_field_exactly(ny, nx, m):
    """A periodic field of a few plane waves within the grid's band (odd and even sizes: an even size's Nyquist
    term is split between ±N/2) sampled m× finer: the analytic values at every fine sample, to rounding."""
    def field(y, x):
        return (torch.exp(2j * math.pi * (x / nx + 2 * y / ny)) + 0.5 * torch.exp(-2j * math.pi * (3 * x / nx - y / ny))
                + 0.2 + 0.3 * torch.cos(2 * math.pi * (nx // 2) * x / nx))
    y, x = torch.arange(ny, dtype=F64)[:, None], torch.arange(nx, dtype=F64)[None, :]
    up = fourier_upsample(field(y, x), m)
    yf, xf = torch.arange(m * ny, dtype=F64)[:, None] / m, torch.arange(m * nx, dtype=F64)[None, :] / m
    assert up.shape == (m * ny, m * nx)
    assert float((up - field(yf, xf)).abs().max()) < 1e-13


def test_the_lattice_follows_the_waves_bandwidth():
    """m = floor(½·λ/(2nΔ)/p) from the rim rays' largest direction-cosine difference Δ from the chief ray's (NA 0.05
    at 0.55 µm: 2.7 µm, m = 2 on a 1 µm grid), capped, and 1 without rim rays."""
    from raywave.hybrid.coherent.stop_edge import RimImages

    class Chief:
        d = torch.tensor([0.0, 0.0, 1.0], dtype=F64)

    th = torch.arange(64, dtype=F64) * (2 * math.pi / 64)
    na = 0.05
    dirs = torch.stack([na * torch.cos(th), na * torch.sin(th), torch.full_like(th, math.sqrt(1 - na * na))], 1)
    rim = RimImages(th, torch.zeros(64, dtype=F64), torch.zeros(64, 3, dtype=F64), torch.zeros(64, dtype=F64), dirs)
    assert EP.asm_coarsening(rim, Chief, 0.55, 1.0, 1e-3) == 2
    assert EP.asm_coarsening(rim, Chief, 0.55, 1.0, 0.25e-3) == EP.MAX_ASM_COARSENING
    assert EP.asm_coarsening(rim, Chief, 0.55, 1.0, 3e-3) == 1
    assert EP.asm_coarsening(None, Chief, 0.55, 1.0, 1e-3) == 1
    # the PSF crop's far tail: the edge waves landing 0.2 mm out from 10 mm turn by a further 0.02 (m = 1.96 µm / p)
    assert EP.asm_coarsening(rim, Chief, 0.55, 1.0, 1e-3, tail=0.02) == 1
    assert EP.asm_coarsening(rim, Chief, 0.55, 1.0, 0.25e-3, tail=0.02) == 7


@pytest.mark.slow  # ~15 s
@pytest.mark.parametrize("theta", [0.0, 2.0])
def test_the_coarse_exact_edge_matches_the_two_lens_truth(theta):
    """The two-ideal-lens system of tests/test_ideal_lens_truth.py (F/9.76: its 7.2 mm exit-pupil beam needs a
    12 GiB field on the DOE's 1 µm grid, refused before; m = 2 here) with ``edge_step="asm"``: measured 1.9e-4 /
    1.8e-4 rel L1 from the wave-optics truth at 0° / 2° (the engine's other edges: 2.8e-4)."""
    import test_ideal_lens_truth as T

    lens = T.two_lens_engine_lens(theta)
    hl = HybridLens(lens, BlankDOE(2000, 1e-3), 5.0, sensor_pitch=T.PIXEL, edge_step="asm")
    with torch.no_grad():
        r = hl.psf_result((0.0, theta), T.WL, ks=T.KS)
    c = tuple(float(v) for v in r.center[0, 0])
    truth = two_ideal_lenses_psf(T.SYSTEM, (0.0, theta), T.WL, c, T.KS, T.PIXEL, pitch=1e-3)
    assert T.l1(r.psf[0, 0], truth) < 3e-4
