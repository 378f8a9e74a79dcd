"""Real image heights (FTYP 3) whose chief ray comes from beyond 90° (issue 44): fisheyes of the OpticExplorer Optics
Database (tests/data/opticsdatabase, MIT).

raywave.lens.fields solves such a height by a continuation in image height from the axis over beam directions up to
180° (an object at infinity seen from behind the first vertex). Checked independently of the solve: raywave's own
aimed chief ray at the solved angle (raywave.lens.sources, a different parametrisation and iteration) traced forward
lands at the requested height to 1e-9 mm and passes the stop centre; Optiland 0.6.3 traces the same start ray to the
same image point (1e-9 relative); the field angle grows monotonically with the height; a height beyond the lens's
reach is left out naming why, and the chief ray just beyond the reported angle is indeed blocked.
"""

import math
import re
import sys
import warnings
from pathlib import Path

import pytest
import torch

import raywave
from raywave.lens.fields import FieldSolveWarning, real_image_height_fields
from raywave.lens.sources import chief_ray

HERE = Path(__file__).resolve().parent
DATA = HERE / "data" / "opticsdatabase"
sys.path.insert(0, str(HERE.parent / "benchmarks"))

KINOPTIK = "Kinoptik Super-Tegea 1.9mm f1.9 Fisheye.zmx"


def _load(name):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = raywave.load_lens(DATA / name)
    return lens, [w for w in caught if issubclass(w.category, FieldSolveWarning)]


def _trace_chief(lens, angle):
    """(image height mm, largest |x|, |y| at the stop mm, valid, start direction z) of raywave's aimed chief ray."""
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cr = chief_ray(lens, (0.0, angle))
        img = lens.trace_to_image(cr)
        at_stop = lens.trace(cr, stop=lens.stop_index + 1)
    valid = bool(img.valid.all()) and bool(at_stop.valid.all())
    return (float(img.o[0, 0, 0, 1]), float(at_stop.o[0, 0, 0, :2].abs().max()), valid, float(cr.d[0, 0, 0, 2]))


@pytest.fixture(scope="module")
def kinoptik():
    return _load(KINOPTIK)


def test_a_real_image_height_from_beyond_90_degrees_lands_there(kinoptik):
    """The Kinoptik Super-Tegea 1.9mm's heights 2.94 and 4.2 mm: all fields solved (no warning), the widest from
    beyond 90°; the aimed chief ray at each solved angle lands at its height to 1e-9 mm through the stop centre."""
    lens, warns = kinoptik
    assert not warns, [str(w.message) for w in warns]
    assert lens.field_definition["values"] == [0.0, 2.94, 4.2]
    assert lens.fields[2] > 90.0 and 0.0 < lens.fields[1] < 90.0
    for angle, height in zip(lens.fields, lens.field_definition["values"]):
        y, at_stop, valid, dz = _trace_chief(lens, angle)
        assert valid
        assert abs(y - height) < 1e-9, (angle, y, height)
        assert at_stop < 1e-9
    assert _trace_chief(lens, lens.fields[2])[3] < 0  # the beam travels backward, from behind the first vertex


def test_the_chief_ray_from_beyond_90_degrees_against_optiland(kinoptik):
    """Optiland 0.6.3 traces raywave's chief ray (start and direction) at the widest solved field, 99.65°, through
    its own model of the file to the same image point; the paraxial data agree too (benchmarks/_optiland_compare)."""
    from _optiland_compare import compare

    lens, _ = kinoptik
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        diffs = compare(str(DATA / KINOPTIK), lens)
    assert max(diffs.values()) < 1e-9, diffs
    assert "chief_y" in diffs


def test_field_angle_grows_with_the_real_image_height(kinoptik):
    """Across the image circle (0.5 to 4.4 mm, through 90°) the solved angle increases strictly with the height,
    and the aimed chief ray traced forward lands at its height (at 0.5, 3.3 and 4.1 mm: raywave's chief-ray aiming,
    a continuation in field angle on the entrance plane, does not reach the 4.4 mm one, 105.4°)."""
    lens, _ = kinoptik
    heights = [0.5, 1.5, 2.5, 3.3, 3.8, 4.1, 4.4]
    angles, why = real_image_height_fields(lens, heights)
    assert not why, why
    assert all(b > a for a, b in zip(angles, angles[1:])), angles
    assert angles[0] < 90.0 < angles[-1]
    for k in (0, 3, 5):
        assert abs(_trace_chief(lens, angles[k])[0] - heights[k]) < 1e-9, (angles[k], heights[k])
    # a negative height: the mirror field
    neg, _ = real_image_height_fields(lens, [-4.1])
    assert neg[0] == pytest.approx(-angles[5], abs=1e-9)


def test_a_height_beyond_reach_is_left_out_with_the_reason():
    """The Zeiss Hologon 15mm's corner, 21.6 mm: its chief ray misses the strongly curved surface 4 before it gets
    there. The warning names the height, the field, the surface and the largest height reached with its angle; at
    that angle the aimed chief ray lands there, and a degree beyond it is blocked."""
    lens, warns = _load("Zeiss Hologon f8 15mm.zmx")
    assert len(warns) == 1
    text = str(warns[0].message)
    m = re.search(r"no chief ray reaches the image height 21.6 mm \(field 3, real image height\): the chief ray "
                  r"misses surface 4 or is totally internally reflected there: the real chief ray reaches "
                  r"([\d.]+) mm at most, at field ([\d.]+)°", text)
    assert m, text
    reached, angle = float(m.group(1)), float(m.group(2))
    assert lens.field_definition["values"] == [0.0, 15.12]
    y, _, valid, _ = _trace_chief(lens, angle)
    assert valid and y == pytest.approx(reached, abs=1e-3)
    assert not _trace_chief(lens, angle + 1.0)[2]
