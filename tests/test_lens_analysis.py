"""Geometric analysis against closed forms: the geometric PSF and the field curvature of a defocused perfect
lens (issue 17: both were untested)."""

import pytest
import torch

from raywave.lens import analysis
from raywave.lens.build import ideal_lens

F, FNUM, DZ = 50.0, 5.0, 1.0   # focal length, f-number, sensor behind the focus (mm)


def test_geometric_psf_of_a_defocused_perfect_lens_is_a_uniform_disk(device):
    """A perfect lens focuses a distant on-axis point to a point; a sensor DZ behind the focus sees a uniform
    disk of radius R = DZ·D/(2F) (similar triangles), whose second moment is <x² + y²> = R²/2."""
    lens = ideal_lens(F, f_number=FNUM, sensor_distance=F + DZ).to(device)
    R = DZ / (2 * FNUM)  # 0.1 mm
    pixel, size = 0.01, 32
    psf = analysis.geometric_psf(lens, (0.0, 0.0), n_rays=201, size=size, pixel=pixel).detach()
    assert psf.device.type == device and psf.shape == (size, size)
    assert float(psf.sum()) == pytest.approx(1.0, abs=1e-12)
    c = (torch.arange(size, dtype=torch.float64, device=device) - size / 2 + 0.5) * pixel  # pixel centres
    r2 = (psf * (c[None, :] ** 2 + c[:, None] ** 2)).sum()
    # bilinear binning adds the triangle kernel's variance pixel²/6 per axis
    assert float(r2) == pytest.approx(R ** 2 / 2 + 2 * pixel ** 2 / 6, rel=0.01)
    # uniform: the inner pixels are flat, nothing lands beyond the rim
    r = torch.sqrt(c[None, :] ** 2 + c[:, None] ** 2)
    inner = psf[r < 0.7 * R]
    assert float(inner.std() / inner.mean()) < 0.05
    assert float(psf[r > R + 1.5 * pixel].sum()) == 0.0


@pytest.mark.parametrize("fields", [[0.0, 5.0, 10.0]])
def test_field_curvature_of_a_defocused_perfect_lens(fields, device):
    """A perfect (paraxial-surface) lens images a distant point at any angle onto the focal plane, so both the
    tangential and the sagittal focus lie DZ in front of a sensor DZ behind it, at every field: a flat field."""
    lens = ideal_lens(F, f_number=FNUM, sensor_distance=F + DZ, fields=fields).to(device)
    tan, sag = analysis.field_curvature(lens)
    assert tan.shape == sag.shape == (len(fields),)
    assert torch.allclose(tan, torch.full_like(tan, -DZ), atol=1e-9, rtol=0)
    assert torch.allclose(sag, torch.full_like(sag, -DZ), atol=1e-9, rtol=0)

