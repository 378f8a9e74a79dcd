"""Training set-up: config YAML (round trip, unknown keys named with the file), warm-up + cosine schedule,
optimizer parameter groups, losses (EDoF loss, PSF size and similarity against hand computations), metrics
against scikit-image, checkpoints (atomic, bit-identical resume)."""

import math
import random
import subprocess
import sys

import numpy as np
import pytest
import torch

from raywave.training.checkpoint import (checkpoint_path, latest_checkpoint, load_checkpoint, save_checkpoint)
from raywave.training.config import ConfigError, TrainConfig, dump_config, from_dict, load_config
from raywave.training.losses import (edof_loss, image_loss, psf_similarity_loss, psf_size, psf_size_loss,
                                     rmse_loss)
from raywave.training.schedule import (DEFAULT_LR, WarmupCosine, build_optimizer, param_groups,
                                       warmup_cosine_scheduler)


# ------------------------------------------------------------------ config
def test_config_round_trip_and_defaults(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("name: demo\nseed: 3\noptics:\n  grid: [5, 5]\n  depths: [200, 300, .inf]\nstage1:\n"
                 "  lr_doe: 0.05\n  max_steps: 7\n")
    cfg = load_config(p)
    assert cfg.name == "demo" and cfg.seed == 3 and cfg.optics.grid == [5, 5]
    assert cfg.optics.depths == [200, 300, math.inf] and cfg.stage1.lr_doe == 0.05 and cfg.stage1.max_steps == 7
    assert cfg.stage1.lr_network == 1e-4 and cfg.stage2.noise is True  # defaults
    out = tmp_path / "resolved.yaml"
    dump_config(cfg, out)
    assert load_config(out) == cfg
    assert from_dict(TrainConfig, {"optics": {"depths": ["inf"]}}).optics.depths == [math.inf]


@pytest.mark.parametrize("text,match", [
    ("nmae: x\n", "unknown key 'nmae'"),
    ("stage1:\n  lr_dOE: 0.1\n", "unknown key 'stage1.lr_dOE'"),
    ("seed: 1.5\n", "seed must be an integer"),
    ("stage1:\n  noise: 1\n", "stage1.noise must be true or false"),
    ("optics: 3\n", "optics must be a mapping"),
])
def test_config_errors_name_key_and_file(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match) as e:
        load_config(p)
    assert "bad.yaml" in str(e.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")


def test_shipped_configs_load():
    from pathlib import Path

    files = sorted(Path(__file__).parent.parent.joinpath("configs").glob("*.yaml"))
    assert {f.name for f in files} >= {"aberration_demo.yaml", "aberration_paper.yaml", "edof_demo.yaml",
                                       "edof_paper.yaml"}
    for f in files:
        load_config(f)


def test_paper_configs_have_the_papers_sizes():
    """Supplement 2.3/2.5/2.6: 10×10 maps (5×5 for EDoF) in stage 1, 40×40 in stage 2, 50 + 50 epochs, Adam at
    1e-4 (lens) / 1e-1 (DOE) / 1e-4 (network), DIV2K, EDoF at 200 / 300 / 10000 mm focused at 300 mm, α = 0.3."""
    from pathlib import Path

    root = Path(__file__).parent.parent / "configs"
    ab, ed = load_config(root / "aberration_paper.yaml"), load_config(root / "edof_paper.yaml")
    assert ab.optics.grid == [10, 10] and ed.optics.grid == [5, 5]
    for c in (ab, ed):
        assert c.optics.eval_grid == [40, 40] and c.lens.doe_pitch == 0.001 and c.data.source == "folder"
        assert (c.stage1.epochs, c.stage2.epochs) == (50, 50) and c.stage1.max_steps is None
        assert (c.stage1.lr_lens, c.stage1.lr_doe, c.stage1.lr_network) == (1e-4, 1e-1, 1e-4)
        assert c.stage2.lr_network == 1e-4 and c.stage2.noise and not c.stage1.noise
    assert ab.baseline == "blank" and ab.optics.depths == [math.inf]
    assert ed.baseline == "paraxial" and ed.optics.depths == [200, 300, 10000] and ed.lens.focus_depth == 300
    assert ed.stage1.loss == "edof" and ed.stage1.edof_alpha == 0.3 and ed.pre_stage.similarity_weight > 0


def test_config_overrides():
    from raywave.training.config import apply_overrides

    cfg = TrainConfig()
    new = apply_overrides(cfg, ["data.root=/data/DIV2K", "optics.grid=[5, 5]", "optics.depths=[.inf, 300]",
                                "stage1.max_steps=7", "device=cuda"])
    assert new.data.root == "/data/DIV2K" and new.optics.grid == [5, 5] and new.optics.depths == [math.inf, 300]
    assert new.stage1.max_steps == 7 and new.device == "cuda"
    assert cfg.data.root is None and cfg.optics.grid == [10, 10]  # the original is untouched
    # PyYAML reads "1e-3" (no dot) as a string; a number field takes it as the number it spells
    assert apply_overrides(cfg, ["stage2.lr_network=1e-3"]).stage2.lr_network == 1e-3
    assert from_dict(TrainConfig, {"stage1": {"lr_doe": "5e-2"}}).stage1.lr_doe == 0.05
    for bad, match in [("data.rot=1", "unknown key 'data.rot'"), ("optics=3", "is a section"),
                       ("stage1.max_steps=abc", "stage1.max_steps must be an integer"), ("seed", "KEY=VALUE"),
                       ("stage1.lr_doe=fast", "stage1.lr_doe must be a number"),
                       ("stage1.lr_doe=nan", "must be a finite number")]:
        with pytest.raises(ConfigError, match=match):
            apply_overrides(cfg, [bad])


# ------------------------------------------------------------------ schedule and optimizer
def test_warmup_then_cosine():
    f = WarmupCosine(total=20, warmup=5, min_ratio=0.1)
    vals = [f(s) for s in range(25)]
    assert vals[:5] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0])
    assert vals[5] == pytest.approx(1.0) and vals[19] == pytest.approx(0.1) and vals[24] == pytest.approx(0.1)
    mid = 5 + (19 - 5) / 2
    assert f(int(mid)) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * (int(mid) - 5) / 14)))
    assert all(a >= b for a, b in zip(vals[5:], vals[6:]))  # monotone decay after the warm-up


def test_scheduler_drives_each_group():
    lens, doe, net = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    opt = build_optimizer(param_groups(lens, doe, net))
    assert [(g["name"], g["lr"]) for g in opt.param_groups] == [(k, DEFAULT_LR[k]) for k in ("lens", "doe", "network")]
    sched = warmup_cosine_scheduler(opt, total=10, warmup=2)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([0.5e-4, 0.5e-1, 0.5e-4])
    opt.step(), sched.step()
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([1e-4, 1e-1, 1e-4])


def test_param_groups_skip_frozen_and_reject_shared():
    lens, net = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    lens.requires_grad_(False)
    assert [g["name"] for g in param_groups(lens, None, net)] == ["network"]
    assert [g["name"] for g in param_groups(None, net, torch.nn.Linear(1, 1), lr_doe=0.0)] == ["network"]
    with pytest.raises(ValueError, match="shares"):
        param_groups(net, net)
    with pytest.raises(ValueError, match="nothing to optimise"):
        build_optimizer(param_groups(lens))


# ------------------------------------------------------------------ losses
def test_rmse_and_edof_loss_by_hand():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 8, 8, dtype=torch.float64, generator=g)
    recon = [target + 0.1 * k for k in range(3)]  # constant offsets: rmse(r_i, r_j) = 0.1 |i − j|
    assert float(rmse_loss(recon[2], target)) == pytest.approx(0.2, abs=1e-9)
    sim = 2 * (0.1 + 0.2 + 0.1)  # ordered pairs
    fid = 0.0 + 0.1 + 0.2
    assert float(edof_loss(recon, target, alpha=0.3)) == pytest.approx(sim + 0.3 * fid, abs=1e-6)
    assert float(edof_loss(torch.stack(recon), target)) == pytest.approx(sim + 0.3 * fid, abs=1e-6)
    r = target.clone().requires_grad_(True)
    rmse_loss(r, target).backward()  # zero error: finite gradient
    assert torch.isfinite(r.grad).all()
    with pytest.raises(ValueError, match="unknown image loss"):
        image_loss("ssim")


def test_psf_size_of_a_gaussian_and_similarity():
    ks = 33
    y, x = torch.meshgrid(torch.arange(ks) - 16.0, torch.arange(ks) - 16.0, indexing="ij")
    s = 2.0
    gauss = torch.exp(-((x - 3) ** 2 + y ** 2) / (2 * s * s)).double()
    gauss /= gauss.sum()
    # a 2-D Gaussian has RMS radius √2 σ about its centroid; about the crop centre the 3-px offset adds 3²
    assert float(psf_size(gauss)) == pytest.approx(math.sqrt(2) * s, rel=1e-6)
    assert float(psf_size(gauss, "center")) == pytest.approx(math.sqrt(2 * s * s + 9), rel=1e-6)
    delta = torch.zeros(ks, ks, dtype=torch.float64)
    delta[16, 16] = 1
    assert float(psf_size_loss(torch.stack([delta, delta]))) == pytest.approx(0, abs=1e-9)
    stack = torch.stack([gauss, gauss, delta])
    # pairs (0,1): 0, (0,2) and (1,2): Σ|g − δ| = 2 − 2 g[16,16]
    expect = 2 * (2 - 2 * float(gauss[16, 16])) / 3
    assert float(psf_similarity_loss(stack)) == pytest.approx(expect, rel=1e-9)


# ------------------------------------------------------------------ metrics
def test_psnr_ssim_match_scikit_image():
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from raywave.training.metrics import psnr, ssim, zone_metrics

    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 48, 48, dtype=torch.float64, generator=g)
    b = (a + 0.05 * torch.randn(a.shape, dtype=torch.float64, generator=g)).clamp(0, 1)
    p, s = psnr(b, a), ssim(b, a)
    for i in range(2):
        an, bn = a[i].permute(1, 2, 0).numpy(), b[i].permute(1, 2, 0).numpy()
        assert float(p[i]) == pytest.approx(peak_signal_noise_ratio(an, bn, data_range=1.0), rel=1e-6)
        ref = structural_similarity(an, bn, data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
        assert float(s[i]) == pytest.approx(ref, abs=5e-3)  # border handling differs slightly
    z = zone_metrics(b, a)
    assert set(z) == {"centre", "edge"} and abs(z["centre"]["psnr"] - float(p.mean())) < 1.0


def test_metrics_do_not_import_torchvision():
    code = ("import sys, torch; from raywave.training.metrics import psnr; psnr(torch.rand(1,3,8,8), "
            "torch.rand(1,3,8,8)); assert 'torchvision' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------ checkpoints
def _setup():
    torch.manual_seed(123)
    net = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Dropout(0.3), torch.nn.Linear(8, 1)).double()
    opt = build_optimizer(param_groups(network=net, lr_network=1e-2))
    sched = warmup_cosine_scheduler(opt, total=10, warmup=3)
    gen = torch.Generator().manual_seed(9)
    return net, opt, sched, gen


def _train(net, opt, sched, gen, steps):
    for _ in range(steps):
        x = torch.randn(16, 4, dtype=torch.float64, generator=gen)  # the run's generator
        noise = np.random.standard_normal() + random.random()  # global numpy/python RNGs
        loss = (net(x).squeeze(-1) - x.sum(-1) - noise).square().mean()  # dropout: torch's global RNG
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()


def test_resume_is_bit_identical(tmp_path):
    np.random.seed(1), random.seed(1)
    net, opt, sched, gen = _setup()
    _train(net, opt, sched, gen, 10)
    straight = [p.detach().clone() for p in net.parameters()]

    np.random.seed(1), random.seed(1)
    net, opt, sched, gen = _setup()
    _train(net, opt, sched, gen, 5)
    path = save_checkpoint(checkpoint_path(tmp_path, 5), modules={"net": net}, optimizer=opt, scheduler=sched,
                           step=5, generators={"data": gen}, extra={"epoch": 0})
    _train(net, opt, sched, gen, 3)  # the run goes on, then "dies"; RNGs are scrambled
    torch.manual_seed(999), np.random.seed(999), random.seed(999)

    net, opt, sched, gen = _setup()
    assert latest_checkpoint(tmp_path) == path
    info = load_checkpoint(path, modules={"net": net}, optimizer=opt, scheduler=sched, generators={"data": gen})
    assert info == {"step": 5, "extra": {"epoch": 0}}
    _train(net, opt, sched, gen, 5)
    resumed = [p.detach().clone() for p in net.parameters()]
    assert all(torch.equal(a, b) for a, b in zip(straight, resumed))


def test_checkpoint_save_is_atomic_and_checks_names(tmp_path):
    net = torch.nn.Linear(2, 2)
    path = save_checkpoint(tmp_path / "c.pt", modules={"net": net}, step=1)
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]  # no temporary left behind
    with pytest.raises(ValueError, match="expected"):
        load_checkpoint(path, modules={"other": net})
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "none.pt", modules={"net": net})
    assert latest_checkpoint(tmp_path / "empty") is None


# ------------------------------------------------------------------ run folders (issue 45, item 9)
def _finished_folder(tmp_path, cfg, stage="done", stage_step=0, step=12):
    from raywave.training.config import dump_config

    run = tmp_path / "run"
    run.mkdir()
    dump_config(cfg, run / "config.yaml")
    save_checkpoint(checkpoint_path(run, step), modules={"m": torch.nn.Linear(1, 1)},
                    extra={"stage": stage, "stage_step": stage_step})
    (run / "log.jsonl").write_text("{}\n")
    return run


def test_a_changed_config_on_a_trained_folder_needs_resume_or_restart(tmp_path):
    from raywave.cli.errors import CommandError
    from raywave.cli.train_commands import prepare_run_folder

    cfg = TrainConfig()
    run = _finished_folder(tmp_path, cfg)
    assert prepare_run_folder(run, cfg, False, False) == [f"{run}: the run is finished (12 steps): evaluating it again"]
    changed = TrainConfig()
    changed.stage1.max_steps = 2
    before = (run / "config.yaml").read_text()
    with pytest.raises(CommandError, match=r"another config \(stage1.max_steps: None -> 2\).*--resume.*--restart"):
        prepare_run_folder(run, changed, False, False)
    assert (run / "config.yaml").read_text() == before  # never replaced silently
    lines = prepare_run_folder(run, changed, False, True)
    assert "replaced (continuing with the new settings): stage1.max_steps: None -> 2" in lines[0]
    lines = prepare_run_folder(run, changed, True, False)
    assert "restarting" in lines[0] and not (run / "checkpoints").exists() and not (run / "log.jsonl").exists()
    with pytest.raises(CommandError, match="exclude each other"):
        prepare_run_folder(run, changed, True, True)


def test_resuming_says_from_which_step(tmp_path):
    from raywave.cli.train_commands import prepare_run_folder

    cfg = TrainConfig()
    run = _finished_folder(tmp_path, cfg, stage="stage1", stage_step=3, step=13)
    assert prepare_run_folder(run, cfg, False, False) == [f"resuming from step 13 (stage1 step 3) of {run}"]
    assert prepare_run_folder(tmp_path / "fresh", cfg, False, False) == []


def test_train_help_has_no_sphinx_markup(capsys):
    from raywave.cli.main import main

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    out = capsys.readouterr().out
    assert "``" not in out and ":mod:" not in out and ":class:" not in out and "--resume" in out


def test_the_config_note_is_a_string_key(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("note: the corners are clipped on purpose\n")
    assert load_config(p).note == "the corners are clipped on purpose"
    from pathlib import Path

    demo = load_config(Path(__file__).parent.parent / "configs" / "aberration_demo.yaml")
    assert "on purpose" in demo.note  # the demo says its corner fields' DOE clipping is intended
