"""Fisheye fields beyond 90° (issue 44): an object at infinity seen from behind the first vertex.

OpticStudio defines a field angle θ in (-180°, 180°) by tan θ = m/n with n < 0 beyond 90°: the collimated beam
(0, sin θ, cos θ) travels sideways or backward and meets the front of a strongly curved first surface. raywave aims
such a field's rays on the plane across the beam, continuing in field angle from the axis, and the tracer takes every
ray where the light travels toward +z from the surface's front side. Checked here: the geometry (the entry crossing
of a ray travelling backward onto a sphere, against the analytic one), and two real fisheyes of the OpticExplorer
Optics Database (tests/data/opticsdatabase, MIT): the chief ray at 90.015° (Canon EF15mm f2.8 Fisheye) and at 91.075°
(Samsung 10mm F3.5 Fisheye, a YFIE operand) traced by Optiland 0.6.3 from the same start lands where raywave's does
(1e-9 relative), passes the centre of the stop, and lands near the image circle's radius (the lenses' 180° diagonal
or circular image).
"""

import math
import sys
import warnings
from pathlib import Path

import pytest
import torch

import raywave
from raywave.io import LensFileWarning, read_lens_spec
from raywave.io.zmx import decode_zmx_bytes
from raywave.lens.sources import beam_basis, beam_direction, chief_ray, check_field_angles
from raywave.surfaces.geometry import Standard

HERE = Path(__file__).resolve().parent
DATA = HERE / "data" / "opticsdatabase"
sys.path.insert(0, str(HERE.parent / "benchmarks"))


def test_a_ray_travelling_backward_meets_the_front_of_a_sphere():
    """A ray at 100° (travelling toward -z) onto a sphere of radius 20 mm (vertex at the origin, centre at z = 20):
    with ``front`` the entry crossing (the smaller root of |o + t d - C| = R), as the analytic solution; without, the
    other crossing (the convention for light after a mirror)."""
    R = 20.0
    g = Standard(1.0 / R, 0.0)
    th = math.radians(100.0)
    d = torch.tensor([0.0, math.sin(th), math.cos(th)], dtype=torch.float64)
    o = torch.tensor([0.0, -40.0, 12.0], dtype=torch.float64)
    c = torch.tensor([0.0, 0.0, R], dtype=torch.float64)
    b = float((o - c) @ d)
    disc = b * b - float((o - c) @ (o - c)) + R * R
    t_in, t_out = -b - math.sqrt(disc), -b + math.sqrt(disc)
    args = [v.reshape(1) for v in (*o, *d)]
    with torch.no_grad():
        t, ok = g.intersect(*args, front=True)
        t2, _ = g.intersect(*args)
    assert bool(ok) and float(t) == pytest.approx(t_in, rel=1e-13)
    assert float(t2) == pytest.approx(t_out, rel=1e-13)


def test_beam_directions_follow_opticstudio_beyond_90_degrees():
    f = torch.tensor([[0.0, 100.0], [120.0, 0.0], [10.0, 95.0], [0.0, 30.0]], dtype=torch.float64)
    d = beam_direction(f)
    assert torch.allclose(d[0], torch.tensor([0.0, math.sin(math.radians(100)), math.cos(math.radians(100))],
                                             dtype=torch.float64), atol=1e-15)
    assert torch.allclose(d[1], torch.tensor([math.sin(math.radians(120)), 0.0, math.cos(math.radians(120))],
                                             dtype=torch.float64), atol=1e-15)
    # both angles: tan θx = l/n, tan θy = m/n with n < 0 (OpticStudio's convention)
    assert float(d[2, 2]) < 0
    assert float(d[2, 0] / d[2, 2]) == pytest.approx(math.tan(math.radians(10.0)), rel=1e-12)
    assert float(d[2, 1] / d[2, 2]) == pytest.approx(math.tan(math.radians(95.0)), rel=1e-12)
    e1, e2 = beam_basis(d)
    for v in (e1, e2):
        assert torch.allclose((v * d).sum(-1), torch.zeros(4, dtype=torch.float64), atol=1e-15)
    assert torch.allclose((e1 * e2).sum(-1), torch.zeros(4, dtype=torch.float64), atol=1e-15)


def test_angles_beyond_90_only_for_an_object_at_infinity():
    check_field_angles([0.0, 110.0, -179.0], distant=True)
    with pytest.raises(ValueError, match=r"between -180° and 180°"):
        check_field_angles([180.0], distant=True)
    with pytest.raises(ValueError, match=r"beyond 90° only for an object at infinity"):
        check_field_angles([95.0])


@pytest.mark.parametrize("name, field, radius", [("Canon EF15mm f2.8 Fisheye.zmx", 90.015, 21.6),
                                                  ("Samsung 10mm F3.5 Fisheye.zmx", 91.075, 14.2)])
def test_fisheye_chief_ray_beyond_90_degrees_against_optiland(name, field, radius):
    from _optiland_compare import compare

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = raywave.load_lens(DATA / name)
    assert max(lens.fields) == pytest.approx(field)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cr = chief_ray(lens, (0.0, field))
        img = lens.trace_to_image(cr)
        at_stop = lens.trace(cr, stop=lens.stop_index + 1)
    assert float(cr.d[0, 0, 0, 2]) < 0  # the beam travels backward, from behind the first vertex
    assert bool(img.valid.all()) and bool(at_stop.valid.all())  # within every clear aperture
    assert float(at_stop.o[0, 0, 0, :2].abs().max()) < 1e-9  # through the centre of the stop
    assert float(img.o[0, 0, 0, 1]) == pytest.approx(radius, rel=0.03)  # the image circle's radius
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        diffs = compare(str(DATA / name), lens)
    assert diffs["chief_y"] < 1e-9, diffs
    assert max(diffs.values()) < 1e-9, diffs


def test_fisheye_field_of_a_finite_object_is_left_out_naming_field_and_line(tmp_path):
    """Beyond 90° needs an object at infinity: with the object at 1 m the field is left out, its number and line
    named."""
    text = decode_zmx_bytes((DATA / "Canon EF15mm f2.8 Fisheye.zmx").read_bytes())[0]
    lines = text.splitlines()
    i = next(k for k, l in enumerate(lines) if l.startswith("SURF 0"))
    j = next(k for k in range(i, len(lines)) if lines[k].strip().startswith("DISZ"))
    lines[j] = "  DISZ 1000"
    yfln = next(k for k, l in enumerate(lines) if l.startswith("YFLN")) + 1
    p = tmp_path / "near.zmx"
    p.write_text("\n".join(lines))
    with pytest.warns(LensFileWarning, match=rf":{yfln}: field 3 \(90.015°, line {yfln}\) left out: a finite "
                                             r"object's angles must lie below 90°"):
        spec = read_lens_spec(p)
    assert spec["fields"]["values"] == [0.0, 63.0105]


def test_the_ray_wave_engine_names_a_field_at_or_beyond_90_degrees():
    """The engine samples the entrance-pupil plane: a field angle ≥ 90° is refused before any work, naming the
    field (both entry points: the PSF path and doe_fields)."""
    from raywave.assembly.build import load_hybrid

    hl = load_hybrid("hybrid_asphere")
    with pytest.raises(ValueError, match=r"field \[0\.0, 95\.0\].*below 90°"):
        hl.psf([(0.0, 95.0)], ks=8)
    with pytest.raises(ValueError, match=r"field \[90\.0, 0\.0\].*below 90°"):
        hl.doe_fields([(90.0, 0.0)])
