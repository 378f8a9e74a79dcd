"""The raywave command line: info, layout, spot, convert, demo; user errors are one line, exit 2."""

import json
import subprocess
import sys

import pytest

from raywave.cli.main import main

INFO_KEYS = {"efl", "efl_real", "bfl", "ffl", "fnum", "epd", "ep_z", "xpd", "xp_z", "fov_deg", "image_height", "total_track"}


def test_info_json_keys_and_values(capsys):
    assert main(["info", "cooke_triplet", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info) == INFO_KEYS | {"surfaces"}  # + the prescription (issue 45)
    assert [r["radius"] for r in info["surfaces"]][:2] == pytest.approx([22.01359, -435.7604])
    assert [r["stop"] for r in info["surfaces"]] == [False, False, True, False, False, False]
    assert info["efl"] == pytest.approx(50.0, rel=0.02)
    assert info["efl_real"] == pytest.approx(info["efl"], rel=1e-5)
    assert info["epd"] == pytest.approx(10.0, rel=1e-12)
    assert info["fnum"] == pytest.approx(info["efl"] / 10.0)
    assert info["fov_deg"] == pytest.approx(40.0)


def test_info_table_text(capsys):
    assert main(["info", "double_gauss"]) == 0
    out = capsys.readouterr().out
    assert "Effective focal length" in out and "Exit pupil" in out


def test_layout_and_spot_png(tmp_path, capsys):
    png = tmp_path / "layout.png"
    assert main(["layout", "double_gauss", "-o", str(png)]) == 0
    assert png.stat().st_size > 10_000
    capsys.readouterr()
    spng = tmp_path / "spot.png"
    assert main(["spot", "singlet", "--json", "-o", str(spng)]) == 0
    table = json.loads(capsys.readouterr().out)
    assert len(table["rms_radius"]) == 3 and len(table["rms_radius"][0]) == 3
    assert spng.stat().st_size > 10_000


def test_convert_round_trip(tmp_path, capsys):
    zmx = tmp_path / "cooke.zmx"
    back = tmp_path / "cooke.json"
    assert main(["convert", "cooke_triplet", str(zmx)]) == 0
    assert main(["convert", str(zmx), str(back)]) == 0
    assert main(["info", str(back), "--json"]) == 0
    capsys.readouterr()
    assert main(["info", "cooke_triplet", "--json"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert main(["info", str(back), "--json"]) == 0
    b = json.loads(capsys.readouterr().out)
    assert b["efl"] == pytest.approx(a["efl"], rel=1e-12)


def test_demo_writes_outputs(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    # a fresh clone's demo warns about nothing (issue 45): the bundled DOE's slight clipping is a note
    assert "warning" not in err.lower() and "raywave/" not in err
    assert "note: the bundled hybrid lens's 3×3 mm DOE" in out and "as intended" in out
    for name in ("paraxial.txt", "paraxial.json", "layout.png", "spot.png", "psf.png", "psf.json"):
        assert (tmp_path / name).stat().st_size > 100
    import json

    psfs = json.loads((tmp_path / "psf.json").read_text())["psfs"]
    assert len(psfs) == 6 and all(0 <= p["energy_outside"] < 0.2 for p in psfs)


def test_missing_file_is_one_line_error(capsys):
    assert main(["info", "no_such_lens.json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("raywave: error:") and "no_such_lens.json" in err and "Traceback" not in err


def test_entry_point_runs():
    out = subprocess.run([sys.executable, "-m", "raywave.cli.main", "info", "singlet", "--json"],
                         capture_output=True, text=True, check=True)
    assert json.loads(out.stdout)["efl"] == pytest.approx(100.0, rel=0.02)


def test_loss_figure_draws_each_stage_with_its_running_mean(tmp_path):
    """``loss.png``: per-step losses (noisy by design: random patches, depths, sensor noise) and their running
    mean, which starts at the first value and averages at most ``width`` values."""
    import json
    from types import SimpleNamespace

    from raywave.cli.train_commands import _loss_figure, _running_mean

    assert _running_mean([1.0, 2.0, 3.0, 4.0, 5.0], 2) == [1.0, 1.5, 2.5, 3.5, 4.5]
    assert _running_mean([4.0, 2.0], 5) == [4.0, 3.0]
    log = tmp_path / "log.jsonl"
    log.write_text("\n".join(json.dumps({"stage": s, "loss": 1.0 + i % 3}) for s in ("stage1", "stage2")
                             for i in range(40)) + "\n")
    _loss_figure(tmp_path / "figures", {"designed": SimpleNamespace(log_path=log)})
    assert (tmp_path / "figures" / "loss.png").stat().st_size > 0


def test_layout_and_spot_write_into_a_folder(tmp_path, capsys):
    """``-o DIR`` writes DIR/layout.png (before: DIR.png); a .png path is kept; another suffix is refused."""
    assert main(["layout", "singlet", "-o", str(tmp_path / "figs")]) == 0
    assert (tmp_path / "figs" / "layout.png").is_file() and not (tmp_path / "figs.png").exists()
    assert main(["layout", "singlet", "-o", str(tmp_path / "a.png")]) == 0 and (tmp_path / "a.png").is_file()
    assert main(["spot", "singlet", "-o", str(tmp_path / "figs")]) == 0 and (tmp_path / "figs" / "spot.png").is_file()
    assert main(["layout", "singlet", "-o", str(tmp_path / "a.jpg")]) == 2
    assert "give a .png file or a folder" in capsys.readouterr().err


def test_psf_warns_when_the_crop_misses_energy(capsys):
    """Before: a PSF with 74 % of its energy outside the crop had its radii printed without a word."""
    assert main(["--quiet", "psf", "hybrid_asphere", "--field", "0,7", "--ks", "8", "--rays", "16", "--json"]) == 0
    out, err = capsys.readouterr()
    outside = json.loads(out)["energy_outside"]
    assert outside > 0.01
    assert f"{outside:.1%} of its energy falls outside the 8×8-pixel crop" in err and "--ks 16" in err
    assert main(["--quiet", "psf", "hybrid_asphere", "--ks", "64", "--rays", "16"]) == 0
    assert "outside the" not in capsys.readouterr().err


def test_spot_vignetted_field_is_not_zero(capsys):
    """Issue 45: a fully vignetted field is "vignetted" in the table and null in JSON, never 0.0000."""
    assert main(["spot", "cooke_triplet", "--fields", "0", "40", "--json"]) == 0
    table = json.loads(capsys.readouterr().out)
    assert table["rms_radius"][1] == [None, None, None] and all(v > 1 for v in table["rms_radius"][0])
    assert [f for f, _ in table["vignetted"]] == [40.0, 40.0, 40.0]
    assert main(["spot", "cooke_triplet", "--fields", "0", "40"]) == 0
    out = capsys.readouterr().out
    assert "vignetted" in out and "0.0000" not in out


def test_spot_on_axis_independent_of_other_fields(capsys):
    """Issue 45: `spot --fields 0,20` and `--fields 0,20,30` print the same on-axis RMS (it used to be 15.87 vs
    16.32 µm at 0.486 µm: the rim ring passed or not with the batch's rounding)."""
    rows = []
    for fields in (["0", "20"], ["0", "20", "30"]):
        assert main(["spot", "cooke_triplet", "--fields", *fields, "--json"]) == 0
        rows.append(json.loads(capsys.readouterr().out)["rms_radius"][0])
    assert rows[0] == pytest.approx(rows[1], abs=1e-9)


def test_info_prints_the_prescription(capsys):
    assert main(["info", "cooke_triplet"]) == 0
    out = capsys.readouterr().out
    assert "STO" in out and "N-SK16" in out and "semi-diam" in out
