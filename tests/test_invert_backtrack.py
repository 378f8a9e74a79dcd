"""Issue 47, class C (h47c, 2026-12-01): the node inversion (:func:`raywave.hybrid.coherent.tracing._invert_to_nodes`)
halves a step that lands on an untraceable ray back towards its last traced iterate instead of giving the node up.
The Olympus M.Zuiko 12 mm F/2 (tests/data/opticsdatabase, MIT) at 0.7 field (31.9°) with a DOE plane 6 mm before the
sensor: on the beam's stretched side the ray map's magnification grows ~5× across the stop's rim, Newton's step from
the coarse start overshoots past the rays that still trace (they miss the rear group beyond ~1.28 of the stop's
radius), and the nodes from 0.954 of the stop's radius outwards were lost: the beam's last rim strip and its whole
ripple band there (3.99e-4 from the converged Huygens PSF; 3.42e-4 with the backtracking)."""

import math
import warnings
from pathlib import Path

import pytest
import torch

from raywave.hybrid.coherent import tracing
from raywave.hybrid.coherent.accurate import entrance_pupil
from raywave.hybrid.coherent.tracing import _Aim, _invert_to_nodes, rays_through, run_serial

FILE = Path(__file__).resolve().parent / "data" / "opticsdatabase" / "Olympus M.Zuiko 12mm F2.0.zmx"


@pytest.fixture(scope="module")
def olympus():
    from raywave.lens.build import load_lens

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = load_lens(FILE)
    return lens


def _aim_and_chief(lens, z_doe: float):
    """The 0.7-field source's :class:`_Aim` on the plane ``z_doe`` and its chief ray ``(uv, X, ∂X/∂uv)``."""
    fld = torch.tensor([0.0, 0.7 * max(abs(float(f)) for f in lens.fields)], dtype=torch.float64)
    wl = torch.tensor([lens.primary_wavelength], dtype=torch.float64)
    ep_z, r_ep = entrance_pupil(lens)
    aim = _Aim(lens, fld, wl, None, z_doe, "angle", 1e-6 * r_ep, ep_z)
    uv_c = torch.zeros(1, 2, dtype=torch.float64)
    x_c, _, jac_c = run_serial(aim.landing(uv_c))
    return aim, (uv_c, x_c, jac_c), r_ep


def _meridional_rim_landing(lens, aim, frac: float) -> float:
    """The DOE-plane height (mm) of the meridional ray through ``frac`` of the stop's radius on its stretched (+y)
    side (bisection on the entrance-plane v)."""
    stop_r = float(lens.surfaces[lens.stop_index].aperture.radius)
    lo, hi = 0.0, 4.4  # entrance-plane v (mm): the stop's +y rim lies between (traced: 1.29 of the radius at 4.4)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        uv = torch.tensor([[[[0.0, mid]]]], dtype=torch.float64)[0]
        rays = rays_through(lens, uv, aim.field[None], "angle", aim.wavelength.reshape(1, 1, 1), ep_z=aim.ep_z)
        _, rec = lens.trace(rays, apertures=False, record=True)
        y = float(rec.points[lens.stop_index + 1][1].reshape(-1)[0])
        lo, hi = (mid, hi) if y < frac * stop_r else (lo, mid)
    uv = torch.tensor([[[[0.0, lo]]]], dtype=torch.float64)[0]
    rays = rays_through(lens, uv, aim.field[None], "angle", aim.wavelength.reshape(1, 1, 1), ep_z=aim.ep_z)
    out = lens.trace(rays, apertures=False)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    return float(out.propagate_to_z(aim.z_doe, n).o[..., 1].reshape(-1)[0])


@pytest.mark.parametrize("halvings, converged", [(0, False), (tracing.BACKTRACK_HALVINGS, True)])
def test_inversion_reaches_the_stretched_rim_only_with_backtracking(olympus, monkeypatch, halvings, converged):
    """Targets on the DOE plane 6 mm before the sensor at the landings of the meridional rays through 0.97 / 1.0 /
    1.05 / 1.1 of the stop's radius (each traceable) from the chief ray's linear guess with the construction's step
    limit (a quarter of the entrance pupil's radius): without backtracking Newton's steps overshoot onto rays that
    miss a surface and nodes are lost; with it every node converges onto its own ray."""
    lens = olympus
    with torch.no_grad():
        z_doe = float(lens.vertex_z()[-1]) + 9.0  # 6.04 mm before the image plane
        aim, chief, r_ep = _aim_and_chief(lens, z_doe)
        ys = [_meridional_rim_landing(lens, aim, f) for f in (0.97, 1.0, 1.05, 1.1)]
        assert ys == sorted(ys)  # the stretched side: no fold among them
        targets = torch.tensor([[0.0, y] for y in ys], dtype=torch.float64)
        monkeypatch.setattr(tracing, "BACKTRACK_HALVINGS", halvings)
        uv, conv, _, x = run_serial(_invert_to_nodes(aim, targets, chief, 0.25 * r_ep))
    assert bool(conv.all()) is converged
    if converged:
        assert float((x - targets).abs().max()) < 1e-9
