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
    with pytest.raises(ValueError, match="several DOEs"):
        midsystem_from_spec(_spec([GRATING, dict(GRATING, distance=4.0)]))


def test_the_last_surface_builder_refuses_a_doe_inside_the_lens(tmp_path):
    """raywave.load_hybrid (and so `raywave psf`) would drop a surface's DOE: it refuses the file instead."""
    path = tmp_path / "triplet_grating.json"
    path.write_text(json.dumps(_spec(GRATING)))
    with pytest.raises(ValueError, match="load_midsystem"):
        raywave.load_hybrid(path)
