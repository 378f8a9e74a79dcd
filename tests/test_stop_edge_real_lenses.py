"""The exit-pupil stop edge on lenses a user loads (issue 19, must-show): ``raywave psf`` with
``stop_edge="exit_pupil"`` and the default blank DOE (the Nyquist pitch and, for a wide beam, the plane moved
towards focus but never beyond the first caustic: raywave.assembly.build.fit_doe_distance) on a Cooke triplet,
a double Gauss, a 50 mm N-BK7 singlet and an F/1.3 asphere (21 mm beam), each compared with the Huygens exit-pupil PSF
(raywave.models.exit_pupil, an independent diffraction model: it diffracts on the exit pupil's reference
sphere, no DOE plane, no angular spectrum) at 0, 0.7 and 1.0 of the lens's largest field, with no
SamplingWarning. Also the stop rim's images (raywave.hybrid.coherent.stop_rim_images) that the Fresnel step
runs from, against the paraxial exit pupil.

The PSF comparisons take minutes each (2048²-sample windows, a Huygens sum over 192² pupil cells): slow suite.
"""

import warnings
from pathlib import Path

import pytest
import torch

from raywave.assembly.build import MAX_DEFAULT_BEAM_PIXELS, load_hybrid
from raywave.hybrid import SamplingWarning
from raywave.hybrid.coherent import footprints, stop_rim_images
from raywave.lens.build import bundled_lens_path, load_lens, resolve_lens_path
from raywave.lens.paraxial import exit_pupil

DATA = Path(__file__).resolve().parent / "data"
LENSES = {
    "cooke_triplet": "cooke_triplet",
    "double_gauss": str(DATA / "zmx" / "double_gauss_ohara_cdgm_hoya.zmx"),
    "singlet_nbk7_50": str(DATA / "real_lenses" / "singlet_nbk7_50.zmx"),
    "asphere_f13": str(DATA / "real_lenses" / "asphere_f13_nsf11.zmx"),
}
#: largest rel L1 (sum |psf − huygens|, 0..2) accepted against the converged reference: issue 47's 1e-3, met since
#: the Fresnel step reads the rim images by trigonometric interpolation (2026-11-29, k47; measured values in
#: docs/ray-wave.md and benchmarks/results/stop_edge_references_2026-11-29_k47.json), on the double Gauss on axis and
#: at 0.7 field since the caustic fallback (p47)
TOL = 1e-3
#: this reference (its edge cut on the sphere through the paraxial exit pupil) is not the right one where the stop
#: rim's images lie far from that sphere: the double Gauss at full field, 7-32 mm from it, where the crop (the coma's
#: cusp, lit by the inner pupil only) is reached by edge waves whose phase depends on where the edge sits; there the
#: reference with its edge at the rim images is 2.22e-3 from this one (h47; docs/ray-wave.md "The double Gauss at full
#: field"). The default is within 1e-3 of that one (6.8e-4 since the ripple band's reach rule and the caustic
#: fallback's 1e-4 rad tolerance, h47b; tests/test_stop_edge_references.py) and 1.99e-3 from this one
TOL_NOT_YET = {("double_gauss", 1.0): 2.5e-3}
#: the reference's own error estimate above which a comparison gives no verdict (issue 47)
REF_TOL = 1e-4
#: (lens, field fraction) → Huygens pupil cells and sensor pitch (mm) where the defaults (192², the DOE pitch) do not
#: settle the comparison: the reference's 192² grid under-samples these off-axis wavefronts (it warns: 0.8–1.1 waves
#: between neighbouring cells) and most of the PSF falls outside a 32-pixel crop of the sub-micron DOE pitch. (Until
#: the default DOE plane stayed before the caustic, these four were also built beyond it: 0.17 rel L1 for the double
#: Gauss at full field; tests/test_caustic.py.)
SETTINGS = {("asphere_f13", 0.7): (384, 3e-3), ("asphere_f13", 1.0): (384, 3e-3), ("double_gauss", 0.7): (384, 3e-3),
            ("double_gauss", 1.0): (384, 3e-3),
            # 1.8e-2 against 192² cells (the reference warns: 0.51 waves), 9.1e-3 against 384² at 3 µm pixels
            ("singlet_nbk7_50", 1.0): (384, 3e-3)}

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")


def test_a_wide_fast_beam_gets_a_default_doe_plane_it_fits_on():
    """A beam too wide for the grid half way to the sensor: the default plane moves towards focus until every beam
    spans at most MAX_DEFAULT_BEAM_PIXELS (the 50 mm F/4 singlet, 0.7 × its 5° field and on axis), and says so;
    but never beyond the first caustic (tests/test_caustic.py): the F/1.3 asphere (21 mm pupil, 0.55 µm Nyquist
    pitch, ~20 000² pixels half way) would fit 2048² pixels 1 mm before focus, where its off-axis rays have
    crossed, so it stops before the crossing with a wider beam."""
    f = [[0.0, 3.5], [0.0, 0.0]]
    hl = load_hybrid(LENSES["singlet_nbk7_50"], fields=f, field_type="angle")
    info = hl.doe_info
    assert info["distance_rule"] == "beam_fit"
    last = float(hl.lens.surfaces[-1].thickness.detach())
    assert 0.5 * last < info["distance"] < last
    boxes = footprints(hl.lens, torch.tensor(f, dtype=torch.float64),
                       torch.tensor(hl.lens.wavelengths, dtype=torch.float64), None, hl.doe_z())
    widest = max(max(b[1] - b[0], b[3] - b[2]) for row in boxes for b in row if b is not None)
    assert widest / info["pitch"] <= MAX_DEFAULT_BEAM_PIXELS
    assert widest / info["pitch"] > 0.5 * MAX_DEFAULT_BEAM_PIXELS  # the nearest plane that fits, not any

    hl = load_hybrid(LENSES["asphere_f13"], fields=[[0.0, 1.0], [0.0, 0.0]], field_type="angle")
    info = hl.doe_info
    assert info["distance_rule"] == "before_caustic"
    last = float(hl.lens.surfaces[-1].thickness.detach())
    assert 0.5 * last < info["distance"] < info["caustic_distance"] < last
    # a beam that fits half way keeps that plane
    assert load_hybrid("singlet").doe_info["distance_rule"] == "half_way"


def test_stop_rim_images_on_axis_are_a_circle_at_the_paraxial_exit_pupil_for_a_small_stop():
    """On axis the rim's images lie on one plane (symmetry); for a small stop (pupil aberrations ∝ radius²) it
    is the paraxial exit pupil (raywave.lens.paraxial.exit_pupil, the stop imaged by the paraxial matrices)."""
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    wl = lens.primary_wavelength
    with torch.no_grad():
        _, z = stop_rim_images(lens, (0.0, 0.0), wl, None)
    assert float(z.max() - z.min()) < 2e-4  # mm, of a 6.7 mm pupil → DOE distance (first-order differences)
    zp = float(exit_pupil(lens, wl)[0].detach())
    big = float(z.mean())
    lens.surfaces[lens.stop_index].aperture.set_radius(0.1 * float(lens.surfaces[lens.stop_index].aperture.radius))
    with torch.no_grad():
        _, z_small = stop_rim_images(lens, (0.0, 0.0), wl, None)
    # pupil spherical aberration: 26 µm at the full stop, 1/100 of it at a tenth of the radius
    assert abs(float(z_small.mean()) - zp) < 0.05 * abs(big - zp)
    assert abs(big - zp) > 1e-3


def _case(name, frac, ks=32, n_pupil=192, sensor_pitch=None):
    """rel L1 of the default PSF from the converged Huygens reference (:func:`_reference`), and the reference's own
    error estimate."""
    from raywave.cli.psf_commands import compute_psf

    path = LENSES[name]
    lens = load_lens(resolve_lens_path(path))
    fld = (0.0, frac * max(float(f) for f in lens.fields))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SamplingWarning)
        out = compute_psf(path, field=fld, ks=ks, stop_edge="exit_pupil", sensor_pitch=sensor_pitch)
    hl = out["hybrid"]
    with torch.no_grad():
        ref = _reference(hl, fld, ks, out["center"], n_pupil)
    return float(abs(out["psf"] - ref.psf.numpy()).sum()), ref.error_estimate


def _reference(hl, fld, ks, center, n0):
    """The Huygens PSF converged in its pupil sampling: ``n_pupil="auto"`` with the polar quadrature (issue 47: its
    levels agree to ~1e-10 once the wavefront is resolved; ``n0`` is no longer needed), ``error_estimate`` its own
    error."""
    from raywave.models.exit_pupil import huygens_psf

    kw = dict(ks=ks, pitch=hl.sensor_pitch, center=tuple(float(c) for c in center), sensor_z=float(hl.sensor_z()))
    return huygens_psf(hl.lens, fld, hl.lens.primary_wavelength, n_pupil="auto", tol=1e-5, max_n_pupil=1024, **kw)


@pytest.mark.slow  # minutes per case (docs/ray-wave.md: "Real lenses")
@pytest.mark.parametrize("frac", [0.0, 0.7, 1.0])
@pytest.mark.parametrize("name", list(LENSES))
def test_exit_pupil_edge_psf_matches_huygens_on_real_lenses(name, frac):
    """Against the converged reference (issue 47; docs/ray-wave.md "Real lenses" and "The adaptive step" have the
    tables, the reference's estimate beside each figure): within 1e-3 (TOL) on the Cooke triplet, the 50 mm singlet
    and the F/1.3 asphere at every field, the double Gauss on axis and at 0.7 field (the caustic fallback); the double
    Gauss at full field within 2.5e-3 of this reference (TOL_NOT_YET: its edge on the paraxial sphere, far from the
    rim images there; within 1e-3 of the rim-image one, tests/test_stop_edge_references.py)."""
    n_pupil, pitch = SETTINGS.get((name, frac), (192, None))
    err, est = _case(name, frac, n_pupil=n_pupil, sensor_pitch=pitch)
    print(f"{name} at {frac} field: rel L1 {err:.3g} from the Huygens exit-pupil PSF (its own error ~{est:.2g})")
    if est > REF_TOL:  # e.g. the double Gauss at full field: ~1 wave between neighbouring cells at 288²
        pytest.xfail(f"the reference is not converged (its own error ~{est:.2g}): no verdict")
    assert err < TOL_NOT_YET.get((name, frac), TOL)


@pytest.mark.slow  # ~4 min: the Huygens reference at 192 and 288 pupil cells
def test_f13_asphere_on_axis_default_is_the_exact_doe_plane_cut():
    """Issue 47: the F/1.3 asphere on axis focuses a sphere (edge_aberration 2.6e-5 waves), its DOE is blank, so the
    default ("adaptive") cuts the edge on the DOE plane, the exit-pupil edge's exact result there. Measured against
    the Huygens PSF converged to 9.7e-5 (192/288 cells, Richardson): 1.2e-4 with intensity_upsample=8, 1.6e-3 with
    the default 4 (the 0.56 µm pixels are the DOE grid's Nyquist pitch: the pixel quadrature, not the edge); the
    Fresnel step 1.4e-3 (8) / 2.4e-3 (4)."""
    from raywave.hybrid.coherent.exit_pupil import adaptive_edge_step

    path = LENSES["asphere_f13"]
    hl = load_hybrid(path, fields=[[0.0, 0.0]], field_type="angle")
    wl = hl.lens.primary_wavelength
    assert adaptive_edge_step(hl.lens, hl.doe, (0.0, 0.0), wl, None, hl.doe_z(), hl.sensor_z()) == "doe"
    hl.intensity_upsample = 8
    with torch.no_grad():
        r = hl.psf_result((0.0, 0.0), wl, ks=32)
    ref = _reference(hl, (0.0, 0.0), 32, r.center[0, 0], 192)
    err = float((r.psf[0, 0] - ref.psf).abs().sum())
    print(f"F/1.3 asphere on axis: {err:.3g} from the Huygens PSF (its own error ~{ref.error_estimate:.2g})")
    assert ref.error_estimate < 3e-4
    assert err < 5e-4
