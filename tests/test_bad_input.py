"""Bad input gets a clear error or warning that names the problem and the place; never silent NaN."""

import json
import warnings

import pytest
import torch

from raywave.cli.main import main
from raywave.io import LensFileError
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.materials import GlassNotFoundError, WavelengthRangeWarning


def _cooke_spec():
    return json.loads(bundled_lens_path("cooke_triplet").read_text())


def _write(tmp_path, spec, name="lens.json"):
    p = tmp_path / name
    p.write_text(json.dumps(spec, indent=2))
    return p


def test_unknown_glass_names_surface_and_suggests(tmp_path):
    spec = _cooke_spec()
    spec["surfaces"][0]["material"] = "N-SK61"
    with pytest.raises(GlassNotFoundError, match=r"surfaces\[0\].*N-SK61.*did you mean.*N-SK16"):
        load_lens(_write(tmp_path, spec))


def test_negative_thickness_in_glass(tmp_path):
    spec = _cooke_spec()
    spec["surfaces"][0]["thickness"] = -1.0
    with pytest.raises(ValueError, match=r"surface 0: negative thickness"):
        load_lens(_write(tmp_path, spec))


def test_overlapping_surfaces(tmp_path):
    spec = _cooke_spec()
    spec["surfaces"][1]["thickness"] = -0.5  # the flint would start before the crown ends
    with pytest.raises(ValueError, match=r"surfaces 1 and 2 overlap"):
        load_lens(_write(tmp_path, spec))


def test_empty_aperture(tmp_path):
    spec = _cooke_spec()
    spec["surfaces"][2]["aperture"] = {"shape": "circle", "radius": 0.0}
    with pytest.raises(LensFileError, match=r"lens.json:\d+:.*aperture"):
        load_lens(_write(tmp_path, spec))


def test_cli_reports_unknown_glass_in_one_line(tmp_path, capsys):
    spec = _cooke_spec()
    spec["surfaces"][4]["material"] = "NOPE-GLASS"
    assert main(["info", str(_write(tmp_path, spec))]) == 2
    err = capsys.readouterr().err
    assert "NOPE-GLASS" in err and "Traceback" not in err


def test_fully_vignetted_point_source_warns_and_stays_finite():
    lens = load_lens(bundled_lens_path("cooke_triplet"))
    with pytest.warns(VignettingWarning, match="every ray is vignetted"):
        rays = point_source_rays(lens, (0.0, 75.0), pupil=("grid", 5))
    out = lens.trace_to_image(rays)
    assert not bool(out.valid.any())
    assert torch.isfinite(out.o).all() and torch.isfinite(out.opl).all()


def test_wavelength_outside_glass_range_warns_during_trace():
    lens = load_lens(bundled_lens_path("singlet"))
    with pytest.warns(WavelengthRangeWarning, match="N-BK7"):
        point_source_rays(lens, (0.0, 0.0), 0.25, pupil=("grid", 3))
