"""Issue 47: the default PSF against references that are themselves converged.

- The pixel quadrature's refinement (``integrated_upsampled_intensity(refine=True)``, the engine's default): where
  the cubic pixel integral at ``q`` = 4 is off (a PSF as sharp as the field's grid allows, on pixels of that pitch)
  it takes ``2q``; elsewhere it leaves the ``q`` result bit for bit. Checked against the exact pixel integral of a
  band-limited intensity (analytic).
- The real lenses against the Huygens exit-pupil PSF with its polar pupil quadrature (``n_pupil="auto"``: levels
  agree to ~1e-10 once the wavefront is resolved) and its stop edge at the stop rim's images (where the stop is
  sharp), the reference's own error beside every figure (slow); the bundled asphere against the one on the paraxial
  exit-pupil sphere (the two references 5e-6 to 3.4e-4 apart there; the engine within 8.2e-4 of either).
"""

import math
import warnings
from pathlib import Path

import pytest
import torch

F64, C128 = torch.float64, torch.complex128
DATA = Path(__file__).resolve().parent / "data"


def _plane_waves(n: int, p: float, waves):
    """A field (n, n) of plane waves ``(amplitude, fx, fy)`` (cycles/mm, rounded to whole cycles a window) sampled at
    pitch p (sample (0, 0) at the origin), and its exact intensity's pixel integral over pixels of ``ps`` centred at
    ``c + (j, i)·ps``."""
    x = torch.arange(n, dtype=F64) * p
    df = 1.0 / (n * p)  # periodic in the window (the upsampling treats it so): whole cycles a period
    waves = [(a, round(fx / df) * df, round(fy / df) * df) for a, fx, fy in waves]
    u = sum(a * torch.exp(2j * math.pi * (fx * x[None, :] + fy * x[:, None])) for a, fx, fy in waves)

    def exact(c: float, ps: float, k: int) -> torch.Tensor:
        lo = c - 0.5 * ps + torch.arange(k, dtype=F64) * ps

        def prim(f, t):  # ∫ e^{2πi f t} dt over [lo, lo + ps]
            if f == 0:
                return torch.full_like(t, ps, dtype=C128)
            return (torch.exp(2j * math.pi * f * (t + ps)) - torch.exp(2j * math.pi * f * t)) / (2j * math.pi * f)

        out = torch.zeros(k, k, dtype=C128)
        for a, fx, fy in waves:
            for b, gx, gy in waves:  # |u|² = Σ a b* e^{2πi ((fx − gx) x + (fy − gy) y)}
                out += a * b.conjugate() * prim(fy - gy, lo)[:, None] * prim(fx - gx, lo)[None, :]
        return out.real

    return u, exact


def test_pixel_quadrature_refines_only_where_q_leaves_more_than_the_tolerance():
    """A field near its grid's band limit (0.8 of Nyquist, crossing waves) on pixels of the field's pitch: the cubic
    integral at q = 4 is ~1e-3 off the exact pixel integral, ``refine=True`` takes q = 8 (the error falls ~16×); a
    field at a tenth of the band is integrated to < 2e-4 at q = 4 and returned unchanged (bit for bit)."""
    from raywave.wave.propagation import integrated_upsampled_intensity
    from raywave.wave.propagation.resample import REFINE_TOL

    n, p = 96, 1e-3
    nyq = 0.5 / p
    k, c = 40, 28 * p
    for frac, refined in ((0.8, True), (0.1, False)):
        waves = [(1.0, frac * nyq, 0.3 * frac * nyq), (0.7, -frac * nyq, 0.1 * nyq), (0.5 + 0.2j, 0.0, -frac * nyq)]
        u, exact = _plane_waves(n, p, waves)
        want = exact(c, p, k)
        plain = integrated_upsampled_intensity(u, 4, p, (0.0, 0.0), p, (c, c), (k, k))
        fine = integrated_upsampled_intensity(u, 8, p, (0.0, 0.0), p, (c, c), (k, k))
        got = integrated_upsampled_intensity(u, 4, p, (0.0, 0.0), p, (c, c), (k, k), refine=True)
        err = {name: float((v - want).abs().sum() / want.sum()) for name, v in (("4", plain), ("8", fine),
                                                                                  ("refined", got))}
        print(f"{frac} of Nyquist: rel L1 from the exact pixel integral {err}")
        if refined:
            assert err["4"] > REFINE_TOL and torch.equal(got, fine) and err["8"] < err["4"] / 8
        else:
            assert err["4"] < REFINE_TOL and torch.equal(got, plain)
    # per image in a batch: the sharp one refined, the smooth one as it was
    u_sharp, _ = _plane_waves(n, p, [(1.0, 0.8 * nyq, 0.2 * nyq), (0.7, -0.8 * nyq, 0.0)])
    u_soft, _ = _plane_waves(n, p, [(1.0, 0.1 * nyq, 0.0), (0.7, -0.05 * nyq, 0.02 * nyq)])
    both = integrated_upsampled_intensity(torch.stack([u_sharp, u_soft]), 4, p, (0.0, 0.0), p, (c, c), (k, k),
                                          refine=True)
    assert torch.equal(both[1], integrated_upsampled_intensity(u_soft, 4, p, (0.0, 0.0), p, (c, c), (k, k)))
    assert torch.allclose(both[0], integrated_upsampled_intensity(u_sharp, 8, p, (0.0, 0.0), p, (c, c), (k, k)),
                          rtol=1e-12, atol=1e-15)


LENSES = {
    "cooke_triplet": "cooke_triplet",
    "double_gauss": str(DATA / "zmx" / "double_gauss_ohara_cdgm_hoya.zmx"),
    "singlet_nbk7_50": str(DATA / "real_lenses" / "singlet_nbk7_50.zmx"),
    "asphere_f13": str(DATA / "real_lenses" / "asphere_f13_nsf11.zmx"),
}
#: sensor pitch (mm) where the DOE pitch leaves most of the PSF outside a 32-pixel crop (as benchmarks/
#: stop_edge_references.py)
PITCH = {("asphere_f13", 0.7): 3e-3, ("asphere_f13", 1.0): 3e-3, ("double_gauss", 0.7): 3e-3,
         ("double_gauss", 1.0): 3e-3, ("singlet_nbk7_50", 1.0): 3e-3}
#: the reference's own error estimate must be below this (the polar levels reach ~1e-10)
REF_TOL = 1e-5
#: the cases that do not yet meet 1e-3 at the default, with the measured figure and what it is made of; the rest must
#: (the double Gauss at full field, 2.73e-3 until 2026-11-29, is within since the ripple band's reach rule and the
#: caustic fallback's tolerance, h47b: benchmarks/results/stop_edge_references_xiv_h47b.json)
KNOWN: dict = {}


def _rim_image_reference(hl, fld, center, ks: int = 32):
    """The Huygens exit-pupil PSF with the stop's edge where it is sharp: at each stop-rim point's own image
    (``huygens_psf(sphere="rim_images")``; tests/test_stop_edge_rim_reference.py checks its surface),
    ``n_pupil="auto"`` (levels ×1.25 until two agree)."""
    from raywave.models.exit_pupil import huygens_psf

    return huygens_psf(hl.lens, fld, hl.lens.primary_wavelength, ks=ks, pitch=hl.sensor_pitch, center=center,
                       n_pupil="auto", sensor_z=float(hl.sensor_z()), max_n_pupil=1024, sphere="rim_images")


@pytest.mark.slow  # the Huygens reference: seconds on axis, up to ~10 min at full field (the double Gauss)
@pytest.mark.parametrize("frac", [0.0, 0.7, 1.0])
@pytest.mark.parametrize("name", list(LENSES))
def test_default_psf_against_the_converged_huygens_reference(name, frac):
    """The default PSF of four real lenses (blank DOE) against the Huygens exit-pupil PSF whose stop edge sits where
    the stop is sharp: at the stop rim's images. A sharp cut of the geometric field is the right boundary value only
    there (the stop's edge is imaged there); on the sphere through the paraxial exit pupil the real field has already
    diffracted from the edge by the pupil's aberrations (7–32 mm of them on the double Gauss at full field: that
    reference moves by 1e-4 per mm of them, and is 2.2e-3 from this one there; 1e-4 to 6e-4 on the other off-axis
    cases). The engine's edge sits at the rim images too (its Fresnel step from each rim point's image). Measured
    (benchmarks/results/stop_edge_references_xiv_h47b.json): every case ≤ 8.2e-4 at the default (the double
    Gauss at full field 6.8e-4)."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import load_lens, resolve_lens_path

    lens = load_lens(resolve_lens_path(LENSES[name]))
    fld = (0.0, frac * max(float(f) for f in lens.fields))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(LENSES[name], sensor_pitch=PITCH.get((name, frac)), fields=[list(fld), [0.0, 0.0]],
                         field_type="angle")
        with torch.no_grad():
            r = hl.psf_result(fld, hl.lens.primary_wavelength, ks=32)
            ref = _rim_image_reference(hl, fld, tuple(float(c) for c in r.center[0, 0]))
    err = float((r.psf[0, 0] - ref.psf).abs().sum())
    print(f"{name} at {frac} field: {err:.3g} from the Huygens PSF with its edge at the rim images (its own error "
          f"~{ref.error_estimate:.2g}, levels {ref.levels})")
    assert ref.error_estimate is not None and ref.error_estimate < REF_TOL
    if (name, frac) in KNOWN:
        assert err < 2e-2
        pytest.xfail(f"not yet 1e-3: {KNOWN[(name, frac)]}")
    assert err < 1e-3


@pytest.mark.slow  # ~1 min: four references
@pytest.mark.parametrize("deg", [0.0, 7.0, 14.0, 17.5])
def test_bundled_asphere_within_1e_3_of_the_converged_reference_at_every_field(deg):
    """The bundled asphere's lens with a 6 mm blank DOE of 1 µm pixels at 0.7 mm, 3 µm sensor pixels, λ 0.53 µm (as
    benchmarks/stop_edge_references.py ``asphere:DEG``). Measured: 2.05e-4 / 1.79e-4 / 3.70e-4 / 9.15e-4 (2026-12-01,
    h47c, the short-reach band: 7.7e-5 / 1.46e-4 / 2.46e-4 / 8.2e-4), the
    references' own errors 1.6e-7 / 6.2e-6 / 1.4e-9 / 4.8e-6 (17.5° was 1.11e-3 against an unconverged 256-cell
    grid)."""
    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import bundled_lens_path, load_lens
    from raywave.models.exit_pupil import huygens_psf

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    hl = HybridLens(lens, BlankDOE(6000, 1e-3), 0.7, sensor_pitch=3e-3)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        r = hl.psf_result((0.0, deg), 0.53, ks=32)
        ref = huygens_psf(lens, (0.0, deg), 0.53, ks=32, pitch=3e-3, center=tuple(float(c) for c in r.center[0, 0]),
                          n_pupil="auto", sensor_z=float(hl.sensor_z()))
    err = float((r.psf[0, 0] - ref.psf).abs().sum())
    print(f"bundled asphere at {deg}°: {err:.3g} from the Huygens PSF (its own error ~{ref.error_estimate:.2g})")
    assert ref.error_estimate < 2e-5 and err < 1e-3
