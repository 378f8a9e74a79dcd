"""`raywave compare`: the models' PSF grid and error table, ground truth for an ideal lens, bad input."""

import csv
import json

import numpy as np
import pytest

from raywave.cli.main import main
from raywave.lens.build import ideal_lens, save_lens


@pytest.fixture(scope="module")
def ideal_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lens") / "ideal.json"
    lens = ideal_lens(5.0, f_number=4.0, wavelengths=(0.55,))
    save_lens(lens, path)
    return path


def test_compare_writes_grid_and_table_with_ground_truth(ideal_file, tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", str(ideal_file), "--fields", "0", "0,2", "--ks", "16", "--sensor-pitch", "0.001",
               "--doe-distance", "1", "-o", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "L1 vs raywave" in text and "exit_pupil" in text
    assert (out / "compare.png").stat().st_size > 20_000
    rows = list(csv.DictReader(open(out / "compare.csv")))
    assert len(rows) == 12 and {r["model"] for r in rows} == {"raywave", "raywave_doe", "paraxial", "pupil", "raytrace",
                                                              "exit_pupil"}
    report = json.loads((out / "compare.json").read_text())
    truth = {r["model"]: r["l1_vs_truth"] for r in report["rows"] if r["field_y_deg"] == 0.0}
    # on axis the ideal lens has a ground truth (the Debye focus): the wave models are close to it
    assert truth["raywave"] < 5e-3 and truth["paraxial"] < 5e-3 and truth["exit_pupil"] < 2e-2
    assert truth["raywave_doe"] < 5e-3  # the paper's DOE-plane edge: on axis as good
    assert all(r["l1_vs_truth"] is None for r in report["rows"] if r["field_y_deg"] == 2.0)
    assert len(report["pairs"]) == 2 * 15
    # the exit-pupil reference converges its own pupil sampling and says how far it may be off (issue 47)
    ep = [r for r in report["rows"] if r["model"] == "exit_pupil"]
    # (polar pupil nodes by default: their levels agree to ~1e-10 once the wavefront is resolved)
    assert all(r["n_pupil"] >= 32 and 0 <= r["error_estimate"] < 1e-3 for r in ep)
    assert "pupil cells, own error" in text


def test_compare_with_a_doe_leaves_out_the_exit_pupil_model(ideal_file, tmp_path, capsys):
    phase = np.tile(np.where(np.arange(800) % 40 < 20, 0.0, np.pi), (800, 1))
    doe = tmp_path / "binary.npz"
    np.savez(doe, phase=phase, pitch=0.001)
    out = tmp_path / "cmp"
    rc = main(["compare", str(ideal_file), "--doe", str(doe), "--ks", "16", "--doe-distance", "1",
               "--sensor-pitch", "0.001", "-o", str(out), "--json"])
    assert rc == 0
    cap = capsys.readouterr()
    report = json.loads(cap.out)
    assert report["models"] == ["raywave", "raywave_doe", "paraxial", "pupil", "raytrace"]
    assert "exit_pupil" in report["notes"][0]
    assert "discontinuous" in cap.err  # the ray model's warning, one line on stderr
    ray = [r for r in report["rows"] if r["model"] == "raytrace"][0]
    assert ray["rays_on_discontinuity"] > 0.05 and ray["l1_vs_raywave"] > 1.0
    assert main(["compare", str(ideal_file), "--doe", str(doe), "--models", "raywave,exit_pupil", "--ks", "8",
                 "--doe-distance", "1", "-o", str(out)]) == 2
    assert "cannot simulate a DOE" in capsys.readouterr().err


@pytest.mark.parametrize("argv,message", [
    (["--models", "raywave,zemax"], "unknown model"),
    (["--fields", "a"], "not a number"),
    (["--fields", "1,2,3"], "Y or X,Y"),
    (["--models", "paraxial", "--reference", "raywave"], "--reference"),
    (["--ks", "0"], "--ks"),
    (["--device", "npu"], "--device"),
])
def test_compare_bad_input_is_one_clear_error(ideal_file, tmp_path, capsys, argv, message):
    assert main(["compare", str(ideal_file), "-o", str(tmp_path / "x"), *argv]) == 2
    assert message in capsys.readouterr().err
