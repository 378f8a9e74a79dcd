"""Lens files with a DOE inside the lens (issue 46): the raywave JSON surface key ``"doe"``."""

import copy
import json
import warnings
from pathlib import Path

import pytest
import torch

import raywave
from raywave.assembly.midsystem import load_midsystem, midsystem_from_spec, surface_doe_positions
from raywave.io import LensFileError, read_lens_spec, validate_spec

LENS = Path(raywave.__file__).parent / "data" / "lenses" / "cooke_triplet.json"
GRATING = {"distance": 3.0, "pitch": 0.012, "size": [12.0, 12.0], "phase_model": {"type": "grating", "period": 0.1},
           "levels": 16, "material": "FUSED_SILICA"}


def _spec(doe):
    spec = copy.deepcopy(read_lens_spec(LENS))
    spec["surfaces"][1]["doe"] = doe
    return spec


def test_surface_doe_key_validates_and_reports_its_path():
    spec = _spec(GRATING)
    validate_spec(spec)
    assert surface_doe_positions(spec) == [(1, 3.0, GRATING)]
    bad = _spec(dict(GRATING, distance=7.5))  # beyond the 6.0 mm gap after surface 1
    with pytest.raises(LensFileError, match=r"surfaces.*1.*doe.*distance"):
        validate_spec(bad)
    with pytest.raises(LensFileError, match="phase_model"):
        validate_spec(_spec(dict(GRATING, phase_model={"type": "grating"})))
    validate_spec(_spec([GRATING]))  # a list of DOEs is valid syntax


def test_surface_doe_builds_a_midsystem_lens(tmp_path):
    path = tmp_path / "triplet_grating.json"
    path.write_text(json.dumps(_spec(GRATING)))
    ml = load_midsystem(path)
    assert (ml.after, ml.distance) == (1, 3.0)
    assert [round(s) for s, _ in ml.orders(0.55)] == [1]  # a 16-level blazed grating: order 1 (98.7 %)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        psf = ml.psf((0.0, 0.0), 0.55, ks=16)
    assert psf.shape == (1, 1, 16, 16) and abs(float(psf.sum()) - 1) < 1e-12 and bool(torch.isfinite(psf).all())


def test_two_surface_does_build_one_midsystem_lens(tmp_path):
    """Two DOEs from one lens file (a list on surface 1: a grating ruled along x 3 mm after it, one along y 4 mm
    after it) build one MidSystemLens with both: across the two planes (in air) the chief ray's direction cosines
    change by both grating equations (λ/period along x and along y, within 1e-12), the orders are the DOEs' products, and
    the PSF is that of the same DOEs given to MidSystemLens directly. A DOE before the sensor as well is refused."""
    from raywave.assembly.midsystem import lens_with_doe
    from raywave.hybrid.midsystem import MidSystemLens
    from raywave.lens.sources import chief_ray

    gy = dict(GRATING, distance=4.0, phase_model={"type": "grating", "period": 0.1, "angle": 90.0})
    path = tmp_path / "triplet_two_gratings.json"
    path.write_text(json.dumps(_spec([GRATING, gy])))
    ml = load_midsystem(path)
    assert ml.placements == [(1, 3.0), (1, 4.0)] and len(ml.does) == 2
    assert [tuple(round(v) for v in s) for s, _ in ml.orders(0.55)] == [(1, 1)]  # 0.987² of the light
    lm, idx = ml.build_lens([1.0, 1.0])
    assert idx == [2, 3]
    wl = 0.55
    with torch.no_grad():
        cr = chief_ray(lm, torch.zeros(1, 2, dtype=torch.float64), torch.tensor([wl], dtype=torch.float64))
        d0 = lm.trace(cr, stop=idx[0]).d.reshape(-1, 3)[0]
        d = lm.trace(cr, stop=idx[1] + 1).d.reshape(-1, 3)[0] - d0
    assert abs(float(d[0]) - wl * 1e-3 / 0.1) < 1e-12 and abs(float(d[1]) - wl * 1e-3 / 0.1) < 1e-12
    assert lens_with_doe(ml.lens, list(ml.does), [1, 1], [3.0, 4.0]).surfaces[idx[1]].comment == "DOE (mid-system)"
    same = MidSystemLens(ml.lens, list(ml.does), [1, 1], [3.0, 4.0], ml.final_distance, ml.final.size[0],
                         ml.final.pitch, sensor_pitch=ml.sensor_pitch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        psf = ml.psf((0.0, 0.0), wl, ks=16)
        ref = same.psf((0.0, 0.0), wl, ks=16)
    assert abs(float(psf.sum()) - 1) < 1e-12 and torch.equal(psf, ref)
    both = _spec([GRATING, gy])
    both["doe"] = {"pitch": 0.01, "size": [2.0, 2.0]}
    with pytest.raises(ValueError, match="before the\\s+sensor|before the sensor"):
        midsystem_from_spec(both)


def test_the_last_surface_builder_refuses_a_doe_inside_the_lens(tmp_path):
    """raywave.load_hybrid (and so `raywave psf`) would drop a surface's DOE: it refuses the file instead."""
    path = tmp_path / "triplet_grating.json"
    path.write_text(json.dumps(_spec(GRATING)))
    with pytest.raises(ValueError, match="load_midsystem"):
        raywave.load_hybrid(path)


def test_conformal_surface_doe_in_a_json_lens():
    """``"conformal": true`` puts the DOE on the surface itself (no distance): validated with its key path, built as
    a conformal DOE (placement distance None); a distance with it, or a non-boolean, is refused."""
    conf = {k: v for k, v in GRATING.items() if k != "distance"}
    conf["conformal"] = True
    spec = _spec(conf)
    validate_spec(spec)
    assert surface_doe_positions(spec) == [(1, None, conf)]
    ml = midsystem_from_spec(spec)
    assert ml.placements == [(1, None)]
    lm, idx = ml.build_lens([1.0])
    assert idx == [1] and len(lm.surfaces) == len(ml.lens.surfaces)
    assert lm.surfaces[1].geometry is ml.lens.surfaces[1].geometry and lm.surfaces[1].interaction.kind == "diffraction"
    with pytest.raises(LensFileError, match=r"surfaces.*1.*doe.*distance.*leave 'distance' out"):
        validate_spec(_spec(dict(conf, distance=0.0)))
    with pytest.raises(LensFileError, match=r"conformal.*true or false"):
        validate_spec(_spec(dict(conf, conformal="yes")))
