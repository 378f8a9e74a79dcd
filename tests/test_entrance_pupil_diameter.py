"""The aiming's entrance-pupil diameter (:func:`raywave.lens.paraxial.entrance_pupil_diameter`, issue 43: the
aiming asked ~10 times per PSF call for the whole first-order data) is the float that the whole data give
(:func:`~raywave.lens.paraxial.paraxial_data`'s ``epd``), on lenses with the stop first and inside, distant and
finite objects, and lens files of the public corpus; where a stop's own clear aperture cuts the beam inside the
system aperture's pupil (a .zmx stop's CLAP, class E), the beam's image of it."""

import warnings
from pathlib import Path

import pytest

from raywave.lens.build import bundled_lens_path, load_lens
from raywave.lens.paraxial import entrance_pupil_diameter, paraxial_data

CORPUS = Path(__file__).resolve().parent / "data" / "opticsdatabase"  # the bundled subset of the public corpus


def _corpus():
    return [pytest.param(f, id=f.stem) for f in sorted(CORPUS.glob("*.zmx"))]


@pytest.mark.parametrize("name", ["hybrid_asphere", "singlet", "cooke_triplet", "double_gauss", "asphere_hk51"])
def test_bundled_lenses(name):
    lens = load_lens(bundled_lens_path(name))
    for wl in (None, 0.47, 0.66):
        want = paraxial_data(lens, lens.primary_wavelength if wl is None else wl).epd
        assert entrance_pupil_diameter(lens, wl) == want


@pytest.mark.parametrize("path", _corpus())
def test_corpus_lenses(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the files' reading notes: tests/test_lens_files_opticsdatabase.py
        try:
            lens = load_lens(path)
        except ValueError as e:  # a file refused with a named error: tested there too
            pytest.skip(f"refused: {e}")
    epd = paraxial_data(lens, lens.primary_wavelength).epd
    if lens.paraxial_stop_radius is None:
        assert entrance_pupil_diameter(lens) == epd
    else:  # the stop's own CLAP cuts the beam (Edmund 32-303, class E): the rays fill its image, the paraxial EPD
        # is the system aperture's
        assert entrance_pupil_diameter(lens) == pytest.approx(epd * lens.stop_radius() / lens.pupil_stop_radius(),
                                                              rel=1e-14)
