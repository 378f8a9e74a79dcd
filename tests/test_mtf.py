"""Issue 45: MTF. The Cooke triplet's FFT MTF against optiland's at the same pupil sampling (on axis and at full
field, three frequencies, within 0.01), the geometric MTF against optiland's, the FFT MTF of a perfect lens against
the analytic diffraction limit, the MTF of a sampled Gaussian against its closed form, and the ray-wave MTF of a
hybrid lens with a blank DOE against the pupil FFT of its lens (two independent wave models)."""

import math
import warnings

import numpy as np
import pytest
import torch

from raywave.cli.main import main
from raywave.lens.build import ideal_lens, resolve_lens_path
from raywave.lens.mtf import diffraction_limited_mtf, diffraction_mtf, geometric_mtf, psf_mtf
from raywave.lens.opd import square_pupil_grid

FREQS = [10.0, 25.0, 60.0]  # cycles/mm; the Cooke triplet's cutoff is 341


def test_fft_mtf_matches_optiland(cooke, optiland_cooke):
    """Same 64×64 pupil grid (optiland num_rays=64, grid 128): tangential and sagittal at 10 / 25 / 60 cycles/mm,
    0° and 20° (full field), within 0.01 (measured: < 1e-4; optiland's curve interpolated linearly as ours)."""
    from optiland.mtf import FFTMTF

    wl, n = cooke.primary_wavelength, 64
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theirs = FFTMTF(optiland_cooke, fields=[(0.0, 0.0), (0.0, 1.0)], wavelength=wl, num_rays=n, grid_size=2 * n)
    ours = diffraction_mtf(cooke, [0.0, 20.0], FREQS, n=n)
    for i in range(2):
        t = np.interp(FREQS, np.asarray(theirs.freq_tang[i]), np.asarray(theirs.mtf[i][0]))
        s = np.interp(FREQS, np.asarray(theirs.freq_sag[i]), np.asarray(theirs.mtf[i][1]))
        assert ours.tangential[i].numpy() == pytest.approx(t, abs=0.01)
        assert ours.sagittal[i].numpy() == pytest.approx(s, abs=0.01)
        assert ours.tangential[i].numpy() == pytest.approx(t, abs=1e-3)  # what was measured: the same pupil
    assert abs(float(ours.tangential[1, 1]) - float(ours.sagittal[1, 1])) > 0.05  # off axis T and S differ


def test_geometric_mtf_matches_optiland(cooke, optiland_cooke):
    """Same 64×64 uniform pupil, × the diffraction limit: within 0.01 (measured ≤ 1.3e-3; optiland bins the rays
    into 257 bins before its Fourier sum, raywave sums over the rays exactly)."""
    from optiland.mtf import GeometricMTF

    wl = cooke.primary_wavelength
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theirs = GeometricMTF(optiland_cooke, fields=[(0.0, 0.0), (0.0, 1.0)], wavelength=wl, num_rays=64,
                              max_freq=100.0, num_points=64)
    px, py = square_pupil_grid(64)
    keep = px * px + py * py <= 1
    nu = torch.tensor(np.asarray(theirs.freq))
    ours = geometric_mtf(cooke, [0.0, 20.0], nu, pupil=(px[keep], py[keep]))
    for i in range(2):
        assert ours.tangential[i].numpy() == pytest.approx(np.asarray(theirs.mtf[i][0]), abs=0.01)
        assert ours.sagittal[i].numpy() == pytest.approx(np.asarray(theirs.mtf[i][1]), abs=0.01)


def test_fft_mtf_of_a_perfect_lens_is_the_diffraction_limit():
    lens = ideal_lens(50.0, f_number=10.0, wavelengths=(0.55,))
    cut = 1.0 / (0.55e-3 * 10.0)
    nu = torch.tensor([0.1, 0.3, 0.5, 0.8]) * cut
    res = diffraction_mtf(lens, [0.0], nu, n=96)
    ref = diffraction_limited_mtf(nu.double(), cut)
    assert res.tangential[0] == pytest.approx(ref, abs=0.01)
    assert res.sagittal[0] == pytest.approx(ref, abs=0.01)


def test_psf_mtf_of_a_gaussian():
    pitch, sigma, ks = 1e-3, 4e-3, 129
    x = (torch.arange(ks, dtype=torch.float64) - ks // 2) * pitch
    g = torch.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * sigma**2))
    nu = torch.tensor([0.0, 20.0, 50.0, 100.0], dtype=torch.float64)
    t, s = psf_mtf(g, pitch, nu, pixel_divided=False)
    exact = torch.exp(-2 * math.pi**2 * sigma**2 * nu**2)
    assert t == pytest.approx(exact, abs=1e-9) and s == pytest.approx(exact, abs=1e-9)
    assert torch.isnan(psf_mtf(g, pitch, torch.tensor([600.0]))[0]).all()  # beyond the pixels' Nyquist limit


def test_raywave_mtf_agrees_with_the_pupil_fft_for_a_blank_doe():
    """hybrid_asphere's DOE is blank: the ray-wave PSF's MTF on axis equals the lens's pupil-FFT MTF within 0.01
    at 50 / 100 / 200 cycles/mm (measured ≤ 0.0025; independent wave models: angular spectrum from the DOE plane vs
    the pupil's autocorrelation)."""
    from raywave.assembly.build import load_hybrid
    from raywave.imaging.mtf import raywave_mtf

    hl = load_hybrid(resolve_lens_path("hybrid_asphere"))
    nu = [50.0, 100.0, 200.0]
    res, outside = raywave_mtf(hl, [0.0], nu, ks=128)
    ref = diffraction_mtf(hl.lens, [0.0], nu, n=128)
    assert float(outside[0]) < 0.02
    assert res.tangential[0] == pytest.approx(ref.tangential[0], abs=0.01)
    assert res.sagittal[0] == pytest.approx(ref.sagittal[0], abs=0.01)


def test_mtf_cli(tmp_path, capsys):
    out = tmp_path / "mtf.png"
    assert main(["mtf", "cooke_triplet", "--field", "0", "--field", "0,20", "--freq", "10,25,60", "--json",
                 "-o", str(out)]) == 0
    import json

    d = json.loads(capsys.readouterr().out)
    assert d["frequencies"] == FREQS and len(d["tangential"]) == 2 and out.stat().st_size > 10_000
    assert main(["mtf", "cooke_triplet", "--field", "40", "--freq", "10"]) == 0
    assert "vignetted" in capsys.readouterr().out
    assert main(["mtf", "cooke_triplet", "--field", "1,2,3"]) == 2
    assert "X,Y" in capsys.readouterr().err
    assert main(["mtf", "cooke_triplet", "--wavelength", "550"]) == 2
    assert "nm" in capsys.readouterr().err
