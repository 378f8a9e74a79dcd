"""The blank DOE given to a lens file without one takes the pitch that samples the wavefront (issue 19):
``NYQUIST_FILL`` × the Nyquist pitch of the steepest phase slope relative to the chief ray, over every field and
wavelength asked for, instead of a fixed 1 µm that aliases for a fast lens (and wastes pixels on a slow one)."""

import json
import math
import warnings

import pytest

from raywave.cli.main import main
from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens, SamplingWarning, load_hybrid
from raywave.hybrid.build import NYQUIST_FILL, nyquist_doe_pitch
from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")


def test_an_ideal_fast_lens_gets_the_nyquist_pitch_of_its_marginal_ray():
    """An ideal F/1.3 lens on axis: the marginal ray's slope relative to the chief ray is sin θ = 1/sqrt(1 + 4N²),
    so the pitch is 0.8·λ/(2 sin θ) rounded down to 2 digits (0.55 µm: 0.59 µm, finer than the former 1 µm)."""
    lens = ideal_lens(5.0, f_number=1.3, wavelengths=(0.55,))
    p = nyquist_doe_pitch(lens, 2.5, fields=[0.0, 0.0])
    want = NYQUIST_FILL * 0.55e-3 / (2 / math.sqrt(1 + 4 * 1.3**2))
    assert p <= want and p == pytest.approx(want, rel=0.02)
    assert p < 1e-3


@pytest.mark.slow  # CI time (README: Slow suite)
def test_the_chosen_pitch_samples_every_field_and_wavelength_without_warning():
    """A fast lens: the bundled asphere with its stop opened to F/2 (1 µm would alias: the former default).
    At the chosen pitch no field of the lens at any of its wavelengths warns; at 1 µm the edge of the field does."""
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    lens.surfaces[0].aperture.set_radius(2.0)
    fields = [[0.0, f] for f in lens.fields]
    p = nyquist_doe_pitch(lens, 0.7, fields=fields)
    assert p < 1e-3
    with warnings.catch_warnings():
        warnings.simplefilter("error", SamplingWarning)
        HybridLens(lens, BlankDOE(round(8.0 / p), p), 0.7, sensor_pitch=3e-3).doe_fields(
            fields, lens.wavelengths, rays=24, check=True)
    with pytest.warns(SamplingWarning, match="too coarse"):
        HybridLens(lens, BlankDOE(8000, 1e-3), 0.7, sensor_pitch=3e-3).doe_fields(fields, lens.wavelengths, rays=24)


def test_load_hybrid_records_the_rule_and_psf_json_reports_it(capsys):
    hl = load_hybrid(bundled_lens_path("asphere_hk51"))
    info = hl.doe_info
    assert info["source"] == "default" and info["pitch_rule"] == "nyquist"
    assert info["pitch"] == pytest.approx(nyquist_doe_pitch(hl.lens, info["distance"]))
    assert load_hybrid(bundled_lens_path("asphere_hk51"), doe_pitch=2e-3).doe_info["pitch_rule"] == "given"
    assert load_hybrid(bundled_lens_path("hybrid_asphere")).doe_info["pitch_rule"] == "file"
    assert main(["psf", "singlet", "--ks", "8", "--rays", "16", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)["doe"]
    assert d["pitch_rule"] == "nyquist" and 2e-3 < d["pitch_mm"] < 5e-3  # F/10: a few µm, not 1 µm
