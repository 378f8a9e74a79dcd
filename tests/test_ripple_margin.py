"""Issue 47 (h47): the exit-pupil stop edge's ripple band on the DOE plane (``RIPPLE_ZONES``: 5 Fresnel zones outside
the geometric shadow) holds edge light that reaches the PSF crop, so it cannot be narrowed for speed.

The edge wave leaves the stop rim's image ``E`` (``z_E``) on straight lines: a ripple ``s`` mm outside the shadow on
the DOE plane (``z_d``) lands ``s·(z_s − z_E)/(z_d − z_E)`` mm beyond the marginal ray's landing on the sensor
(``z_s``), and one Fresnel zone on the DOE plane, ``sqrt(λ/n · (z_d − z_E)(z_s − z_d)/(z_s − z_E))``, lands
``sqrt(λ/n · (z_s − z_d)(z_s − z_E)/(z_d − z_E))`` beyond it: 47 µm on the bundled asphere (0.53 µm, z_E 1.59,
z_d 8.30, z_s 11.22 mm). A ks 32 crop of 3 µm pixels reaches 1.2 zones out, ks 64 2.2 zones, plus the marginal
rays' own landing offset (astigmatism off axis: 134 µm, ~3 zones, at 17.5°), plus the band's 2-zone roll-off: the
5 zones are what the crop needs (docs/ray-wave.md, "The ripple band's width and the cost";
benchmarks/results/ripple_margin_2026-11-29_h47.json).
"""

import math

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.models import huygens_psf

WL, PS, KS = 0.53, 3e-3, 32

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")


def _band(monkeypatch, zones: float):
    """The exit-pupil edge's outer ripple band at ``zones`` Fresnel zones (the inner tail at its default)."""
    import raywave.hybrid.coherent.accurate as ac
    import raywave.hybrid.coherent.stop_edge as se

    full = se.RIPPLE_ZONES
    monkeypatch.setattr(se, "RIPPLE_ZONES", float(zones))  # the band fixed (no reach rule: MAX at the same)
    monkeypatch.setattr(se, "MAX_RIPPLE_ZONES", float(zones))
    monkeypatch.setattr(se, "RIPPLE_MIN_ZONES", float(zones))  # (no narrowing where the reach is short)
    inner = se.INNER_TAIL * math.sqrt(2.0) * full
    monkeypatch.setattr(ac, "_nu_inner", lambda _z: inner)
    monkeypatch.setattr(se, "_nu_inner", lambda _z: inner)


@pytest.mark.slow
def test_the_ripple_band_holds_edge_light_that_reaches_the_crop(monkeypatch):
    """The bundled asphere at 14° (6 mm blank DOE of 1 µm pixels at 0.7 mm, ks 32, 3 µm pixels, λ 0.53 µm), against
    the Huygens exit-pupil PSF (independent of the DOE-plane construction; ``n_pupil="auto"``: 144, its last level's
    change 1.4e-9):
    2.5e-4 rel L1 with the 5-zone band, 2.2e-3 with 3 zones (measured 2026-11-29 on the 22 references: 3 zones is
    9× worse here, 13× on the 50 mm singlet at 0.7 field). Run at 5 and 3 zones: the narrower band must be clearly
    worse (the ripples between 3 and 5 zones land in the crop), the default within 5e-4."""
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    fld = (0.0, 14.0)
    errs = {}
    ref = None
    for zones in (5.0, 3.0):
        with monkeypatch.context() as m:
            _band(m, zones)
            hl = HybridLens(lens, BlankDOE(6000, 1e-3), 0.7, sensor_pitch=PS)
            with torch.no_grad():
                r = hl.psf_result(fld, WL, ks=KS)
        if ref is None:
            center = tuple(float(c) for c in r.center[0, 0])
            ref = huygens_psf(lens, fld, WL, ks=KS, pitch=PS, center=center, n_pupil="auto",
                              max_n_pupil=432, sensor_z=float(hl.sensor_z())).psf.to(torch.float64).reshape(KS, KS)
            ref = ref / ref.sum()
        errs[zones] = float((r.psf[0, 0] - ref).abs().sum())
    assert errs[5.0] < 5e-4
    assert errs[3.0] > 4 * errs[5.0]
