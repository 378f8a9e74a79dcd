"""The paraxial EDoF baseline (``baseline: paraxial``) on a tiny lens (ideal f = 2 mm, F/8, 128² pixel DOE,
refocused to 30 mm, depths 20 mm / 30 mm / 1 m): the paraxially designed DOE lowers the paraxial objective
against the blank DOE; for this ideal lens the paraxial model is exact, so the ray-wave model must agree with it
on both DOEs (an independent check of the hand-over); the CLI's baseline run trains with that DOE frozen and
writes the baseline's metrics."""

import json
import subprocess
import sys

import pytest
import torch

from raywave.training.config import ConfigError, load_config
from raywave.training.trainer import Trainer

CFG = """name: tiny_edof
seed: 1
dtype: float64
checkpoint_every: 2
baseline: {baseline}
baseline_steps: 6
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.256, doe_distance: 0.5, focus_depth: 30.0}}
optics: {{grid: [2, 2], eval_grid: [2, 2], ks: 16, rays: 20, depths: [20.0, 30.0, 1000.0],
          wavelengths: {{R: [0.64], G: [0.53], B: [0.46]}}}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 4, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1}}
pre_stage: {{steps: 1, similarity_weight: 1.0, lr_doe: 0.1}}
stage1: {{max_steps: 1, batch_size: 2, warmup_steps: 0, lr_network: 0.001, loss: edof}}
stage2: {{max_steps: 1, batch_size: 2, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0, noise: true, loss: edof}}
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, tiny_lens_file):

    d = tmp_path_factory.mktemp("tiny_edof")
    for kind in ("paraxial", "blank", "nonsense"):
        (d / f"{kind}.yaml").write_text(CFG.format(lens=tiny_lens_file, baseline=kind))
    return d


@pytest.fixture(scope="module")
def designed(tiny, tmp_path_factory):
    folder = tmp_path_factory.mktemp("base")
    tr = Trainer(load_config(tiny / "paraxial.yaml"), folder, baseline=True, progress=False)
    return tr, folder


def test_paraxial_design_beats_blank_and_ray_wave_agrees_on_an_ideal_lens(designed):
    tr, folder = designed
    rec = json.loads((folder / "baseline_design.json").read_text())
    assert rec["objective_designed"] == tr.baseline_design["objective_designed"]
    blank, des = rec["objective_blank"], rec["objective_designed"]
    print("paraxial objective blank → designed:", blank["paraxial"], des["paraxial"],
          "| ray-wave:", blank["ray_wave"], des["ray_wave"])
    assert des["paraxial"] < 0.97 * blank["paraxial"]  # measured: 3.196 → 3.019 in 6 steps
    for key in ("objective_blank", "objective_designed"):  # ideal lens: the paraxial model is exact
        assert rec[key]["ray_wave"] == pytest.approx(rec[key]["paraxial"], rel=5e-3)
    assert len(rec["history_paraxial"]) == 6 and rec["settings"]["steps"] == 6
    phase = tr.hl.doe.phase_map
    assert float(phase.abs().max()) > 0 and not phase.requires_grad  # designed, then frozen for the baseline


def test_the_stored_design_is_reused_and_redone_when_its_settings_change(tiny, designed, tmp_path):
    """A baseline Trainer on a folder with a design (resume, --restart, raywave eval) loads it; other settings
    (here baseline_steps) design again."""
    import shutil

    tr, folder = designed
    for name in ("baseline_design.json", "baseline_doe.pt"):
        shutil.copy(folder / name, tmp_path / name)
    again = Trainer(load_config(tiny / "paraxial.yaml"), tmp_path, baseline=True, progress=False)
    assert torch.equal(again.hl.doe.phase_map, tr.hl.doe.phase_map)
    assert again.baseline_design["design_seconds"] == tr.baseline_design["design_seconds"]  # loaded, not redone
    # a record from before `about` and `field_jitter` were settings (designed about the centroid, fixed nodes)
    rec = json.loads((tmp_path / "baseline_design.json").read_text())
    del rec["settings"]["about"], rec["settings"]["field_jitter"]
    (tmp_path / "baseline_design.json").write_text(json.dumps(rec))
    old = Trainer(load_config(tiny / "paraxial.yaml"), tmp_path, baseline=True, progress=False)
    assert old.baseline_design["design_seconds"] == tr.baseline_design["design_seconds"]
    cfg = load_config(tiny / "paraxial.yaml")
    cfg.baseline_steps = 1
    other = Trainer(cfg, tmp_path, baseline=True, progress=False)
    assert len(other.baseline_design["history_paraxial"]) == 1
    assert not torch.equal(other.hl.doe.phase_map, tr.hl.doe.phase_map)
    assert json.loads((tmp_path / "baseline_design.json").read_text())["settings"]["steps"] == 1


def test_blank_and_unknown_baselines(tiny, tmp_path):
    tr = Trainer(load_config(tiny / "blank.yaml"), tmp_path / "b", baseline=True, progress=False)
    assert tr.baseline_design is None and float(tr.hl.doe.phase_map.abs().max()) == 0
    assert not (tmp_path / "b" / "baseline_design.json").exists()
    with pytest.raises(ValueError, match="baseline must be one of 'blank', 'paraxial', got 'nonsense'"):
        Trainer(load_config(tiny / "nonsense.yaml"), tmp_path / "n", baseline=True, progress=False)
    with pytest.raises(ConfigError, match="baseline_steps"):
        bad = tmp_path / "bad.yaml"
        bad.write_text("baseline_steps: many\n")
        load_config(bad)


@pytest.mark.slow  # CI time (README: Slow suite)
def test_cli_trains_the_paraxial_baseline_and_writes_its_metrics(tiny, tmp_path):
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "raywave.cli.main", "train", str(tiny / "paraxial.yaml"), "-o", str(run),
                        "--quiet"], capture_output=True, text=True, env={**__import__("os").environ,
                                                                         "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    m = json.loads((run / "metrics.json").read_text())
    assert set(m) >= {"designed", "baseline", "gain_db"}
    assert set(m["baseline"]) == {"depth=20/centre", "depth=20/edge", "depth=30/centre", "depth=30/edge",
                                  "depth=1000/centre", "depth=1000/edge", "mean"}
    assert (run / "baseline" / "baseline_design.json").is_file()
    ck = sorted((run / "baseline" / "checkpoints").glob("*.pt"))[-1]
    phase = torch.load(ck, weights_only=True)["modules"]["hybrid"]
    key = next(k for k in phase if k.endswith("phase_map"))
    assert float(phase[key].abs().max()) > 0  # the baseline trained with the paraxial DOE (not a blank one)


def test_the_paraxial_design_measures_psf_size_about_the_pre_stages_point(tiny, tmp_path, monkeypatch):
    """The paraxial baseline minimises the pre-stage's own objective: with ``pre_stage.about: center`` its
    PSF sizes are measured about the chief-ray pixel (a DOE that shifts the image is penalised), as in the
    pre-stage of the designed run; the setting is part of the stored design's settings."""
    import raywave.training.baselines as B

    seen = []
    real = B.psf_objective

    def spy(psf, similarity_weight=0.0, about="centroid"):
        seen.append(about)
        return real(psf, similarity_weight, about=about)

    monkeypatch.setattr(B, "psf_objective", spy)
    cfg = load_config(tiny / "paraxial.yaml")
    cfg.pre_stage.about, cfg.baseline_steps = "center", 2
    tr = Trainer(cfg, tmp_path, baseline=True, progress=False)
    assert seen and set(seen) == {"center"}  # design steps and the before/after objectives alike
    assert tr.baseline_design["settings"]["about"] == "center"


def test_paraxial_reconstruction_builds_the_baselines_pipeline_on_the_paraxial_model(tiny, designed, tmp_path):
    """``baseline_reconstruction: paraxial`` (the paper's baseline pipeline): the reconstruction's maps come from the
    paraxial model, the sensor images from the ray-wave model. On this ideal lens the two models agree, so the
    deconvolution with the paraxial PSFs restores as well as with the true ones (an independent check), and the
    sensor images are the ones the ray-wave reconstruction sees."""
    from raywave.models.paraxial import ParaxialModel

    _, folder = designed
    runs = {}
    for rec in ("ray_wave", "paraxial"):
        cfg = load_config(tiny / "paraxial.yaml")
        cfg.network.deconv = "wiener"
        cfg.baseline_reconstruction = rec
        run = tmp_path / rec
        run.mkdir()
        for f in ("baseline_design.json", "baseline_doe.pt"):  # the stored design: not designed again
            (run / f).write_bytes((folder / f).read_bytes())
        runs[rec] = Trainer(cfg, run, baseline=True, progress=False)
    rw, px = runs["ray_wave"], runs["paraxial"]
    assert rw.recon_model is rw.hl and isinstance(px.recon_model, ParaxialModel)
    assert torch.equal(rw.hl.doe.phase_map, px.hl.doe.phase_map)
    m_rw, m_px = rw.evaluate(), px.evaluate()
    assert px.truth_map() is not px.stage2_map and rw.truth_map() is rw.stage2_map
    assert torch.allclose(px.truth_map().psf, rw.stage2_map.psf, atol=1e-12)
    assert not torch.allclose(px.stage2_map.psf, px.truth_map().psf, atol=1e-12)  # another model's PSFs
    for k in m_rw:
        assert m_px[k]["psnr_input"] == pytest.approx(m_rw[k]["psnr_input"], abs=1e-9)
        assert m_px[k]["psnr_deconv_true"] == pytest.approx(m_rw[k]["psnr_deconv"], abs=1e-9)
        assert m_px[k]["psnr_deconv"] == pytest.approx(m_rw[k]["psnr_deconv"], abs=0.3)
        assert "psnr_deconv_true" not in m_rw[k]
    bad = tmp_path / "bad.yaml"
    bad.write_text("baseline_reconstruction: exact\n")
    with pytest.raises(ConfigError, match="baseline_reconstruction"):
        load_config(bad)
