"""MidSystemLens's final plane as a value type (:class:`raywave.hybrid.midsystem.FinalPlane`, issue 43: ≤ 10
parameters a function); the earlier ``final_distance, final_size, final_pitch`` (keywords or positional) still
build the same lens."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import FinalPlane, MidSystemLens, Orders  # noqa: E402


def _parts():
    sys_ = W.TwoLensSystem(f_doe=10.0, doe_radius=10.0)
    return M.two_lens_split(sys_), FresnelDOE(10.0, 200, 1e-3, wavelength=0.55)


def test_final_plane_value_type_and_the_earlier_forms_agree():
    lens, doe = _parts()
    new = MidSystemLens(lens, doe, 1, None, FinalPlane(0.01, 0.4, 1e-3), sensor_pitch=2e-3, min_efficiency=0.02)
    kw = MidSystemLens(lens, doe, 1, None, final_distance=0.01, final_size=0.4, final_pitch=1e-3, sensor_pitch=2e-3,
                       min_efficiency=0.02)
    pos = MidSystemLens(lens, doe, 1, None, 0.01, 0.4, 1e-3, 2e-3, "doe", 0.02)
    for ml in (new, kw, pos):
        assert ml.final_distance == 0.01 and ml.final.shape == new.final.shape
        assert ml.final.pitch == 1e-3 and ml.sensor_pitch == 2e-3 and ml.min_efficiency == 0.02
        assert ml.stop_edge == ("doe" if ml is pos else "auto")
    assert new.final.shape[0] == 400


def test_final_plane_missing_or_unknown_arguments_are_named():
    lens, doe = _parts()
    with pytest.raises(TypeError, match="missing final_pitch"):
        MidSystemLens(lens, doe, 1, None, final_distance=0.01, final_size=0.4)
    with pytest.raises(TypeError, match="unexpected keyword"):
        MidSystemLens(lens, doe, 1, None, FinalPlane(0.01, 0.4, 1e-3), final_pich=1e-3)
    with pytest.raises(TypeError, match="given twice"):
        MidSystemLens(lens, doe, 1, None, 0.01, 0.4, 1e-3, final_pitch=1e-3)


def test_orders_value_type_and_the_short_keywords_agree():
    """``orders=Orders(keep, min_efficiency, weak_edge)`` and the short forms build the same lens."""
    lens, doe = _parts()
    plane = FinalPlane(0.01, 0.4, 1e-3)
    full = MidSystemLens(lens, doe, 1, None, plane, stop_edge="exit_pupil", edge_step="asm",
                         orders=Orders([1, -1], 1e-3, "doe"))
    short = MidSystemLens(lens, doe, 1, None, plane, stop_edge="exit_pupil", edge_step="asm", orders=[1, -1],
                          min_efficiency=1e-3, weak_edge="doe")
    for ml in (full, short):
        assert ml.only == [{1, -1}] and ml.min_efficiency == 1e-3 and ml.weak_edge == "doe"
    default = MidSystemLens(lens, doe, 1, None, plane)
    assert default.only == [None] and default.min_efficiency == 0.01 and default.weak_edge is None


def test_orders_bad_values_and_both_forms_are_named():
    lens, doe = _parts()
    plane = FinalPlane(0.01, 0.4, 1e-3)
    with pytest.raises(ValueError, match="weak_edge must be None or 'doe'"):
        MidSystemLens(lens, doe, 1, None, plane, weak_edge="exit_pupil")
    with pytest.raises(ValueError, match="min_efficiency must be ≥ 0"):
        Orders(min_efficiency=float("nan"))
    with pytest.raises(TypeError, match="inside orders=Orders"):
        MidSystemLens(lens, doe, 1, None, plane, orders=Orders(), min_efficiency=0.02)
