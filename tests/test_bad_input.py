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


def test_a_doe_grid_beyond_any_size_is_refused_naming_the_file(tmp_path):
    """The slow fuzz run found a mutated .zmx whose beam (a 1e307 mm semi-diameter) sized the default DOE at
    4.7e307 mm: an OverflowError in the pixel count. Any DOE size that is no grid is a ValueError naming the file."""
    from raywave.assembly.build import _pixels, load_hybrid

    with pytest.raises(ValueError, match=r"case\.zmx: the DOE would span 1e\+308 mm"):
        _pixels(1e308, 1e-3, "case.zmx")
    with pytest.raises(ValueError, match="inf pixels"):
        _pixels(float("inf"), 1e-3)
    p = _write(tmp_path, json.loads(bundled_lens_path("singlet").read_text()), "huge.json")
    with pytest.raises(ValueError, match=r"huge\.json: the DOE would span"):
        load_hybrid(p, doe_size=(1e300, 1e300), doe_pitch=1e-3)


def _shown_lines(err: str) -> list[str]:
    """The non-blank lines of captured stderr as a terminal shows them: a progress bar drawn on a slow machine (after
    its 2 s delay) and cleared with a carriage return leaves only what follows the last ``\\r`` of its line."""
    # split at newlines only: str.splitlines() also splits at "\r", so every redraw of a bar came out as a line
    return [ln.rsplit("\r", 1)[-1] for ln in err.split("\n") if ln.rsplit("\r", 1)[-1].strip()]


def test_cli_psf_with_no_light_prints_only_the_error(capsys):
    """The field's VignettingWarning repeated the error: an error exit prints one line (slow fuzz run). Since issue
    45 the dark source is found from one trace before the PSF is computed (its beam misses the 0.05 mm DOE)."""
    assert main(["psf", "singlet", "--field", "0", "15", "--doe-size", "0.05", "--ks", "8", "--rays", "8"]) == 2
    err = _shown_lines(capsys.readouterr().err)
    assert len(err) == 1 and err[0].startswith("raywave: error: --field: field (0, 15) deg"), err
    assert "misses the 0.0518×0.0518 mm DOE aperture" in err[0], err


def test_slow_fuzz_findings_are_clean_refusals(tmp_path, capsys):
    """More cases the slow fuzz run found: a DOE pitch whose grid overflows (the CLI traced it into an
    OverflowError), a JSON aperture shape or DOE phase-model type given as a list (TypeError: unhashable)."""
    from raywave.doe import BlankDOE
    from raywave.io import read_hybrid_spec

    with pytest.raises(ValueError, match="DOE size must be finite"):
        BlankDOE(16, 1e308)
    # (since issue 45 the pitch check refuses both options themselves: no pixel is larger than 0.1 mm)
    assert main(["psf", "singlet", "--doe-pitch", "1e308", "--ks", "8", "--rays", "8"]) == 2
    err = _shown_lines(capsys.readouterr().err)
    assert len(err) == 1 and "--doe-pitch is 1e+308 mm, larger than any DOE" in err[0], err
    assert main(["psf", "singlet", "--sensor-pitch", "1e300", "--ks", "8", "--rays", "8"]) == 2  # inf crop window
    err = _shown_lines(capsys.readouterr().err)
    assert len(err) == 1 and "--sensor-pitch is 1e+300 mm" in err[0], err
    spec = json.loads(bundled_lens_path("singlet").read_text())
    spec["surfaces"][0]["aperture"] = {"radius": 1.0, "shape": [1.0, 2.0]}
    with pytest.raises(LensFileError, match=r"surfaces\[0\]\.aperture\.shape.*circle"):
        load_lens(_write(tmp_path, spec, "list_shape.json"))
    spec = json.loads(bundled_lens_path("singlet").read_text())
    spec["doe"] = {"distance": 5.0, "pitch": 1e-3, "shape": [8, 8], "phase_model": {"type": ["fresnel"]}}
    with pytest.raises(LensFileError, match=r"list_model\.json.*phase_model\.type"):
        read_hybrid_spec(_write(tmp_path, spec, "list_model.json"))
