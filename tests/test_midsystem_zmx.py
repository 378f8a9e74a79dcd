""".zmx diffractive surfaces inside the lens (issue 46): BINARY_2 / DGRATING read as DOEs at a surface, with the
BINARY_2 convention (φ = M Σ A_i (r/R)^(2i) rad, power −M A_1 λ / (π R²)) checked against a hand y–nu trace and
optiland's real-ray trace of the same phase profile."""

import math
import warnings

import numpy as np
import pytest
import torch

from raywave.assembly.midsystem import doe_lens, surface_doe_info, surface_doe_pitch
from raywave.hybrid.midsystem import DOEPhaseSurface, insert_doe
from raywave.io import LensFileError, read_lens_spec

M, A1, A2, R_NORM, WL = 1.0, -300.0, 10.0, 5.0, 0.55

DOUBLET = """VERS 190513 80 123457
MODE SEQ
NAME doublet with a BINARY_2 inside
UNIT MM X W X CM MR CPMM
ENPD 8.0
FTYP 0 0 2 2 0 0 0
YFLN 0.0 3.0
WAVM 1 0.55 1
PWAV 1
SURF 0
  TYPE STANDARD
  CURV 0.0
  DISZ INFINITY
SURF 1
  STOP
  TYPE STANDARD
  CURV 0.02
  DISZ 4.0
  GLAS ___BLANK 1 0 1.5 0
SURF 2
  TYPE BINARY_2
  CURV 0.0
  DISZ 2.0
  CLAP 0 5.0 0
  PARM 0 1
  XDAT 1 2 0 0 1 0 0 ""
  XDAT 2 5.0 0 0 1 0 0 ""
  XDAT 3 -300.0 0 0 1 0 0 ""
  XDAT 4 10.0 0 0 1 0 0 ""
SURF 3
  TYPE STANDARD
  CURV 0.016666666666666666
  DISZ 3.0
  GLAS ___BLANK 1 0 1.6 0
SURF 4
  TYPE STANDARD
  CURV -0.0125
  DISZ 40.0
SURF 5
  TYPE STANDARD
  CURV 0.0
  DISZ 0.0
"""


def _doe_power():
    """The BINARY_2's paraxial power (1/mm) by hand: φ ≈ M A_1 r²/R² = −π r²/(λ f)."""
    return -M * A1 * WL * 1e-3 / (math.pi * R_NORM ** 2)


def _hand_efl(power_doe: float, curv: float = 0.0) -> float:
    """y–nu trace of the doublet with the DOE a thin element of ``power_doe`` on the back face of lens 1 (of
    curvature ``curv``; it adds −y·power to n·u, in any medium)."""
    y, nu = 1.0, 0.0
    nu -= y * (1.5 - 1.0) / 50.0
    y += 4.0 * nu / 1.5
    nu -= y * ((1.0 - 1.5) * curv + power_doe)  # the glass→air face's power (none when plane) and the DOE's
    y += 2.0 * nu
    nu -= y * (1.6 - 1.0) / 60.0
    y += 3.0 * nu / 1.6
    nu -= y * (1.0 - 1.6) / -80.0
    return -1.0 / nu


def _real_efl(lens, h=4e-4):
    """−h / tan u of a collimated on-axis ray at height h (mm) through ``lens``."""
    from raywave.rays.bundle import RayBundle

    rays = RayBundle.create(torch.tensor([[0.0, h, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([WL]))
    with torch.no_grad():
        out = lens.trace(rays, apertures=False)
    return -h * float(out.d[..., 2].reshape(-1)[0]) / float(out.d[..., 1].reshape(-1)[0])


@pytest.fixture
def doublet(tmp_path):
    path = tmp_path / "doublet.zmx"
    path.write_text(DOUBLET)
    return path



def _optiland_doublet_efl(radius_doe: float) -> float:
    """The doublet's EFL (mm) in optiland, with the BINARY_2's radial phase on its surface 2 of radius ``radius_doe``
    (mm; inf: plane): a paraxial real ray at pupil height 4e-4 mm (skips where optiland is absent)."""
    pytest.importorskip("optiland")
    from optiland.materials import IdealMaterial  # lazy: optiland is a test-only dependency
    from optiland.optic import Optic
    from optiland.phase import RadialPhaseProfile

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o = Optic()
        o.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
        o.surfaces.add(index=1, radius=50.0, thickness=4.0, material=IdealMaterial(1.5), is_stop=True)
        o.surfaces.add(index=2, radius=radius_doe, thickness=2.0, material="air",
                       phase_profile=RadialPhaseProfile([M * A1 / R_NORM ** 2, M * A2 / R_NORM ** 4]))
        o.surfaces.add(index=3, radius=60.0, thickness=3.0, material=IdealMaterial(1.6))
        o.surfaces.add(index=4, radius=-80.0, thickness=40.0, material="air")
        o.surfaces.add(index=5)
        o.set_aperture("EPD", 8.0)
        o.fields.set_type("angle")
        o.fields.add(y=0.0)
        o.wavelengths.add(WL, is_primary=True)
        rays = o.trace_generic(0.0, 0.0, 0.0, 1e-4, WL)  # pupil y 1e-4: h = 4e-4 mm
    return -4e-4 * float(rays.N[0]) / float(rays.M[0])

def test_binary2_inside_a_doublet_is_read_as_a_surface_doe(doublet):
    spec = read_lens_spec(doublet)
    s = spec["surfaces"][1]
    assert s["type"] == "standard" and s["radius"] == "inf" and s["material"] == "air" and s["thickness"] == 2.0
    assert s["doe"] == {"distance": 0.0, "aperture": "circle", "size": [10.0, 10.0], "phase": None,
                        "phase_model": {"type": "binary_2", "order": 1.0, "norm_radius": 5.0,
                                        "coefficients": [-300.0, 10.0]}}
    assert "doe" not in spec  # no DOE before the sensor
    lens, doe, after, distance = doe_lens(spec, str(doublet), doublet.parent)
    assert (after, distance) == (1, 0.0) and type(doe).__name__ == "Binary2DOE" and doe.aperture == "circle"
    # the default pitch samples the phase's steepest slope (r = 5 mm: (600 − 40)/5 = 112 rad/mm) at <= 0.4 rad
    assert 0.4 / 112 * 0.9 <= doe.pitch <= 0.4 / 112


def test_binary2_power_against_hand_trace_and_optiland(doublet):
    spec = read_lens_spec(doublet)
    lens, doe, after, distance = doe_lens(spec, str(doublet), doublet.parent)
    with_doe = insert_doe(lens, after, distance, DOEPhaseSurface(doe), 1.0, doe)
    efl_hand = _hand_efl(_doe_power())
    efl_ray = _real_efl(with_doe)  # through the DOE's pixel phase map, interpolated as the engine does
    assert abs(efl_ray - efl_hand) < 1e-7 * efl_hand
    assert abs(_hand_efl(0.0) - efl_hand) > 2.0  # the DOE matters (≈ 2.6 mm of EFL)
    info = surface_doe_info(spec, lens)
    assert len(info) == 1 and info[0]["surface"] == 1 and info[0]["type"] == "binary_2"
    assert abs(info[0]["power"] - _doe_power()) < 1e-15 and abs(info[0]["efl_with_doe"] - efl_hand) < 1e-7 * efl_hand

    assert abs(efl_ray - _optiland_doublet_efl(np.inf)) < 1e-7 * efl_ray


DGRATING = DOUBLET.replace("""  TYPE BINARY_2
  CURV 0.0
  DISZ 2.0
  CLAP 0 5.0 0
  PARM 0 1
  XDAT 1 2 0 0 1 0 0 ""
  XDAT 2 5.0 0 0 1 0 0 ""
  XDAT 3 -300.0 0 0 1 0 0 ""
  XDAT 4 10.0 0 0 1 0 0 ""
""", """  TYPE DGRATING
  CURV 0.0
  DISZ 2.0
  DIAM 2.0 0 0 0 1 ""
  PARM 1 0.05
  PARM 2 -1
""")


def test_dgrating_inside_the_lens_bends_rays_by_the_grating_equation(tmp_path):
    path = tmp_path / "grating.zmx"
    path.write_text(DGRATING)
    spec = read_lens_spec(path)
    d = spec["surfaces"][1]["doe"]
    # 0.05 lines/µm, order −1: the rulings along x diffract along −y; 20 µm period; sized by the semi-diameter
    assert d["phase_model"] == {"type": "grating", "period": 0.02, "angle": -90.0}
    assert d["aperture"] == "circle" and d["size"] == [4.0, 4.0]
    lens, doe, after, distance = doe_lens(spec, str(path), tmp_path)
    assert doe.pitch <= 0.4 * 0.02 / (2 * math.pi)
    with_doe = insert_doe(lens, after, distance, DOEPhaseSurface(doe), 1.0, doe)
    from raywave.rays.bundle import RayBundle

    # a collimated on-axis ray: refracted toward the axis by lens 1, then diffracted at the grating (glass → air)
    rays = RayBundle.create(torch.tensor([[0.0, 0.3, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([WL]))
    with torch.no_grad():
        before = lens.trace(rays, stop=2)  # the plane glass → air face alone
        after_doe = with_doe.trace(rays, stop=3)  # and the DOE 0 mm after it
    sin_in, sin_out = float(before.d[..., 1].reshape(-1)[0]), float(after_doe.d[..., 1].reshape(-1)[0])
    assert abs(sin_out - (sin_in + (-1) * 0.05e3 * WL * 1e-3)) < 1e-9  # n' sinθ' = n sinθ + M T λ (air after)


CURVED = DOUBLET.replace("SURF 2\n  TYPE BINARY_2\n  CURV 0.0", "SURF 2\n  TYPE BINARY_2\n  CURV -0.01")


def test_curved_binary2_is_a_conformal_doe(tmp_path):
    """A BINARY_2 on a curved face (R −100 mm, glass → air) inside the lens is read as a conformal DOE on that
    surface (its curvature kept, ``"conformal": true``): the EFL through the engine's interpolated pixel map (the
    phase on the sag, refracting in one step) is a hand y–nu trace's with the DOE's power added to the face's
    within 1e-7, and optiland's real-ray trace of the same radial phase on the same curved surface within 1e-7;
    ``raywave info`` says where it sits."""
    from raywave.assembly.midsystem import load_midsystem

    path = tmp_path / "curved.zmx"
    path.write_text(CURVED)
    spec = read_lens_spec(path)
    s = spec["surfaces"][1]
    assert s["radius"] == pytest.approx(-100.0) and s["doe"]["conformal"] is True and "distance" not in s["doe"]
    lens, doe, after, distance = doe_lens(spec, str(path), tmp_path)
    assert (after, distance) == (1, None)
    with_doe = insert_doe(lens, after, distance, DOEPhaseSurface(doe), 1.0, doe)
    assert len(with_doe.surfaces) == len(lens.surfaces) and with_doe.surfaces[1].interaction.kind == "diffraction"
    efl_hand = _hand_efl(_doe_power(), curv=-0.01)
    efl_ray = _real_efl(with_doe)
    assert abs(efl_ray - efl_hand) < 1e-7 * efl_hand
    assert abs(_hand_efl(_doe_power()) - efl_hand) > 0.5  # the curvature matters
    info = surface_doe_info(spec, lens)
    assert info[0]["conformal"] and abs(info[0]["efl_with_doe"] - efl_hand) < 1e-7 * efl_hand
    ml = load_midsystem(path)
    assert ml.placements == [(1, None)]

    assert abs(efl_ray - _optiland_doublet_efl(-100.0)) < 1e-7 * efl_ray


@pytest.mark.parametrize("edit, expected", [
    (lambda t: t.replace("  CURV 0.0\n  DISZ 2.0\n  CLAP", "  CURV 0.0\n  DISZ 0.0\n  CLAP"), "DISZ\\) > 0 mm"),
    (lambda t: t.replace("  PARM 0 1\n", "  PARM 0 1\n  PARM 2 0.001\n"), "aspheric substrate"),
])
def test_diffractive_surfaces_inside_the_lens_that_are_refused(tmp_path, edit, expected):
    path = tmp_path / "bad.zmx"
    path.write_text(edit(DOUBLET))
    with pytest.raises(LensFileError, match=expected):
        read_lens_spec(path)


def test_default_pitch_refuses_an_unsampled_phase():
    from raywave.io.doe import DOEData

    data = DOEData(phase_model={"type": "grating", "period": 1e-4})  # 0.1 µm period over 10 mm
    with pytest.raises(LensFileError, match="doe_pitch"):
        surface_doe_pitch(data, (10.0, 10.0), "surfaces[1].doe", "x.zmx")
