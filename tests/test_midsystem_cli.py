"""`raywave info` and `raywave layout` show where the DOEs inside a lens are (issue 46)."""

import copy
import json
import math
from pathlib import Path

import pytest

import raywave
from raywave.cli.main import main
from raywave.io import read_lens_spec
from tests.test_midsystem_zmx import A1, DOUBLET, M, R_NORM, _hand_efl

TRIPLET = Path(raywave.__file__).parent / "data" / "lenses" / "cooke_triplet.json"


@pytest.fixture
def doublet(tmp_path):
    path = tmp_path / "doublet.zmx"
    path.write_text(DOUBLET)
    return path


def test_info_names_the_doe_inside_the_lens(doublet, capsys):
    assert main(["info", str(doublet)]) == 0
    out = capsys.readouterr().out
    assert "DOE inside the lens at surface 1, 0 mm after its vertex (z 4 mm): binary_2, circle 10 × 10 mm" in out
    power = -M * A1 * 0.55e-3 / (math.pi * R_NORM ** 2)
    line = next(ln for ln in out.splitlines() if "DOE paraxial power" in ln)
    assert float(line.split()[-2]) == pytest.approx(power, rel=1e-5)
    assert main(["info", str(doublet), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    (d,) = info["surface_does"]
    assert (d["surface"], d["distance"], d["z"], d["type"]) == (1, 0.0, 4.0, "binary_2")
    assert d["power"] == pytest.approx(power, rel=1e-12)
    assert d["efl_with_doe"] == pytest.approx(_hand_efl(power), rel=1e-7)


def test_info_of_a_json_grating_inside_the_triplet(tmp_path, capsys):
    spec = copy.deepcopy(read_lens_spec(TRIPLET))
    spec["surfaces"][1]["doe"] = {"distance": 3.0, "pitch": 0.012, "size": [12.0, 12.0],
                                  "phase_model": {"type": "grating", "period": 0.1}}
    path = tmp_path / "triplet_grating.json"
    path.write_text(json.dumps(spec))
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "DOE inside the lens at surface 1, 3 mm after its vertex" in out and "grating" in out
    line = next(ln for ln in out.splitlines() if "first-order deflection" in ln)
    wl = spec["wavelengths"]["values"][spec["wavelengths"].get("primary", 0)]  # µm
    assert float(line.split("in air")[1].split()[0]) == pytest.approx(math.degrees(math.asin(wl * 1e-3 / 0.1)),
                                                                      abs=1e-6)


def test_layout_draws_the_doe_plane_where_it_sits(doublet, tmp_path, capsys):
    png = tmp_path / "layout.png"
    assert main(["layout", str(doublet), "-o", str(png)]) == 0
    assert png.stat().st_size > 10_000 and "wrote" in capsys.readouterr().out

    from raywave.assembly.midsystem import doe_lens, lens_with_doe
    from raywave.plotting import plot_layout

    lens, doe, after, distance = doe_lens(read_lens_spec(doublet), str(doublet), doublet.parent)
    fig = plot_layout(lens_with_doe(lens, doe, after, distance))
    dashed = [ln for ln in fig.axes[0].lines if ln.get_linestyle() == "--"]
    assert len(dashed) == 1
    z, y = dashed[0].get_data()
    assert list(z) == pytest.approx([4.0, 4.0]) and max(y) == pytest.approx(5.0, rel=1e-3)  # at z 4 mm, its 5 mm aperture
    assert "DOE (after surface 1)" in [t.get_text() for t in fig.axes[0].texts]


def test_load_lens_names_the_surface_doe_it_leaves_out(doublet):
    """``load_lens`` builds the refractive lens only: a DOE inside it is named (SurfaceDOEWarning), not dropped
    silently."""
    from raywave.lens.build import SurfaceDOEWarning, load_lens

    with pytest.warns(SurfaceDOEWarning, match=r"surface 1 carries a DOE inside the lens.*load_midsystem"):
        load_lens(doublet)


def test_spot_traces_the_doe_inside_the_lens(doublet, capsys, recwarn):
    """``raywave spot`` traces each wavelength through the DOE's strongest order at that wavelength (the
    BINARY_2 of the doublet: its spots are those of ``lens_with_doe``, not of the refractive lens), and says so."""
    import torch

    from raywave.assembly.midsystem import doe_lens, lens_with_doe
    from raywave.lens.analysis import rms_spot_radius
    from raywave.lens.build import SurfaceDOEWarning

    assert main(["spot", str(doublet), "--json"]) == 0
    table = json.loads(capsys.readouterr().out)
    assert table["doe_inside"]["surface"] == 1 and table["doe_inside"]["distance"] == 0.0
    assert not [w for w in recwarn if issubclass(w.category, SurfaceDOEWarning)]
    lens, doe, after, distance = doe_lens(read_lens_spec(doublet), str(doublet), doublet.parent)
    for j, w in enumerate(lens.wavelengths):
        with torch.no_grad():
            want = rms_spot_radius(lens_with_doe(lens, doe, after, distance, wavelength=w), table["fields"], [w])
            plain = rms_spot_radius(lens, table["fields"], [w])
        got = torch.tensor([row[j] for row in table["rms_radius"]], dtype=torch.float64)
        assert torch.allclose(got, want[:, 0] * 1e3, rtol=1e-9)
        assert not torch.allclose(got, plain[:, 0] * 1e3, rtol=1e-2)  # the DOE changes the spots
    assert main(["spot", str(doublet)]) == 0
    assert "with the DOE inside the lens (0 mm after surface 1" in capsys.readouterr().out
