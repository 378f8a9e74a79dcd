"""DOE fabrication: binary masks and etch depths of an L = 2^k level DOE, GDSII / OASIS mask files, the report
and ``raywave doe export``."""

import json

import numpy as np
import pytest
import torch

from raywave.cli.main import main
from raywave.doe import fabrication as fab
from raywave.materials import get_material

gdstk = pytest.importorskip("gdstk")


def _n_fs(w):
    return float(get_material("FUSED_SILICA").n(torch.tensor(w, dtype=torch.float64)))


# ---------------------------------------------------------------------------- depths
def test_etch_depths_fused_silica_550nm():
    n = _n_fs(0.55)
    h = 0.55 / (n - 1) * 1e3                              # nm
    d = fab.etch_depths(16, "fused_silica", 0.55) * 1e6   # mm -> nm
    assert fab.height_2pi("FUSED_SILICA", 0.55) * 1e6 == pytest.approx(h, rel=1e-14)
    np.testing.assert_allclose(d, [h / 2, h / 4, h / 8, h / 16], rtol=1e-14)
    # the numbers: about 598, 299, 150, 75 nm
    np.testing.assert_allclose(d, [598, 299, 150, 75], atol=0.6)
    assert len(fab.etch_depths(2, "fused_silica", 0.55)) == 1
    assert fab.etch_depths(2, "fused_silica", 0.55)[0] == pytest.approx(h / 2 * 1e-6, rel=1e-14)


# ---------------------------------------------------------------------------- masks <-> levels
@pytest.mark.parametrize("L", [2, 4, 16])
def test_masks_levels_round_trip(L):
    rng = np.random.default_rng(L)
    lv = rng.integers(0, L, size=(41, 57))
    m = fab.masks_from_levels(lv, L)
    assert m.shape == (int(np.log2(L)), 41, 57) and m.dtype == bool
    np.testing.assert_array_equal(fab.levels_from_masks(m), lv)
    # torch input (DOE.levels returns torch.long)
    np.testing.assert_array_equal(fab.masks_from_levels(torch.as_tensor(lv), L), m)


def test_bit_convention():
    # level L-1: never etched; level 0: etched by every mask; mask 1 = most significant bit of L-1-level
    m = fab.masks_from_levels(np.array([[15, 0, 7, 14]]), 16)
    np.testing.assert_array_equal(m[:, 0, :].T, [[0, 0, 0, 0], [1, 1, 1, 1], [1, 0, 0, 0], [0, 0, 0, 1]])


@pytest.mark.parametrize("L", [2, 4, 16])
def test_etch_sum_reproduces_quantised_height(L):
    rng = np.random.default_rng(100 + L)
    lv = rng.integers(0, L, size=(32, 48))
    m = fab.masks_from_levels(lv, L)
    k = m.shape[0]
    # exactly, in units of h_2π / L
    units = sum(m[j].astype(np.int64) * 2 ** (k - 1 - j) for j in range(k))
    np.testing.assert_array_equal(units, (L - 1) - lv)
    # in mm: top surface minus the etch is the height h(ℓ) = ℓ·h_2π/L (phase 2πℓ/L at λ0)
    d = fab.etch_depths(L, "fused_silica", 0.55)
    h = fab.level_heights(lv, L, "fused_silica", 0.55)
    top = (L - 1) * fab.height_2pi("fused_silica", 0.55) / L
    np.testing.assert_allclose(top - fab.etch_profile(m, d), h, rtol=0, atol=1e-18)
    phase = 2 * np.pi * (_n_fs(0.55) - 1) * h * 1e3 / 0.55
    np.testing.assert_allclose(phase, 2 * np.pi * lv / L, atol=1e-12)


def test_quantise_phase_folds_L_to_zero():
    L = 16
    step = 2 * np.pi / L
    ph = np.array([[0.0, 0.49 * step, 0.51 * step, 2 * np.pi - 0.4 * step, -step, 15.2 * step + 4 * np.pi]])
    np.testing.assert_array_equal(fab.quantise_phase(ph, L), [[0, 0, 1, 0, 15, 15]])


# ---------------------------------------------------------------------------- report
def test_report_min_feature_and_fill():
    ny, nx = 12, 20
    lines = np.zeros((ny, nx), bool)
    lines[:, 2:5] = True          # 3-px line, then a 2-px space, then a 4-px line
    lines[:, 7:11] = True
    lines[:, nx - 1] = True       # 1-px line cut by the grid edge: not a feature
    blocks = np.zeros((ny, nx), bool)
    blocks[3:5, 0:nx] = True      # full-width band 2 px tall; gaps to the edges are not features
    empty = np.zeros((ny, nx), bool)
    masks = np.stack([lines, blocks, empty])
    depths = np.array([4e-4, 2e-4, 1e-4])
    r = fab.mask_report(masks, 0.002, depths)
    assert r["levels"] == 8 and r["masks"] == 3 and r["pitch_um"] == pytest.approx(2.0)
    assert r["shape"] == [ny, nx]
    np.testing.assert_allclose(r["depths_nm"], [400, 200, 100])
    a, b, c = r["per_mask"]
    assert (a["min_line_um"], a["min_space_um"], a["min_feature_um"]) == (6.0, 4.0, 4.0)
    assert a["fill_factor"] == pytest.approx(8 / 20)
    assert (b["min_line_um"], b["min_space_um"], b["min_feature_um"]) == (4.0, None, 4.0)
    assert b["fill_factor"] == pytest.approx(2 / 12)
    assert c["min_feature_um"] is None and c["fill_factor"] == 0.0
    assert r["min_feature_um"] == 4.0
    assert [p["layer"] for p in r["per_mask"]] == [1, 2, 3]
    json.dumps(r)
    # fab limit: 3 µm features are fine, 5 µm are not
    fab.check_min_feature(masks, 0.002, 3.0)
    with pytest.raises(ValueError, match=r"pitch 2 µm .*minimum feature 5 µm: mask 1"):
        fab.check_min_feature(masks, 0.002, 5.0)


# ---------------------------------------------------------------------------- errors
def test_errors():
    with pytest.raises(ValueError, match="power of two.*L = 12"):
        fab.masks_from_levels(np.zeros((4, 4), int), 12)
    with pytest.raises(ValueError, match="power of two.*L = 12"):
        fab.etch_depths(12, "fused_silica", 0.55)
    with pytest.raises(ValueError, match=r"\[0, 16\).*16"):
        fab.masks_from_levels(np.array([[0, 16]]), 16)
    with pytest.raises(ValueError, match=r"\[0, 4\)"):
        fab.masks_from_levels(np.array([[-1, 2]]), 4)
    with pytest.raises(ValueError, match="integers"):
        fab.masks_from_levels(np.array([[0.5, 2]]), 4)
    m = fab.masks_from_levels(np.zeros((4, 4), int), 4)
    for bad in (0, -1e-3, float("nan")):
        with pytest.raises(ValueError, match="pitch"):
            fab.mask_report(m, bad, [1e-4, 5e-5])
    with pytest.raises(ValueError, match="pitch"):
        fab.write_mask_file("x.gds", m, 0.0)
    with pytest.raises(ValueError, match=r"\.gds or \.oas"):
        fab.write_mask_file("x.dxf", m, 1e-3)


# ---------------------------------------------------------------------------- mask files
@pytest.mark.parametrize("ext", ["gds", "oas"])
@pytest.mark.parametrize("L, shape", [(2, (17, 23)), (16, (40, 33))])
def test_mask_file_round_trip(tmp_path, ext, L, shape):
    rng = np.random.default_rng(7)
    lv = rng.integers(0, L, size=shape)
    lv[5:15, 3:12] = L - 2    # blocks: vertically merged rectangles
    m = fab.masks_from_levels(lv, L)
    out = fab.write_mask_file(tmp_path / f"m.{ext}", m, 1.5e-3, name="test", label="levels etc.")
    assert out["rectangles"] == [len(fab.rectangles_from_mask(x)) for x in m]
    back = fab.read_mask_file(tmp_path / f"m.{ext}", shape, 1.5e-3)
    np.testing.assert_array_equal(back, m)
    # layers, alignment marks on every mask layer, the label on its own layer
    lib = gdstk.read_gds(str(tmp_path / "m.gds")) if ext == "gds" else gdstk.read_oas(str(tmp_path / "m.oas"))
    cells = {c.name: c for c in lib.cells}
    assert {"TOP", "DOE", "ALIGN", "LABEL"} <= set(cells)
    assert {p.layer for p in cells["DOE"].polygons} == set(range(1, m.shape[0] + 1))
    assert {p.layer for p in cells["ALIGN"].polygons} == set(range(1, m.shape[0] + 1))
    assert len(cells["ALIGN"].polygons) == 4 * m.shape[0]
    assert {p.layer for p in cells["LABEL"].polygons} == {fab.LABEL_LAYER}


def test_rectangles_cover_exactly():
    rng = np.random.default_rng(3)
    m = rng.random((30, 40)) < 0.5
    m[10:20, 5:25] = True
    r = fab.rectangles_from_mask(m)
    cover = np.zeros(m.shape, int)
    for x0, y0, x1, y1 in r:
        cover[y0:y1, x0:x1] += 1
    np.testing.assert_array_equal(cover, m.astype(int))
    # the solid block is merged across rows: far fewer rectangles than row runs
    assert len(fab.rectangles_from_mask(np.ones((50, 50), bool))) == 1


# ---------------------------------------------------------------------------- CLI
def test_cli_export_end_to_end(tmp_path, capsys):
    rng = np.random.default_rng(11)
    y, x = np.mgrid[-32:32, -32:32] + 0.5
    phase = -0.04 * (x ** 2 + y ** 2) + 0.3 * rng.standard_normal((64, 64))
    np.savez(tmp_path / "doe.npz", phase=phase, pitch=1e-3)
    out = tmp_path / "masks"
    assert main(["doe", "export", str(tmp_path / "doe.npz"), "--levels", "16", "--material", "fused_silica",
                 "--wavelength", "0.55", "-o", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert "\n" not in line and "16 levels = 4 masks" in line
    assert {p.name for p in out.iterdir()} == {"masks.gds", "report.json"} | {f"mask_{j}.png" for j in range(1, 5)}
    r = json.loads((out / "report.json").read_text())
    assert r["levels"] == 16 and r["pitch_um"] == pytest.approx(1.0) and len(r["per_mask"]) == 4
    np.testing.assert_allclose(r["depths_nm"], fab.etch_depths(16, "fused_silica", 0.55) * 1e6)
    lv = fab.quantise_phase(phase, 16)
    m = fab.read_mask_file(out / "masks.gds", (64, 64), 1e-3)
    np.testing.assert_array_equal(fab.levels_from_masks(m), lv)
    assert r["level_histogram"] == np.bincount(lv.ravel(), minlength=16).tolist()

    # OASIS, a .npy with --pitch, 4 levels, the phase given at 0.6 µm
    np.save(tmp_path / "doe.npy", phase)
    assert main(["doe", "export", str(tmp_path / "doe.npy"), "--pitch", "0.002", "--levels", "4", "--format", "oas",
                 "--wavelength", "0.6", "-o", str(tmp_path / "o2"), "--no-png"]) == 0
    m = fab.read_mask_file(tmp_path / "o2" / "masks.oas", (64, 64), 2e-3)
    np.testing.assert_array_equal(fab.levels_from_masks(m), fab.quantise_phase(phase, 4))
    r = json.loads((tmp_path / "o2" / "report.json").read_text())
    h = 0.6 / (_n_fs(0.6) - 1) * 1e3
    np.testing.assert_allclose(r["depths_nm"], [h / 2, h / 4], rtol=1e-12)
    assert r["format"] == "OASIS" and r["previews"] == []


def test_cli_export_errors(tmp_path, capsys):
    np.save(tmp_path / "p.npy", np.zeros((8, 8)))
    np.save(tmp_path / "p3.npy", np.zeros((2, 8, 8)))
    (tmp_path / "junk.npz").write_text("not a zip")
    cases = [
        (["p.npy", "--pitch", "1e-3", "--levels", "12"], "power of two"),
        (["p.npy"], "--pitch"),
        (["p.npy", "--pitch", "0"], "--pitch"),
        (["p.npy", "--pitch", "-1"], "--pitch"),
        (["p3.npy", "--pitch", "1e-3"], "2-D"),
        (["junk.npz"], "cannot read"),
        (["missing.npy", "--pitch", "1e-3"], "not found"),
        (["p.npy", "--pitch", "1e-3", "--material", "unobtanium"], "--material"),
        (["p.npy", "--pitch", "1e-3", "--wavelength", "550"], "µm, not nm"),
        (["p.npy", "--pitch", "1e-3", "--format", "dxf"], "--format"),
        (["cooke_triplet"], "no DOE"),
        (["hybrid_asphere"], "blank"),
    ]
    for argv, msg in cases:
        a = [str(tmp_path / argv[0]) if argv[0].endswith((".npy", ".npz")) else argv[0]] + argv[1:]
        assert main(["doe", "export", *a, "-o", str(tmp_path / "out")]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("raywave: error:") and msg in err and "\n" not in err, (argv, err)
    # a fab minimum feature larger than the pitch, with 1-pixel features in the masks
    rng = np.random.default_rng(0)
    np.save(tmp_path / "r.npy", rng.uniform(0, 2 * np.pi, (16, 16)))
    assert main(["doe", "export", str(tmp_path / "r.npy"), "--pitch", "1e-3", "--min-feature", "2",
                 "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "pitch 1 µm" in err and "minimum feature 2 µm" in err


def test_cli_export_lens_file_with_doe(tmp_path, capsys):
    """A raywave lens .json with a "doe" section whose phase is a .npz map."""
    from raywave.lens.build import bundled_lens_path

    spec = json.loads(bundled_lens_path("hybrid_asphere").read_text())
    ny = nx = 24
    y, x = np.mgrid[:ny, :nx]
    phase = 0.3 * x + 0.05 * y ** 2
    np.savez(tmp_path / "ph.npz", phase=phase, pitch=spec["doe"]["pitch"])
    spec["doe"].pop("size", None)
    spec["doe"]["phase"] = "ph.npz"
    (tmp_path / "lens.json").write_text(json.dumps(spec))
    assert main(["doe", "export", str(tmp_path / "lens.json"), "--levels", "8", "-o", str(tmp_path / "m"),
                 "--no-png"]) == 0
    m = fab.read_mask_file(tmp_path / "m" / "masks.gds", (ny, nx), spec["doe"]["pitch"])
    np.testing.assert_array_equal(fab.levels_from_masks(m), fab.quantise_phase(phase, 8))
