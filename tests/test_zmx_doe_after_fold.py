"""A .zmx DOE plane (a BINARY_2 last surface) right after a coordinate break or a mirror: the reader places it on
the local axis after that surface (the image-space frame of raywave/lens/frames.py; after an odd number of mirrors
the thicknesses are negative and the DOE's distance is along the light), and ``load_hybrid(...).psf`` gives the
PSFs of the same lens unfolded (1e-10), the DOE and sensor at the same distances along the light."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.io import LensFileError, read_lens_spec, write_lens_spec

FOLD = Path(__file__).resolve().parent / "data" / "zmx" / "fold_mirror_doublet.zmx"


def _doe(disz: float) -> list[str]:
    """A BINARY_2 surface (2 terms, normalisation radius 5 mm, a 1.6 mm square) with thickness ``disz``."""
    return ["  TYPE BINARY_2", "  CURV 0.0", f"  DISZ {disz!r}", "  SQAP 0.8 0.8", "  PARM 0 1",
            "  XDAT 1 2", "  XDAT 2 5", "  XDAT 3 -40", "  XDAT 4 12"]


def _blocks():
    """(head lines, [SURF blocks as line lists], tail lines) of the corpus fold (AC254-100, COORDBRK 45°, flat
    mirror, COORDBRK 45°, −24.513 mm to the image)."""
    lines = FOLD.read_text().splitlines()
    starts = [i for i, ln in enumerate(lines) if ln.startswith("SURF ")]
    end = next(i for i in range(starts[-1] + 1, len(lines)) if not lines[i].startswith("  "))
    blocks = [lines[a:b] for a, b in zip(starts, starts[1:] + [end])]
    return lines[:starts[0]], blocks, lines[end:]


def _with_disz(block, disz):
    return [f"  DISZ {disz!r}" if ln.startswith("  DISZ") else ln for ln in block]


def _write(path, head, blocks, tail):
    out = list(head)
    for k, b in enumerate(blocks):
        out += [f"SURF {k}"] + [ln for ln in b if not ln.startswith("SURF ")]
    path.write_text("\r\n".join(out + tail) + "\r\n")
    return path


def _psf(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(path, doe_pitch=0.008, sensor_pitch=0.002)
        with torch.no_grad():
            res = hl.psf_result([(0.0, 0.0), (0.3, 1.0)], [0.55], ks=16, rays=24)
    return hl, res


def _unfolded(tmp_path, head, blocks, tail, distance):
    """The doublet alone: its last gap 40 + ``distance`` mm to the DOE, then 14.513 mm to the image."""
    b = blocks[:3] + [_with_disz(blocks[3], 40.0 + distance), ["SURF x"] + _doe(14.513), blocks[-1]]
    return _write(tmp_path / "unfolded.zmx", head, b, tail)


@pytest.mark.parametrize("case", ["after-coordinate-break", "after-mirror"])
def test_doe_after_a_fold_gives_the_unfolded_psf(tmp_path, case):
    head, blocks, tail = _blocks()
    assert [b[0] for b in blocks] == [f"SURF {k}" for k in range(8)]
    if case == "after-coordinate-break":  # fold, then 10 mm to the DOE along the light (DISZ -10), 14.513 on
        b = blocks[:6] + [_with_disz(blocks[6], -10.0), ["SURF x"] + _doe(-14.513), blocks[7]]
    else:  # a flat mirror at normal incidence 40 mm after the doublet, the DOE 10 mm back along the light
        mirror = _with_disz(blocks[5], -10.0)
        b = blocks[:4] + [mirror, ["SURF x"] + _doe(-14.513), blocks[7]]
    folded = _write(tmp_path / f"{case}.zmx", head, b, tail)
    spec = read_lens_spec(folded)
    assert spec["doe"]["distance"] == 10.0
    assert spec["surfaces"][-1]["thickness"] == pytest.approx(-24.513, abs=1e-12)
    hl, a = _psf(folded)
    ref, b_ = _psf(_unfolded(tmp_path, head, blocks, tail, 10.0))
    assert hl.doe_distance == 10.0 and ref.doe_distance == 50.0  # both 50 mm after the doublet along the light
    assert float(hl.sensor_distance().detach()) == pytest.approx(float(ref.sensor_distance().detach()), abs=1e-12)
    assert float(b_.psf.max()) > 0.01 and float(b_.psf.sum((-1, -2)).min()) > 0.5
    np.testing.assert_allclose(a.psf.numpy(), b_.psf.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.center.numpy(), b_.center.numpy(), rtol=0, atol=1e-12)
    # the writer puts the DOE back where it was (signed distances after the mirror)
    again = tmp_path / "again.zmx"
    write_lens_spec(spec, again)
    assert read_lens_spec(again)["doe"] == spec["doe"]
    assert read_lens_spec(again)["surfaces"][-1]["thickness"] == pytest.approx(-24.513, abs=1e-12)


def test_doe_after_a_fold_must_lie_before_the_image_along_the_light(tmp_path):
    head, blocks, tail = _blocks()
    b = blocks[:6] + [_with_disz(blocks[6], -10.0), ["SURF x"] + _doe(14.513), blocks[7]]  # wrong sign
    with pytest.raises(LensFileError, match=r"surface 7: the DOE plane must lie before the image: its thickness "
                                            r"\(DISZ\) must be < 0 mm \(negative after an odd number of mirrors"):
        read_lens_spec(_write(tmp_path / "bad.zmx", head, b, tail))
    b = blocks[:6] + [_with_disz(blocks[6], 10.0), ["SURF x"] + _doe(-14.513), blocks[7]]
    with pytest.raises(LensFileError, match=r"surface 6: the distance to the DOE plane \(DISZ\) must be <= 0 mm"):
        read_lens_spec(_write(tmp_path / "bad2.zmx", head, b, tail))
