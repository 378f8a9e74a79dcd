"""Units at every entry point (issue 45, item 3): one wavelength check (µm; a number that looks like nm is named)
for the CLI, the Python API and lens files, and one pitch check (mm; a number that looks like µm is named)."""

import json

import pytest

from raywave.cli.main import main
from raywave.utils.checks import MAX_PITCH_MM, pitch_mm, wavelength_um, wavelengths_um


def test_wavelength_check_names_nanometres():
    assert wavelength_um(0.55) == 0.55 and wavelengths_um([0.47, 0.53]) == [0.47, 0.53]
    assert wavelengths_um(0.6) == [0.6] and wavelengths_um("0.6") == [0.6]
    with pytest.raises(ValueError, match=r"µm, not nm \(587.6 looks like nanometres: 587.6 nm = 0.5876 µm"):
        wavelength_um(587.6)
    for bad in (0, -0.5, float("nan"), float("inf"), "green"):
        with pytest.raises(ValueError, match="wavelength in µm"):
            wavelength_um(bad)


def test_pitch_check_names_mm_and_um():
    assert pitch_mm(0.001) == 0.001 and pitch_mm(MAX_PITCH_MM) == MAX_PITCH_MM
    with pytest.raises(ValueError, match=r"1 mm = 1000 µm.*pitches are in mm, not µm.*0.001 mm = 1 µm"):
        pitch_mm(1, "--doe-pitch")


def test_cli_info_refuses_nanometres(capsys):
    """Before: `raywave info cooke_triplet --wavelength 587.6` printed an EFL of 32 mm."""
    assert main(["info", "cooke_triplet", "--wavelength", "587.6"]) == 2
    err = capsys.readouterr().err
    assert "--wavelength" in err and "nanometres" in err and "0.5876 µm" in err and "Traceback" not in err


@pytest.mark.parametrize("argv", [
    ["psf", "singlet", "--wavelength", "550"],
    ["psf", "singlet", "--doe-wavelength", "550"],
    ["compare", "singlet", "--wavelength", "550"],
    ["psfmap", "singlet", "--wavelengths", "0.5", "550"],
    ["doe", "report", "x.npy", "--pitch", "0.001", "--wavelength", "550"],
])
def test_every_cli_wavelength_option_uses_the_one_check(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "nanometres" in err and "not a plausible wavelength" in err


@pytest.mark.parametrize("argv,flag", [
    (["psf", "singlet", "--doe-pitch", "1"], "--doe-pitch"),
    (["psf", "singlet", "--sensor-pitch", "3"], "--sensor-pitch"),
    (["compare", "singlet", "--doe-pitch", "2"], "--doe-pitch"),
    (["psfmap", "singlet", "--doe-pitch", "1"], "--doe-pitch"),
    (["doe", "report", "x.npy", "--pitch", "1"], "--pitch"),
])
def test_every_cli_pitch_option_uses_the_one_check(argv, flag, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert flag in err and "mm" in err and "µm" in err and "not µm" in err


def test_python_api_refuses_nanometres_at_every_entry():
    """Before: `hl.psf(..., [550])` failed with an unrelated node-grid message."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import load_lens, resolve_lens_path
    from raywave.lens.sources import point_source_rays

    lens = load_lens(resolve_lens_path("cooke_triplet"))
    with pytest.raises(ValueError, match="nanometres"):
        lens.paraxial(587.6)
    with pytest.raises(ValueError, match="nanometres"):
        point_source_rays(lens, (0.0, 0.0), [587.6])
    hl = load_hybrid("singlet")
    for call in (lambda: hl.psf((0.0, 0.0), [550]), lambda: hl.psf_result((0.0, 0.0), 550),
                 lambda: hl.doe_fields((0.0, 0.0), [0.5, 550])):
        with pytest.raises(ValueError, match="nanometres"):
            call()


def test_lens_construction_and_files_refuse_nanometres(tmp_path):
    from raywave.io import read_lens_spec
    from raywave.lens.build import ideal_lens, lens_from_spec, resolve_lens_path

    with pytest.raises(ValueError, match="nanometres"):
        ideal_lens(10.0, f_number=4.0, wavelengths=(550.0,))
    spec = read_lens_spec(resolve_lens_path("singlet"))
    spec["wavelengths"]["values"] = [550.0]
    p = tmp_path / "nm.json"
    p.write_text(json.dumps(spec))
    with pytest.raises(ValueError, match="wavelength"):
        lens_from_spec(read_lens_spec(p))


def test_python_api_refuses_a_pitch_in_um():
    from raywave.assembly.build import load_hybrid

    with pytest.raises(ValueError, match=r"1 mm = 1000 µm.*not µm"):
        load_hybrid("hybrid_asphere", doe_pitch=1)
    with pytest.raises(ValueError, match=r"sensor pitch.*5 mm = 5000 µm"):
        load_hybrid("hybrid_asphere", sensor_pitch=5)
