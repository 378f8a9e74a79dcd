"""Clipping apertures at the semi-diameters (``load_lens(..., clip_apertures=True)``, ``--clip-apertures``): a
semi-diameter alone does not clip (OpticStudio's convention); made a hard aperture it vignettes an off-axis beam by
the overlap of two circles, checked against the analytic lens-shaped area."""

import math
import warnings
from pathlib import Path

import pytest
import torch

from raywave.lens.build import lens_from_spec, load_lens, clip_at_semi_diameters
from raywave.lens.sources import point_source_rays

DATA = Path(__file__).resolve().parent / "data" / "opticsdatabase"

#: the system: a window of semi-diameter R1, a gap T, the stop (radius RS) with an ideal lens
R1, T, RS = 1.5, 10.0, 1.0


def _spec(field_deg: float) -> dict:
    return {
        "format": "raywave-lens", "version": 1, "object": {"distance": "inf"},
        "fields": {"type": "angle", "values": [0.0, field_deg]},
        "wavelengths": {"values": [0.55], "primary": 0},
        "surfaces": [
            {"type": "standard", "radius": "inf", "thickness": T, "material": "air", "semi_diameter": R1},
            {"type": "paraxial", "focal_length": 50.0, "thickness": 50.0, "material": "air",
             "aperture": {"shape": "circle", "radius": RS}, "stop": True},
        ],
    }


def _overlap(r1: float, r2: float, d: float) -> float:
    """Area (mm²) common to two discs of radii r1, r2 whose centres are d apart (the lens-shaped intersection)."""
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a1 = r1 * r1 * math.acos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
    a2 = r2 * r2 * math.acos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
    return a1 + a2 - 0.5 * math.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2))


def _transmitted(lens, field_deg: float, n: int = 401) -> float:
    """Fraction of a uniform pupil grid's rays (n × n over the entrance pupil's disc) that reach the image."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rays = point_source_rays(lens, (0.0, field_deg), 0.55, pupil=("grid", n))
        out = lens.trace(rays)
    return float(out.valid.double().mean())


def test_spec_gets_circular_apertures_at_the_semi_diameters_only_where_none_is():
    spec = _spec(5.0)
    out = clip_at_semi_diameters(spec)
    assert out["surfaces"][0]["aperture"] == {"shape": "circle", "radius": R1}
    assert out["surfaces"][1]["aperture"] == {"shape": "circle", "radius": RS}  # the stop keeps its own
    assert spec["surfaces"][0].get("aperture") is None  # the input is not changed


@pytest.mark.parametrize("field_deg", [0.0, 3.5, 5.0, 9.0])
def test_clipping_aperture_vignettes_by_the_two_circles_overlap(field_deg):
    """The window T before the stop sees the collimated beam (radius RS) shifted by T·tan θ: the transmitted
    fraction is the overlap of that disc with the window's (radius R1) over π RS² (analytic). Without clear apertures
    nothing is vignetted. A uniform 401² pupil grid counts the fraction to within 6e-5 here (2e-4 on 201²)."""
    plain = lens_from_spec(_spec(field_deg))
    clear = lens_from_spec(clip_at_semi_diameters(_spec(field_deg)))
    expected = _overlap(R1, RS, T * math.tan(math.radians(field_deg))) / (math.pi * RS * RS)
    assert _transmitted(plain, field_deg) == 1.0
    assert abs(_transmitted(clear, field_deg) - expected) < 5e-4, expected  # 3.5°: 0.965 passes, 9°: 0.379


@pytest.fixture(scope="module")
def nikkor():
    """The Nikkor Z 50 mm F/1.2 S read plainly and with ``clip_apertures`` (its fields are solved on reading)."""
    path = DATA / "Nikon Nikkor Z 50mm f1.2 S.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lens(path), load_lens(path, clip_apertures=True)


def test_load_lens_clip_apertures_keeps_the_on_axis_beam_and_vignettes_off_axis(nikkor):
    """A camera lens file whose semi-diameters are its elements' clear apertures (Nikon Nikkor Z 50 mm F/1.2 S): on
    axis every ray passes either way; at full field 93 % of the rays pass outside the elements unclipped, 36 % with
    the clear apertures (the mounts' cat's-eye vignetting of a fast lens; measured on 101² pupil grids)."""
    plain, clear = nikkor
    full = max(float(f) for f in plain.fields)
    assert _transmitted(clear, 0.0, 101) > 0.999
    assert _transmitted(plain, full, 101) > 0.9
    assert 0.3 < _transmitted(clear, full, 101) < 0.45


def test_memory_refusal_names_the_clip_apertures_option(monkeypatch, nikkor):
    """A refused DOE grid of a lens whose rays pass outside its semi-diameters names ``clip_apertures``: those
    rays, steep behind the lens, set the default DOE's Nyquist pitch (the Nikkor Z 50 mm F/1.2 at full field)."""
    from raywave.assembly.build import load_hybrid
    from raywave.utils.errors import MemoryLimitError

    monkeypatch.setenv("RAYWAVE_MEMORY_LIMIT", "1MB")
    path = DATA / "Nikon Nikkor Z 50mm f1.2 S.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full = max(float(f) for f in nikkor[0].fields)
        with pytest.raises(MemoryLimitError, match="clip_apertures=True") as err:
            load_hybrid(path, fields=[[0.0, full]], field_type="angle")
    assert "--clip-apertures" in str(err.value) and "semi-diameter" in str(err.value)


def test_cli_clip_apertures_changes_the_off_axis_spot(capsys):
    """``raywave spot --clip-apertures``: the Nikkor Z 50 mm F/1.2's full-field spot loses the rays that passed
    outside its elements (its RMS radius changes), the on-axis one is the same."""
    import json

    from raywave.cli.main import main

    path = str(DATA / "Nikon Nikkor Z 50mm f1.2 S.zmx")
    out = []
    for extra in ([], ["--clip-apertures"]):
        assert main(["spot", path, "--json", "--quiet", *extra]) == 0
        out.append(json.loads(capsys.readouterr().out)["rms_radius"])
    assert out[0][0] == pytest.approx(out[1][0], rel=1e-9)  # on axis: every ray passes either way
    assert abs(out[0][-1][1] - out[1][-1][1]) > 0.05 * out[0][-1][1]


def test_psf_with_clip_apertures_of_a_lens_whose_beams_fit_them():
    """``raywave psf --clip-apertures`` (``compute_psf(..., clip_apertures=True)``): the bundled asphere's beams lie
    inside its semi-diameters (3.0 / 3.5 mm), so its surfaces get hard apertures and the PSF is the same."""
    from raywave.cli.psf_commands import compute_psf

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clear = compute_psf("hybrid_asphere", ks=16, clip_apertures=True)
        plain = compute_psf("hybrid_asphere", ks=16)
    radii = [float(s.aperture.radius) for s in clear["hybrid"].lens.surfaces if s.aperture is not None]
    assert radii == [1.0, 3.0, 3.5]
    assert [s.aperture is None for s in plain["hybrid"].lens.surfaces] == [False, True, True]
    assert abs(clear["psf"] - plain["psf"]).max() == 0.0


def _asphere_with_semi_diameters(tmp_path, sd: float) -> Path:
    """The bundled hybrid asphere's file with its two lens surfaces' semi-diameters set to ``sd`` mm."""
    import json

    from raywave.lens.build import bundled_lens_path

    spec = json.loads(bundled_lens_path("hybrid_asphere").read_text())
    for s in spec["surfaces"]:
        if "semi_diameter" in s:
            s["semi_diameter"] = sd
    out = tmp_path / "asphere.json"
    out.write_text(json.dumps(spec))
    for name in ("doe_phase.npy",):  # the DOE's phase file, if the bundled lens names one beside it
        src = bundled_lens_path("hybrid_asphere").parent / name
        if src.exists():
            (tmp_path / name).write_bytes(src.read_bytes())
    return out


def test_apertures_at_the_beams_rim_leave_the_on_axis_psf_unchanged(tmp_path):
    """Clipping apertures raised to the on-axis beam's rim (semi-diameters of 0.1 mm, far inside the beam): on axis
    they block no ray, and the default PSF (exit-pupil edge) is the PSF without them bit for bit; before, the edge's
    ripple band, built on virtual rays past the stop's rim, was cut at them. Off axis (14°) they vignette the
    beam: less power reaches the DOE."""
    from raywave.assembly.build import load_hybrid

    path = _asphere_with_semi_diameters(tmp_path, 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = load_hybrid(path)
        clipped = load_hybrid(path, clip_apertures=True)
        radii = [float(s.aperture.radius) for s in clipped.lens.surfaces[1:]]
        assert radii == pytest.approx([1.0, 0.4676], abs=1e-3)  # raised to the on-axis beam's rim, not 0.1 mm
        with torch.no_grad():
            a = plain.psf((0.0, 0.0), 0.53, ks=32)
            b = clipped.psf((0.0, 0.0), 0.53, ks=32)
            pa = plain.doe_fields((0.0, 14.0), [0.53])[0][0].power
            pb = clipped.doe_fields((0.0, 14.0), [0.53])[0][0].power
    assert torch.equal(a, b)
    assert float(pb) < 0.95 * float(pa)
