"""Issue 47, class C (h47c, 2026-12-01): the caustic fallback also moves the Fresnel step's plane back where the rays
past the stop's rim fold within the edge's ripple band (:func:`raywave.hybrid.coherent.exit_pupil._band_cut`,
``go_phase_errors(band_fold=True)``). The Fresnel step multiplies the geometric field continued past the rim over
that band; at a fold it is singular and beyond it there is none. The Olympus M.Zuiko 12 mm F/2 (tests/data/
opticsdatabase, MIT) at 0.7 field: the rays past the compressed side's rim fold 0.39 / 0.21 / 0.07 mm outside the
shadow 6.0 / 4.0 / 2.2 mm before the sensor (~6.5 / 4.3 / 2 zones); on its default plane (2.2 mm) the Fresnel step
was 1.80e-3 from the converged Huygens PSF, built 2.4 mm before it and carried by the angular spectrum 4.88e-4
(benchmarks/results/stop_edge_band_fold_2026-12-01_xxv_h47c.json)."""

import math
import warnings
from pathlib import Path

import pytest
import torch

from raywave.hybrid.coherent import exit_pupil as xp

FILE = Path(__file__).resolve().parent / "data" / "opticsdatabase" / "Olympus M.Zuiko 12mm F2.0.zmx"


def _cut(lens, field, wl: float, z_xp: float, zs: torch.Tensor) -> torch.Tensor:
    """:func:`_band_cut` of one source on the planes ``zs`` (P,) mm: (P,) bool."""
    f = torch.tensor([field], dtype=torch.float64)
    with torch.no_grad():
        return xp._band_cut(lens, f, [wl], (None, lens.field_type, None), zs[None], [z_xp])[0, 0]


def test_an_ideal_lens_band_never_folds():
    """An ideal lens's rays past the rim meet only at its focus: no plane before the focus is cut, in or out of
    focus (analytic: straight lines through one point)."""
    from raywave.lens.build import ideal_lens

    lens = ideal_lens(2.0, f_number=8.0, wavelengths=(0.53,))
    zs = torch.linspace(0.05, 1.95, 20, dtype=torch.float64)
    for fld in ((0.0, 0.0), (0.0, 3.0)):
        assert not bool(_cut(lens, fld, 0.53, 0.0, zs).any())


def test_the_olympus_band_folds_towards_the_focus_only(monkeypatch):
    """The Olympus at 0.7 field, planes 6.0 to 0.2 mm before the sensor: cut from ~1.8 mm before the default plane
    (2.2 mm before the sensor) on, never again uncut towards the focus (monotone), and not 6 mm before the sensor
    (the fold ~6.5 zones out, beyond the 5-zone band), where the plain Fresnel step holds (3.42e-4)."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import load_lens

    monkeypatch.setenv("RAYWAVE_MEMORY_LIMIT", "16GiB")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = load_lens(FILE)
        fld = (0.0, 0.7 * max(abs(float(f)) for f in lens.fields))
        hl = load_hybrid(FILE, sensor_pitch=3e-3, fields=[list(fld), [0.0, 0.0]], field_type=lens.field_type)
    wl = hl.lens.primary_wavelength
    z_xp = hl._exit_pupil_planes([wl])[0]
    z_s = hl.sensor_z()
    before = torch.tensor([6.0, 5.0, 4.5, 4.0, 3.5, 3.0, 2.2, 1.5, 1.0, 0.5, 0.2], dtype=torch.float64)
    cut = _cut(hl.lens, fld, wl, z_xp, z_s - before).tolist()
    assert not cut[0] and cut[6:] == [True] * 5
    first = cut.index(True)
    assert all(cut[first:])  # monotone towards the focus
    assert 2.2 < float(before[first]) <= 4.5
    # the engine's fallback takes the nearest plane before the cut ones (the caustic rule finds none: its estimate
    # exceeds the tolerance everywhere on this wide angle, 1.2e-3 – 1.6e-3 rad)
    zs, err = xp.go_phase_errors(hl.lens, torch.tensor([fld], dtype=torch.float64), [wl], None, None,
                                 ([z_xp], hl.doe_z()), band_fold=True)
    z_from, est = xp.go_fallback_plane(hl.lens, None, z_xp, hl.doe_z(), (zs[0], err[0, 0]))
    assert math.isinf(est) and z_from is not None and 1.8 < hl.doe_z() - z_from < 3.0
