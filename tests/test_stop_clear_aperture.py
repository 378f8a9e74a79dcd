"""A stop with its own clear aperture smaller than the system aperture makes it (.zmx: ENPD with a smaller CLAP on
the stop surface, as the database's Edmund catalogue achromats have it; docs/ray-wave.md class E): the CLAP is the
stop's hard edge, as in OpticStudio (a surface aperture vignettes whatever the system aperture says), and the ENPD
still sets the paraxial pupil (EPD, F/#). Every check is analytic: the singlet's stop lies behind a flat air surface
(stop -> entrance pupil magnification 1), so the ENPD 10 mm makes the stop 5 mm in radius, and a beam filling that
pupil passes the 3.5 mm CLAP in the fraction (3.5 / 5)² = 0.49, blocked at the stop itself."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from aperture_singlet import R_STOP, grid, parallel_rays, singlet_zmx
from raywave.io import read_lens_spec
from raywave.io.errors import LensFileWarning
from raywave.lens.build import lens_from_spec, lens_to_spec, load_lens
from raywave.lens.sources import point_source_rays

CLAP = 3.5


def _file(tmp_path, clap: float = CLAP):
    """The aperture singlet (ENPD 10, stop on the lens's front surface) with ``CLAP 0 clap 0`` on its stop; the
    file path and the line number of that CLAP."""
    text = singlet_zmx().replace("  STOP\n", f"  STOP\n  CLAP 0 {clap:g} 0\n")
    p = tmp_path / "stop_clap.zmx"
    p.write_text(text)
    line = text.splitlines().index(f"  CLAP 0 {clap:g} 0") + 1
    return p, line


def _load(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = load_lens(path)
    return lens, [w for w in caught if issubclass(w.category, LensFileWarning)]


def test_stop_clap_is_the_hard_edge_and_enpd_the_paraxial_pupil(tmp_path):
    path, line = _file(tmp_path)
    spec = read_lens_spec(path)
    assert spec["surfaces"][1]["aperture"] == {"shape": "circle", "radius": CLAP, "fixed": True}
    lens, warned = _load(path)
    assert lens.stop_index == 1 and lens.stop_radius() == CLAP and lens.pupil_stop_radius() == R_STOP
    p = lens.paraxial()
    assert p.epd == pytest.approx(2 * R_STOP, rel=1e-14)  # the ENPD, not 2 · CLAP
    assert p.fnum == pytest.approx(p.efl / (2 * R_STOP), rel=1e-14)
    # the warning names the file and the CLAP's line, and says which sets what
    msg = [str(w.message) for w in warned if "own clear aperture" in str(w.message)]
    assert len(msg) == 1 and msg[0].startswith(f"{path}:{line}: ")
    assert "system aperture sets the paraxial pupil" in msg[0] and "hard edge" in msg[0]


def test_beam_filling_the_enpd_is_cut_at_the_stop(tmp_path):
    """Parallel rays on a fine grid filling the ENPD (radius 5): the rays that pass are exactly those inside the
    CLAP, blocked at the stop (surface 1), none further on; the fraction is (CLAP / R_STOP)² to the grid's error."""
    lens, _ = _load(_file(tmp_path)[0])
    x, y = grid(step=0.01, half=R_STOP)
    inside_pupil = x * x + y * y <= R_STOP**2
    x, y = x[inside_pupil], y[inside_pupil]
    _, rec = lens.trace(parallel_rays(x, y), record=True)
    want = x * x + y * y <= CLAP**2
    before_stop, after_stop, at_image = (v.numpy() for v in (rec.valid[1], rec.valid[2], rec.valid[-1]))
    assert bool(before_stop.all())  # the flat surface in front passes the whole pupil
    assert bool((after_stop == want).all()) and bool((at_image == want).all())
    assert after_stop.mean() == pytest.approx((CLAP / R_STOP) ** 2, abs=2e-3)


def test_aiming_fills_the_real_beam(tmp_path):
    """The engine's rays fill the beam the CLAP passes: every on-axis ray of the pupil is valid and the marginal ray
    meets the stop at the CLAP's radius (the normalised pupil's rim is the stop's hard edge)."""
    lens, _ = _load(_file(tmp_path)[0])
    rays = point_source_rays(lens, (0.0, 0.0), pupil=("hexapolar", 6))
    assert bool(lens.trace(rays).valid.all())
    rim = point_source_rays(lens, (0.0, 0.0), pupil=(torch.tensor([0.0]), torch.tensor([1.0])))
    _, rec = lens.trace(rim, record=True)
    y_stop = float(rec.points[2][1].reshape(-1)[0])
    assert y_stop == pytest.approx(CLAP, abs=1e-9)


def test_clap_at_or_beyond_the_enpd_stop_changes_nothing(tmp_path):
    """A stop CLAP at least the ENPD's stop radius: the stop is the ENPD's, as before, and nothing warns."""
    lens, warned = _load(_file(tmp_path, clap=6.0)[0])
    assert lens.stop_radius() == pytest.approx(R_STOP, rel=1e-15) and lens.paraxial_stop_radius is None
    assert not [w for w in warned if "own clear aperture" in str(w.message)]


def test_round_trips_keep_the_clap_and_the_pupil(tmp_path):
    lens, _ = _load(_file(tmp_path)[0])
    spec = lens_to_spec(lens)
    assert spec["surfaces"][1]["aperture"] == {"shape": "circle", "radius": CLAP, "fixed": True}
    again = lens_from_spec(spec)
    assert again.stop_radius() == CLAP and again.paraxial().epd == pytest.approx(2 * R_STOP, rel=1e-14)
    path = tmp_path / "again.zmx"
    from raywave.lens.build import save_lens

    save_lens(lens, path)
    back, _ = _load(path)
    assert back.stop_radius() == CLAP and back.paraxial().epd == pytest.approx(2 * R_STOP, rel=1e-14)
    # a larger system aperture later still keeps the CLAP; a smaller one sizes the stop below it
    again.set_system_aperture({"epd": 12.0})
    assert again.stop_radius() == CLAP and again.paraxial().epd == pytest.approx(12.0, rel=1e-14)
    again.set_system_aperture({"epd": 4.0})
    assert again.stop_radius() == pytest.approx(2.0, rel=1e-14) and again.paraxial_stop_radius is None


def test_fixed_is_only_a_circle_key(tmp_path):
    from raywave.io.json_format import validate_spec

    spec = lens_to_spec(_load(_file(tmp_path)[0])[0])
    spec["surfaces"][0]["aperture"] = {"shape": "square", "half_width": 6.0, "fixed": True}
    with pytest.raises(Exception, match="fixed"):
        validate_spec(spec, "<spec>")
    spec["surfaces"][0]["aperture"] = {"shape": "circle", "radius": 6.0, "fixed": "yes"}
    with pytest.raises(Exception, match="fixed"):
        validate_spec(spec, "<spec>")


def test_grid_fraction_is_the_area_ratio():
    """The check's own yardstick: the grid's count inside a disc is its area ratio to the grid's error."""
    x, y = grid(step=0.01, half=R_STOP)
    r2 = x * x + y * y
    assert np.mean(r2[r2 <= R_STOP**2] <= CLAP**2) == pytest.approx((CLAP / R_STOP) ** 2, abs=2e-3)


def test_optiland_reads_the_stop_clap_alike(tmp_path):
    """Optiland 0.6.3 (an independent .zmx reader and tracer) on the same file: the same EPD and F/# (the ENPD's),
    the CLAP as the stop's radial aperture, and the same rays of a grid filling the ENPD pass, ray for ray."""
    pytest.importorskip("optiland")
    from optiland.fileio.zemax.reader.converter import ZemaxToOpticConverter
    from optiland.fileio.zemax.reader.parser import ZemaxDataParser
    from optiland.rays import RealRays

    path, _ = _file(tmp_path)
    lens, _ = _load(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o = ZemaxToOpticConverter(ZemaxDataParser(str(path)).parse()).convert()
        epd, f2 = float(np.ravel(o.paraxial.EPD())[0]), float(np.ravel(o.paraxial.f2())[0])
    stop = o.surfaces.surfaces[2]
    assert stop.is_stop and float(stop.aperture.r_max) == CLAP
    p = lens.paraxial()
    assert p.epd == pytest.approx(epd, rel=1e-14) and p.fnum == pytest.approx(f2 / epd, rel=1e-6)
    x, y = grid(step=0.05, half=R_STOP)
    keep = x * x + y * y <= R_STOP**2
    x, y = x[keep], y[keep]
    n = x.size
    rays = RealRays(x, y, np.full(n, -1.0), np.zeros(n), np.zeros(n), np.ones(n), np.ones(n),
                    np.full(n, lens.primary_wavelength))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o.surfaces.trace(rays, skip=1)
    theirs = np.asarray(rays.i) > 0
    ours = lens.trace(parallel_rays(x, y)).valid.numpy()
    assert bool((ours == theirs).all()) and ours.mean() == pytest.approx((CLAP / R_STOP) ** 2, abs=1e-2)


def test_the_edmund_catalogue_file():
    """The database's Edmund 32-303 (tests/data/opticsdatabase): ENPD 6.25 and the stop's CLAP 2.8125 (line 44):
    the stop's hard edge 2.8125 mm, the paraxial EPD 6.25 mm, F/3.2 (EFL 19.999 mm), the warning at line 44."""
    from pathlib import Path

    path = Path(__file__).resolve().parent / "data" / "opticsdatabase" / "Edmund 32-303.zmx"
    lens, warned = _load(path)
    p = lens.paraxial()
    assert lens.stop_radius() == 2.8125 and lens.pupil_stop_radius() == pytest.approx(3.125, rel=1e-15)
    assert p.epd == 6.25 and p.fnum == pytest.approx(19.999164535792882 / 6.25, rel=1e-12)
    assert [str(w.message) for w in warned if "own clear aperture" in str(w.message)][0].startswith(f"{path}:44: ")
    # the paraxial comparison model's thin lens takes the beam's pupil (the stop at the first vertex: the CLAP)
    from raywave.assembly.build import load_hybrid
    from raywave.models.paraxial import ParaxialModel

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(path)
    assert ParaxialModel(hl).thin_lens()[1] == pytest.approx(2.8125, rel=1e-14)
