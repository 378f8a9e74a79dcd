"""Caustics before the DOE plane (issue 19: "works for any lens a user loads").

The accurate field is built from a one-to-one map of stop points to DOE-plane points. An aberrated beam's rays
cross before focus (a caustic); a DOE plane beyond that point got a wrong field with no warning: an f/3 double
Gauss at 14° with its default blank DOE 2.2 mm before the sensor was 0.17 rel L1 from the Huygens exit-pupil PSF
(2.4e-3 on a plane before the caustic; tests/test_stop_edge_real_lenses.py, docs/ray-wave.md). Checked here:
the fold detection (against a 1-D criterion: rays along the stop's meridian land in order until they cross), the
default plane staying before the caustic, and the warning for a plane beyond it.
"""

import math
import warnings
from pathlib import Path

import pytest
import torch

from raywave.assembly.build import CAUSTIC_MARGIN, load_hybrid
from raywave.hybrid import CausticWarning
from raywave.hybrid.coherent import doe_clippings
from raywave.lens.analysis import beam_folds, beam_rays_at, fold_fraction, pupil_grid
from raywave.lens.build import load_lens
from raywave.lens.sources import point_source_rays

DOUBLE_GAUSS = str(Path(__file__).resolve().parent / "data" / "zmx" / "double_gauss_ohara_cdgm_hoya.zmx")


def _map(fn, n=24):
    px, py, index = pupil_grid(n)
    xy = fn(torch.stack([px, py], -1))
    return fold_fraction(xy, torch.ones(px.shape, dtype=torch.bool), index, n)


def test_fold_fraction_of_simple_maps():
    """One orientation (a scaled, rotated or mirrored map) is no fold; a map that turns back on itself is."""
    assert float(_map(lambda p: 3.0 * p)) == 0.0
    rot = torch.tensor([[0.6, -0.8], [0.8, 0.6]], dtype=torch.float64)
    assert float(_map(lambda p: p @ rot.T)) == 0.0
    assert float(_map(lambda p: -p)) == 0.0  # past a focus: mirrored as a whole, still one to one
    assert float(_map(lambda p: p * torch.tensor([-1.0, 1.0], dtype=torch.float64))) == 0.0
    # x → x³ − 0.5·x folds where |x| < sqrt(1/6): ~38 % of the disc's columns (the less common orientation)
    folded = float(_map(lambda p: torch.stack([p[:, 0] ** 3 - 0.5 * p[:, 0], p[:, 1]], -1)))
    assert 0.2 < folded < 0.5


def _meridian_crosses(lens, field_deg: float, dz: float) -> bool:
    """Independent 1-D criterion: rays through the stop's y meridian land on the plane ``dz`` mm after the last
    vertex in the order of their stop coordinate unless some have crossed."""
    py = torch.linspace(-0.999, 0.999, 801, dtype=torch.float64)
    wl = torch.tensor([lens.primary_wavelength], dtype=torch.float64)
    rays = point_source_rays(lens, torch.tensor([[0.0, field_deg]], dtype=torch.float64), wl,
                             pupil=(torch.zeros_like(py), py), aim="full")
    out = lens.trace(rays)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    y = out.propagate_to_z(float(lens.vertex_z()[-1].detach()) + dz, n).o[0, 0, :, 1]
    steps = torch.diff(y)
    return bool((steps > 0).any() and (steps < 0).any())


@pytest.mark.parametrize("dz, crossed", [(50.0, False), (55.0, False), (59.0, True), (59.99, True)])
def test_beam_folds_finds_the_double_gauss_caustic(dz, crossed):
    lens = load_lens(DOUBLE_GAUSS)
    z = float(lens.vertex_z()[-1].detach()) + dz
    with torch.no_grad():
        folds = float(beam_folds(lens, [z], fields=[0.0, 14.0], wavelengths=[lens.primary_wavelength]).max())
        assert _meridian_crosses(lens, 14.0, dz) == crossed
    assert (folds > 0) == crossed


def test_the_default_blank_doe_stays_before_the_caustic():
    """The default plane moves towards focus for a wide beam (beam fit) but stops where the widest beam is still
    CAUSTIC_MARGIN × as wide as where the first rays cross; the rule and the crossing are reported. (With the
    DOE-plane edge: the default edge moves this lens's plane further back, where its Fresnel step takes no caustic
    fallback: tests/test_caustic_fallback.py.)"""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(DOUBLE_GAUSS, fields=[[0.0, 14.0], [0.0, 0.0]], field_type="angle", stop_edge="doe")
    info = hl.doe_info
    assert info["distance_rule"] == "before_caustic"
    d, dc = info["distance"], info["caustic_distance"]
    assert 0.5 * float(hl.lens.surfaces[-1].thickness.detach()) < d < dc
    lens = hl.lens
    z_last = float(lens.vertex_z()[-1].detach())
    with torch.no_grad():
        assert float(beam_folds(lens, [z_last + d], fields=[[0.0, 14.0], [0.0, 0.0]]).max()) == 0.0

        def widest(dz):  # the largest side of any one source's footprint (mm)
            at, _, _ = beam_rays_at(lens, z_last + dz, [[0.0, 14.0], [0.0, 0.0]])
            sides = []
            for xy, v in zip(at.o[..., :2].flatten(0, 1), at.valid.flatten(0, 1)):
                sides.append(float((xy[v].amax(0) - xy[v].amin(0)).max()))
            return max(sides)

        assert widest(d) >= CAUSTIC_MARGIN * widest(dc) * (1 - 1e-6)
    # a lens whose beams fit half way keeps that plane, with no caustic before it
    info = load_hybrid("singlet").doe_info
    assert info["distance_rule"] == "half_way"


def test_a_doe_plane_beyond_the_caustic_warns():
    """The diagnostic trace (doe_clippings) counts the folded cells; doe_fields warns once for the call."""
    hl = load_hybrid(DOUBLE_GAUSS, doe_distance=59.99, fields=[[0.0, 14.0], [0.0, 0.0]], field_type="angle")
    f = torch.tensor([[0.0, 14.0], [0.0, 0.0]], dtype=torch.float64)
    wl = torch.tensor([hl.lens.primary_wavelength], dtype=torch.float64)
    with torch.no_grad():
        clips = doe_clippings(hl.optics, hl.doe, f, wl, None, hl.doe_z(), folds=True)
        assert clips[0][0][2] > 0.05 and clips[1][0][2] == 0.0  # 14°: folded; on axis: none
        before = load_hybrid(DOUBLE_GAUSS, doe_distance=53.0, fields=[[0.0, 14.0], [0.0, 0.0]], field_type="angle")
        assert doe_clippings(before.optics, before.doe, f, wl, None, before.doe_z(), folds=True)[0][0][2] == 0.0
        # the two-tuple of the public doe_clipping is unchanged
        assert len(doe_clippings(hl.optics, hl.doe, f, wl, None, hl.doe_z())[0][0]) == 2
        # the fold warning comes from the geometric trace, whatever the stop edge: the DOE-plane edge builds these
        # fields in ~1 s, the default's caustic fallback (StopEdgeWarning, tests/test_caustic_fallback.py) in ~20 s
        with pytest.warns(CausticWarning, match=r"1 source\(s\).*field \[0.0, 14.0\]"):
            hl.with_doe(hl.doe, stop_edge="doe").doe_fields([[0.0, 14.0], [0.0, 0.0]], hl.lens.primary_wavelength,
                                                             rays=16)
    assert math.isfinite(clips[0][0][0])


def test_cli_psf_reports_the_caustic_rule(capsys):
    """`raywave psf --json` names the rule and where the rays first cross; the text output says it too."""
    import json

    from raywave.cli.main import main

    assert main(["psf", DOUBLE_GAUSS, "--field", "0", "14", "--ks", "8", "--rays", "16", "--stop-edge", "doe",
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    doe = summary["doe"]
    assert doe["distance_rule"] == "before_caustic"
    assert doe["distance_mm"] < doe["caustic_distance_mm"]
    # the text output formats the same record (one engine run instead of two)
    from raywave.cli.psf_commands import _format_text

    assert "kept before the rays' first crossing" in _format_text(summary)
