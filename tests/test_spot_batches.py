"""Issue 45: a ray aimed at the stop's rim is treated the same whatever else is in the batch (the rim rule of
raywave.rays.pupil), so a field's RMS spot does not depend on the other fields of the call; a fully vignetted field
is NaN (never 0); and the Cooke triplet's RMS spots agree with optiland's on the same (hexapolar) sampling."""

import itertools
import math
import warnings

import pytest
import torch

from raywave.lens import analysis
from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.rays import pupil


def _rms(lens, fields, pattern=("hexapolar", 6)):
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        return analysis.rms_spot_radius(lens, fields, lens.wavelengths, pupil=pattern)


@pytest.mark.parametrize("pattern", [("hexapolar", 6), ("grid", 16)])
def test_rms_spot_independent_of_batch(cooke, pattern):
    """Every field alone equals the same field in every batch of the others (incl. the 30° field that used to flip
    the on-axis rim rays, issue 45), to 1e-12 mm."""
    others = [0.0, 7.0, 14.0, 20.0, 30.0]
    alone = {f: _rms(cooke, [f], pattern)[0] for f in others}
    for batch in [*itertools.combinations(others, 2), (0.0, 20.0, 30.0), tuple(others)]:
        got = _rms(cooke, list(batch), pattern)
        for i, f in enumerate(batch):
            assert torch.allclose(got[i], alone[f], rtol=0, atol=1e-12), (batch, f)


def test_rim_rays_all_pass_on_axis(cooke):
    """On axis every hexapolar ray, the rim ring included, reaches the image (the stop is the only aperture)."""
    with torch.no_grad():
        out = cooke.trace_to_image(point_source_rays(cooke, [[0.0, 0.0], [0.0, 30.0]], cooke.wavelengths,
                                                     pupil=("hexapolar", 6)))
    assert bool(out.valid[0].all())


def test_inset_rim_rule():
    px, py = pupil.hexapolar(3)
    qx, qy = pupil.inset_rim(px, py)
    r = torch.sqrt(qx**2 + qy**2)
    rim = torch.sqrt(px**2 + py**2) > 0.99
    assert torch.allclose(r[rim], torch.full_like(r[rim], pupil.RIM_INSET), rtol=0, atol=1e-15)
    assert torch.equal(qx[~rim], px[~rim]) and torch.equal(qy[~rim], py[~rim])
    # idempotent, bit for bit (the ray-wave footprint's samples are already inset), and outside the rim untouched
    sx, sy = pupil.inset_rim(qx, qy)
    assert torch.equal(sx, qx) and torch.equal(sy, qy)
    far = torch.tensor([1.01, 0.0], dtype=torch.float64), torch.tensor([0.0, 0.0], dtype=torch.float64)
    assert torch.equal(pupil.inset_rim(*far)[0], far[0])


def test_vignetted_field_is_nan_not_zero(cooke):
    with pytest.warns(VignettingWarning):
        rms = analysis.rms_spot_radius(cooke, [0.0, 40.0])
    assert bool(torch.isfinite(rms[0]).all()) and bool(torch.isnan(rms[1]).all())


def test_cooke_rms_spots_match_optiland(cooke):
    """Monochromatic RMS spot radius about the spot's centroid, hexapolar 6 rings (127 rays), fully aimed rays, at
    0 / 14 / 20°: optiland's to 1e-6 relative."""
    pytest.importorskip("optiland")
    from optiland.analysis import SpotDiagram

    from optiland_bridge import optiland_lens

    wl = cooke.primary_wavelength
    fields = [0.0, 14.0, 20.0]
    o = optiland_lens(cooke, wl, fields)
    sd = SpotDiagram(o, fields="all", wavelengths=[wl], num_rings=6, distribution="hexapolar", reference="centroid")
    theirs = [float(r[0]) for r in sd.rms_spot_radius()]
    with torch.no_grad():
        ours = analysis.rms_spot_radius(cooke, fields, [wl], pupil=("hexapolar", 6))[:, 0].tolist()
    assert not any(math.isnan(v) for v in ours)
    assert ours == pytest.approx(theirs, rel=1e-6)
