"""Issue 47 (h47b): the exit-pupil stop edge's ripple band widened by its edge waves' reach
(:func:`raywave.hybrid.coherent.stop_edge.edge_reach_zones`, :func:`~raywave.hybrid.coherent.stop_edge.ripple_band`).

Checked against the geometry it stands for, built independently here: rim images on a circle whose rim rays meet at
a focus on the sensor. The edge wave that leaves the DOE plane ``s`` outside the shadow at a rim point runs on the
straight line from that rim point's image; the sensor point it reaches, found by intersecting that line with the
sensor plane, must be the point whose reach is ``s`` in Fresnel zones ``s / sqrt(λ_m d (R − d) / R)``.
"""

import math
from pathlib import Path

import pytest
import torch

from raywave.hybrid.coherent.stop_edge import (INNER_TAIL, MAX_RIPPLE_ZONES, REACH_MARGIN, RIPPLE_ZONES, RimImages,
                                               edge_reach_zones, ripple_band, short_reach_band)

F64 = torch.float64
A, Z_E, Z_D, Z_S, LAM = 3.0, 0.0, 40.0, 45.0, 0.55e-3  # rim radius, planes (mm), wavelength in the medium (mm)


def _rim(k: int = 64, with_dirs: bool = True) -> RimImages:
    """Rim images on a circle of radius A at z = Z_E whose rays meet on the axis at the sensor plane."""
    th = torch.arange(k, dtype=F64) * (2 * math.pi / k)
    pts = torch.stack([A * torch.cos(th), A * torch.sin(th), torch.full_like(th, Z_E)], 1)
    d = torch.tensor([0.0, 0.0, Z_S], dtype=F64) - pts
    d = d / d.norm(dim=1, keepdim=True)
    return RimImages(th, pts[:, 2], pts, torch.zeros(k, dtype=F64), d if with_dirs else None)


def _landing(s: float) -> float:
    """x (mm) on the sensor of the edge wave leaving the DOE plane s mm outside the shadow at the rim point of
    azimuth 0 (a line from its image through that DOE-plane point)."""
    e = torch.tensor([A, 0.0, Z_E], dtype=F64)
    d = torch.tensor([0.0, 0.0, Z_S], dtype=F64) - e
    shadow = e + d * (Z_D - Z_E) / d[2]
    q = shadow + torch.tensor([s, 0.0, 0.0], dtype=F64)  # outward at azimuth 0: +x
    return float((e + (q - e) * (Z_S - Z_E) / (q[2] - e[2]))[0])


def _zone() -> float:
    """The DOE-plane Fresnel zone (mm) of the converging edge: sqrt(λ_m d (R − d) / R) along the rim ray."""
    r = math.hypot(A, Z_S - Z_E)
    d = r * (Z_D - Z_E) / (Z_S - Z_E)
    return math.sqrt(LAM * d * (r - d) / r)


@pytest.mark.parametrize("zones", [1.5, 4.0, 9.0])
def test_the_reach_is_where_the_edge_wave_that_lands_there_left_the_doe_plane(zones):
    """A sensor point x on the axis plane: the edge wave from the rim point on its side, ``zones`` zones outside the
    shadow, lands there (outer band); from the opposite rim point it is the inner side's tail (÷ INNER_TAIL)."""
    x = _landing(zones * _zone())
    reach = edge_reach_zones(_rim(), Z_D, Z_S, torch.tensor([x, 0.0], dtype=F64), LAM)
    # the opposite rim point (azimuth π) sends its inner tail there from the same distance inside its shadow
    assert reach == pytest.approx(zones / INNER_TAIL, rel=1e-9)
    # on the focus itself every rim point's wave is the geometric light: no reach
    assert edge_reach_zones(_rim(), Z_D, Z_S, torch.zeros(2, dtype=F64), LAM) == pytest.approx(0.0, abs=1e-9)


def test_the_crop_half_width_adds_its_projection():
    """A crop of half-width h about the focus reaches h / (m · zone) along the axes' normals (|n_x| + |n_y| = 1
    there), divided by INNER_TAIL on the inner side."""
    m = (Z_S - Z_E) / (Z_D - Z_E)
    h = 3 * m * _zone()
    reach = edge_reach_zones(_rim(256), Z_D, Z_S, torch.zeros(2, dtype=F64), LAM, half=h)
    assert reach == pytest.approx(3.0 / INNER_TAIL * math.sqrt(2.0), rel=2e-2)  # the diagonal normals: |n_x|+|n_y| = √2


def test_the_band_widens_from_ripple_zones_up_to_its_cap():
    """``ripple_band``: at most RIPPLE_ZONES where the reach + REACH_MARGIN is within it (:func:`short_reach_band`:
    the reach + REACH_TAIL_ZONES, at least RIPPLE_MIN_ZONES), RIPPLE_ZONES where it is unknown (no ray directions),
    reach + REACH_MARGIN beyond, at most MAX_RIPPLE_ZONES."""
    near = torch.tensor([_landing(0.5 * _zone()), 0.0], dtype=F64)
    reach = edge_reach_zones(_rim(), Z_D, Z_S, near, LAM)
    assert reach < RIPPLE_ZONES and ripple_band(_rim(), Z_D, Z_S, near, LAM) == short_reach_band(reach) <= RIPPLE_ZONES
    assert ripple_band(_rim(with_dirs=False), Z_D, Z_S, near, LAM) == RIPPLE_ZONES
    mid = torch.tensor([_landing(6.0 * INNER_TAIL * _zone()), 0.0], dtype=F64)
    assert ripple_band(_rim(), Z_D, Z_S, mid, LAM) == pytest.approx(6.0 + REACH_MARGIN, rel=1e-9)
    far = torch.tensor([_landing(40.0 * _zone()), 0.0], dtype=F64)
    assert ripple_band(_rim(), Z_D, Z_S, far, LAM) == MAX_RIPPLE_ZONES


def _bands(hl, fields, wavelengths):
    """``ripple_band`` of each source (fields (F, 2) deg × wavelengths µm) of a HybridLens at its DOE plane."""
    from raywave.hybrid.coherent.geometry import chief_rays
    from raywave.hybrid.coherent.stop_edge import stop_rim_images_all

    lens, zd, zs = hl.optics, hl.doe_z(), float(hl.sensor_z())
    f = torch.as_tensor(fields, dtype=F64).reshape(-1, 2)
    wl = torch.tensor(list(wavelengths), dtype=F64)
    _, at_sensor, _ = chief_rays(lens, f, wl, None, zd, zs)
    rims = stop_rim_images_all(lens, f, list(wavelengths), None)
    n = lens.surfaces[-1].material.n(wl)
    return [[ripple_band(rims[j][i], zd, zs, at_sensor.o[i, j, :2], float(w) * 1e-3 / float(n[j]))
             for j, w in enumerate(wavelengths)] for i in range(f.shape[0])]


def test_the_bundled_asphere_stays_within_five_zones_and_the_double_gauss_at_full_field_widens():
    """The rule keeps the bundled hybrid_asphere's 6×6 map (R, G, B) within RIPPLE_ZONES on every source (its reach
    ≤ 3.9; since h47c, 2026-12-01, the sources of short reach narrower: :func:`short_reach_band`, at least 4 zones) and
    widens the double Gauss at full field (to its reach, 8.9: the crop is the coma's cusp, lit by the inner pupil
    only)."""
    import warnings

    from raywave.assembly.build import load_hybrid
    from raywave.imaging.psfmap import field_grid
    from raywave.lens.build import bundled_lens_path

    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
        bands = _bands(hl, field_grid(hl, (6, 6)).reshape(-1, 2), (0.66, 0.53, 0.47))
        flat = [b for row in bands for b in row]
        assert all(4.0 <= b <= RIPPLE_ZONES for b in flat) and min(flat) == 4.0 and max(flat) == RIPPLE_ZONES
        dg = load_hybrid(str(Path(__file__).resolve().parent / "data" / "zmx" / "double_gauss_ohara_cdgm_hoya.zmx"),
                         sensor_pitch=3e-3, fields=[[0.0, 14.0]], field_type="angle")
        (band,), = _bands(dg, [[0.0, 14.0]], [dg.lens.primary_wavelength])
    assert 8.0 < band < 10.0


def test_many_sources_at_once_give_each_source_its_own_reach_bit_for_bit():
    """``edge_reach_many`` (issue 43: a call's sources in one pass, one host read) is the one-source rule row by row:
    the same floats as :func:`edge_reach_zones` of each (sensor points on and off the axis, both sides, with and
    without a crop half-width), None for a source without rim images or without ray directions, and rims of
    different point counts in one call."""
    from raywave.hybrid.coherent.stop_edge import edge_reach_many

    rims = [_rim(), _rim(256), None, _rim(with_dirs=False), _rim(96), _rim()]
    pts = torch.tensor([[0.0, 0.0], [0.31, -0.2], [0.1, 0.0], [0.1, 0.0], [-1.2, 0.4], [2.5, 2.5]], dtype=F64)
    lams = [LAM, 0.47e-3, LAM, LAM, 0.66e-3, LAM]
    for half in (0.0, 0.02):
        got = edge_reach_many(rims, Z_D, Z_S, pts, lams, half)
        want = [edge_reach_zones(r, Z_D, Z_S, p, lam, half) for r, p, lam in zip(rims, pts, lams)]
        assert got[2] is None and got[3] is None
        assert got == want  # exact equality: each row's arithmetic is the one-source rule's
        assert all(isinstance(v, float) for i, v in enumerate(got) if i not in (2, 3))
