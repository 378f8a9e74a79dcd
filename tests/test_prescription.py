"""Issue 45: the prescription (``Lens.table()``, ``print(lens)``, ``raywave info``) and the paraxial power of a
BINARY_2 DOE, checked against a real ray through the same phase traced with the local grating approximation."""

import math
import sys
from pathlib import Path

import pytest
import torch

from raywave.cli.main import main
from raywave.io import read_lens_spec
from raywave.lens.analysis import real_ray_efl
from raywave.lens.build import load_lens, resolve_lens_path
from raywave.lens.lens import Lens
from raywave.lens.prescription import binary2_power, doe_power, surface_table
from raywave.surfaces.geometry import Plane
from raywave.surfaces.interaction import Diffraction
from raywave.surfaces.surface import Surface

sys.path.insert(0, str(Path(__file__).parent))
from test_cli_psf import TINY_ZMX  # noqa: E402  (a lens + BINARY_2 DOE plane .zmx)


def test_cooke_table_rows():
    lens = load_lens(resolve_lens_path("cooke_triplet"))
    spec = read_lens_spec(resolve_lens_path("cooke_triplet"))
    rows = surface_table(lens)
    assert [r.radius for r in rows] == pytest.approx([s["radius"] for s in spec["surfaces"]], rel=1e-12)
    assert [r.glass for r in rows] == [s["material"] for s in spec["surfaces"]]
    assert [r.stop for r in rows] == [i == 2 for i in range(6)]
    assert rows[2].fixed and rows[2].semi_diameter == pytest.approx(lens.stop_radius())
    # unfixed semi-diameters are the traced beam: the front lens carries at least the on-axis EPD/2 = 5 mm
    assert rows[0].semi_diameter > 5.0 and not rows[0].fixed
    text = str(lens)
    assert "22.01359" in text and "STO" in text and "N-SK16" in text and "Standard()" not in text
    assert "Standard(radius=22.01359, conic=0)" in repr(lens)  # the module tree (field signatures) keeps radii too


def test_asphere_terms_listed():
    text = load_lens(resolve_lens_path("hybrid_asphere")).table()
    assert "even_asphere" in text and "a4 = 0.000533" in text and "-1.2051" in text


def _binary2_phase(a, norm, order=1.0):
    """The BINARY_2 phase φ = M Σ A_i (r/R)^(2i) (rad) and its gradient, as a Diffraction phase callable."""
    def phase(x, y, wavelength):
        r2 = (x * x + y * y) / norm**2
        phi = sum(order * c * r2 ** (i + 1) for i, c in enumerate(a))
        dphi_dr2 = sum(order * c * (i + 1) * r2**i for i, c in enumerate(a)) / norm**2
        return phi, 2 * x * dphi_dr2, 2 * y * dphi_dr2
    return phase


@pytest.mark.parametrize("order", [1.0, 2.0])
def test_binary2_power_matches_a_real_ray(tmp_path, order):
    """The paraxial DOE power and the EFL of lens + DOE equal a real paraxial-height ray's EFL through the same
    BINARY_2 phase on a plane 3 mm after the lens (local grating approximation, raywave.surfaces.Diffraction)."""
    path = tmp_path / "tiny.zmx"
    path.write_text(TINY_ZMX.replace("PARM 0 1", f"PARM 0 {order:g}"))
    spec = read_lens_spec(path)
    lens = load_lens(path)
    p = doe_power(lens, spec["doe"], 0.55)
    model = spec["doe"]["phase_model"]
    assert p.power == pytest.approx(binary2_power(model, 0.55))
    assert p.power == pytest.approx(-order * (-100.0) * 0.55e-3 / (math.pi * 2.0**2), rel=1e-12)
    d = spec["doe"]["distance"]
    s0, s1 = lens.surfaces
    doe_plane = Surface(Plane(), s1.material, float(s1.thickness) - d,
                        interaction=Diffraction(_binary2_phase(model["coefficients"], model["norm_radius"]), order))
    s1b = Surface(s1.geometry, s1.material, d)
    with_doe = Lens([s0, s1b, doe_plane], epd=4.0, wavelengths=[0.55], primary=0)
    with torch.no_grad():
        efl = float(real_ray_efl(with_doe, 0.55, height=1e-4))
    assert p.efl == pytest.approx(efl, rel=1e-6)
    assert abs(p.efl - float(lens.paraxial(0.55).efl)) > 0.5  # the DOE's power matters here


def test_info_prints_table_and_doe_power(tmp_path, capsys):
    path = tmp_path / "tiny.zmx"
    path.write_text(TINY_ZMX)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "STO" in out and "semi-diam" in out and "DOE paraxial power" in out and "lens + DOE" in out
    assert main(["info", "cooke_triplet"]) == 0
    out = capsys.readouterr().out
    assert "-435.7604" in out and "DOE" not in out
