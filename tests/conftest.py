import math

import pytest
import torch

from raywave.lens.build import load_lens, resolve_lens_path
from raywave.lens.lens import Lens
from raywave.materials.base import Air, ConstantIndex
from raywave.surfaces.aperture import CircularAperture
from raywave.surfaces.geometry import EvenAsphere, Standard
from raywave.surfaces.surface import Surface


def std(radius, thickness, n=1.0, stop=False, ap=None, conic=0.0):
    """A standard surface with a constant-index medium after it (test helper)."""
    c = 0.0 if radius == math.inf else 1.0 / radius
    mat = Air() if n == 1.0 else ConstantIndex(n)
    return Surface(Standard(c, conic), mat, thickness, aperture=CircularAperture(ap) if ap else None, is_stop=stop)


@pytest.fixture
def cooke_const():
    """The classic Cooke triplet (Zemax sample prescription) with constant indices n_d."""
    s = [
        std(22.01359, 3.25896, 1.6204),
        std(-435.7604, 6.007551),
        std(-22.21328, 0.9994, 1.6034),
        std(20.29192, 4.750409, stop=True, ap=4.5),
        std(79.68364, 2.952076, 1.6204),
        std(-18.3783, 42.20778),
    ]
    return Lens(s, fields=[0.0, 14.0, 20.0])


@pytest.fixture
def asphere_const():
    """An aspheric singlet (n = 1.5) with a stop in front."""
    s = [
        std(math.inf, 0.1, stop=True, ap=1.0),
        Surface(EvenAsphere(1 / 4.7531, -1.2051, [0.0, 5.33e-4, 1.12e-5, -3.75e-7]), ConstantIndex(1.5), 7.5),
        std(-15.65, 5.0),
    ]
    return Lens(s, fields=[0.0, 5.0])


def _devices():
    return ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]


@pytest.fixture(params=_devices())
def device(request):
    """The torch devices to run a core test on: "cpu", and "cuda" where a GPU is present (cf. Optiland's
    backend fixture)."""
    return request.param


@pytest.fixture(scope="session")
def tiny_lens_file(tmp_path_factory):
    """A tiny lens file for training tests: ideal f = 2 mm, F/8, a 0.2 mm sensor of 2 µm pixels (tiny.json)."""
    from raywave.io import write_lens_spec
    from raywave.lens.build import ideal_lens, lens_to_spec

    d = tmp_path_factory.mktemp("tiny_lens")
    lens = ideal_lens(2.0, f_number=8.0, wavelengths=(0.55,))
    lens.set_sensor((0.2, 0.2), (100, 100))
    write_lens_spec(lens_to_spec(lens), d / "tiny.json")
    return d / "tiny.json"


@pytest.fixture(scope="module")
def cooke():
    """The bundled Cooke triplet (``cooke_triplet``), loaded once per test module."""
    return load_lens(resolve_lens_path("cooke_triplet"))


@pytest.fixture(scope="module")
def optiland_cooke(cooke):
    """The same Cooke triplet built in optiland (skips where optiland is absent), fields 0 / 14 / 20°."""
    pytest.importorskip("optiland")
    from optiland_bridge import optiland_lens  # lazy: optiland is a test-only dependency

    return optiland_lens(cooke, cooke.primary_wavelength, [0.0, 14.0, 20.0])
