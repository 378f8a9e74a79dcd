"""Issue 45: ray fans, OPD maps and their Zernike fit, against optiland on the Cooke triplet (same media, same stop
size, fully aimed rays) and against analytic wavefronts."""

import json
import math
import warnings

import numpy as np
import pytest
import torch

from raywave.cli.main import main
from raywave.lens.fans import opd_fan, ray_fan
from raywave.lens.opd import OPDMap, fringe_index, noll_index, opd_map, square_pupil_grid, zernike_fit, zernike_term
from raywave.rays.pupil import hexapolar


def test_ray_fan_matches_optiland(cooke, optiland_cooke):
    """Tangential and sagittal fans (21 rays, relative to the chief ray) at 0 / 14 / 20°: optiland's to 1e-6 mm
    (its iterative aiming's tolerance)."""
    from optiland.analysis import RayFan

    wl = cooke.primary_wavelength
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theirs = RayFan(optiland_cooke, fields="all", wavelengths=[wl], num_points=21)
    ours = ray_fan(cooke, [0.0, 14.0, 20.0], [wl], n=21)
    for i, fp in enumerate(theirs.fields):
        d = theirs.data[f"{fp.coord}"][f"{wl}"]
        assert ours.ey[i, 0].numpy() == pytest.approx(np.asarray(d["y"]), abs=1e-6)
        assert ours.ex[i, 0].numpy() == pytest.approx(np.asarray(d["x"]), abs=1e-6)
    assert float(ours.ey[2, 0].abs().max()) > 0.02  # 20°: tens of µm of aberration, not a trivial zero


@pytest.mark.parametrize("ordering", ["fringe", "noll"])
def test_zernike_fit_matches_optiland(cooke, optiland_cooke, ordering):
    """OPD on optiland's hexapolar 15-ring sampling and the 16-term fit: coefficients to 1e-4 waves on axis and at
    full field (measured 1.5e-9 / 2e-5)."""
    from optiland.wavefront import ZernikeOPD

    wl = cooke.primary_wavelength
    px, py = hexapolar(15)
    for hy, f in ((0.0, 0.0), (1.0, 20.0)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            theirs = ZernikeOPD(optiland_cooke, (0.0, hy), wl, num_rings=15, zernike_type=ordering, num_terms=16)
        fit = zernike_fit(opd_map(cooke, (0.0, f), wl, pupil=(px, py)), 16, ordering)
        assert fit.coefficients.numpy() == pytest.approx(np.asarray(theirs.coeffs), abs=1e-4)


def test_zernike_orderings_and_orthonormality():
    assert [fringe_index(j) for j in (1, 2, 3, 4, 5, 9, 16, 25, 36)] == [
        (0, 0), (1, 1), (1, -1), (2, 0), (2, 2), (4, 0), (6, 0), (8, 0), (10, 0)]
    assert [noll_index(j) for j in range(1, 12)] == [
        (0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3), (3, 3), (4, 0)]
    # Noll terms have unit RMS and are orthogonal over the disk (a fine grid's mean)
    px, py = square_pupil_grid(401)
    k = px * px + py * py <= 1
    z = torch.stack([zernike_term(j, px[k], py[k], "noll") for j in range(1, 16)])
    gram = z @ z.T / k.sum()
    assert gram == pytest.approx(torch.eye(15, dtype=torch.float64), abs=0.02)


def test_zernike_fit_recovers_a_known_wavefront():
    px, py = square_pupil_grid(41)
    true = {4: 0.3, 7: -0.12, 9: 0.05}  # Fringe defocus, coma x, spherical (waves)
    w = sum(c * zernike_term(j, px, py, "fringe") for j, c in true.items())
    inside = px * px + py * py <= 1
    m = OPDMap(torch.where(inside, w, torch.nan), px, py, inside, (0.0, 0.0), 0.55)
    fit = zernike_fit(m, 16, "fringe")
    want = torch.zeros(16, dtype=torch.float64)
    for j, c in true.items():
        want[j - 1] = c
    assert fit.coefficients == pytest.approx(want, abs=1e-12) and fit.residual_rms < 1e-12


def test_on_axis_opd_is_the_seidel_defocus_and_spherical(cooke):
    """On axis the OPD fan is even in the pupil and the tangential and sagittal fans agree (rotational symmetry)."""
    f = opd_fan(cooke, [0.0], n=21)
    assert f.w_t[0] == pytest.approx(f.w_s[0], abs=1e-9)
    assert f.w_t[0] == pytest.approx(f.w_t[0].flip(-1), abs=1e-9)
    assert float(f.w_t[0, 1, 10]) == pytest.approx(0.0, abs=1e-9)  # the chief ray: zero OPD


def test_fan_and_opd_cli(tmp_path, capsys):
    png = tmp_path / "fan.png"
    assert main(["fan", "cooke_triplet", "--field", "0", "--field", "20", "--json", "-o", str(png)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert len(d["ey"]) == 2 and len(d["ey"][0]) == 3 and png.stat().st_size > 10_000
    png = tmp_path / "opd.png"
    assert main(["opd", "cooke_triplet", "--field", "0,20", "--zernike", "16", "--json", "-o", str(png)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert len(d["zernike"]) == 16 and d["rms"] > 0.1 and png.stat().st_size > 10_000 and not math.isnan(d["rms"])
    assert main(["opd", "cooke_triplet", "--field", "0", "--field", "20"]) == 2
    assert "one field" in capsys.readouterr().err
