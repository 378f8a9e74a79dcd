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
from raywave.hybrid.midsystem import FinalPlane, MidSystemLens  # noqa: E402


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
        assert ml.stop_edge == "doe"
    assert new.final.shape[0] == 400


def test_final_plane_missing_or_unknown_arguments_are_named():
    lens, doe = _parts()
    with pytest.raises(TypeError, match="missing final_pitch"):
        MidSystemLens(lens, doe, 1, None, final_distance=0.01, final_size=0.4)
    with pytest.raises(TypeError, match="unexpected keyword"):
        MidSystemLens(lens, doe, 1, None, FinalPlane(0.01, 0.4, 1e-3), final_pich=1e-3)
    with pytest.raises(TypeError, match="given twice"):
        MidSystemLens(lens, doe, 1, None, 0.01, 0.4, 1e-3, final_pitch=1e-3)
