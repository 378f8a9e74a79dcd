"""End-to-end design features (issue 15) on a tiny lens: the PSF-aware reconstruction (multi-Wiener + network,
gradients to the PSFs through the replay), the fabrication-aware DOE (quantised from a stage-1 step on, the
exported GDSII read back equals the evaluated element level for level, the exported lens file is that element),
the ablation table and warnings surfaced once per run."""

import json
import warnings

import numpy as np
import pytest
import torch

from raywave.training.config import load_config
from raywave.training.trainer import Trainer

CFG = """name: tiny_e2e
seed: 3
dtype: float64
checkpoint_every: 2
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.256, doe_distance: 0.5}}
optics: {{grid: [2, 2], eval_grid: [2, 2], ks: 16, rays: 20, doe_levels: 4, doe_wavelength: 0.5,
         doe_material: N-BK7, fabricate_from: 1}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 4, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1, deconv: {deconv}, ablation: {ablation}}}
pre_stage: {{steps: 1}}
stage1: {{max_steps: 2, batch_size: 2, warmup_steps: 0, lr_network: 0.001, lr_doe: 0.3}}
stage2: {{max_steps: 1, batch_size: 2, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0, noise: true}}
"""


@pytest.fixture(scope="module")
def tiny_lens(tiny_lens_file):
    return tiny_lens_file


def _cfg(tmp_path, lens, deconv="wiener", ablation="false"):
    p = tmp_path / "cfg.yaml"
    p.write_text(CFG.format(lens=lens, deconv=deconv, ablation=ablation))
    return load_config(p)


@pytest.fixture(scope="module")
def trained(tiny_lens, tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    cfg = _cfg(d, tiny_lens, ablation="true")
    tr = Trainer(cfg, d / "run", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr.run()
        tr.train_plain_network(progress=False)
    return tr


def test_fabrication_schedule(tiny_lens, tmp_path):
    """Continuous dispersive height map in the pre-stage and before ``fabricate_from``; quantised from it on
    (and in stage 2 / evaluation); a resumed run gets the state of its step back."""
    tr = Trainer(_cfg(tmp_path, tiny_lens), tmp_path / "r", progress=False)
    doe = tr.hl.doe
    assert doe.material_name == "N-BK7" and doe.design_wavelength == 0.5 and doe.quant_levels is None
    assert [tr.fabricated_at("pre", 0), tr.fabricated_at("stage1", 0), tr.fabricated_at("stage1", 1),
            tr.fabricated_at("stage2", 0), tr.fabricated_at("done", 0)] == [False, False, True, True, True]
    with torch.no_grad():
        doe.phase_map.uniform_(-7.0, 7.0)
    tr._fabrication("stage1", 1)
    prof = doe.profile_pixels().detach()
    assert doe.quant_levels == 4
    assert torch.allclose(torch.remainder(prof / (np.pi / 2) + 0.5, 1.0) - 0.5, torch.zeros_like(prof), atol=1e-9)
    tr._fabrication("pre", 0)  # back (a resumed pre-stage)
    assert doe.quant_levels is None and not doe.wrap


def test_straight_through_gradient_reaches_the_quantised_doe(tiny_lens, tmp_path):
    cfg = _cfg(tmp_path, tiny_lens)
    cfg.pre_stage.steps = 0
    tr = Trainer(cfg, tmp_path / "st", progress=False)
    before = tr.hl.doe.phase_map.detach().clone()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr.run(stop_after=2)  # stage-1 steps 0 (continuous) and 1 (quantised)
    assert tr.hl.doe.quant_levels == 4
    assert not torch.equal(tr.hl.doe.phase_map.detach(), before)


def test_exported_element_is_the_evaluated_one(trained):
    """masks.gds read back = the level map of the DOE that was evaluated, level for level; lens.json loads as
    the same element (phase at several wavelengths: wrapped, quantised, dispersive)."""
    from raywave.doe.fabrication import levels_from_masks, read_mask_file
    from raywave.hybrid.build import load_hybrid

    tr = trained
    doe = tr.hl.doe
    final = tr.export()
    report = json.loads((final / "masks" / "report.json").read_text())
    assert report["levels"] == 4 and report["evaluated_as_fabricated"] is True and report["material"] == "N-BK7"
    masks = read_mask_file(final / "masks" / "masks.gds", doe.shape, doe.pitch)
    assert masks.shape[0] == 2
    got = levels_from_masks(masks)
    with torch.no_grad():
        evaluated = torch.round(doe.profile_pixels() / (2 * np.pi / 4)).long().remainder(4).numpy()
    assert np.array_equal(got, evaluated)
    hl = load_hybrid(final / "lens.json")
    assert hl.doe.quant_levels == 4 and hl.doe.material_name == "N-BK7"
    for wl in (0.45, 0.5, 0.62):
        a = hl.doe.phase(wl, None, 1).detach()
        b = doe.phase(wl, None, 1).detach()
        assert torch.allclose(a, b, atol=1e-12)


def test_evaluation_has_the_ablation_rows(trained):
    from raywave.cli.train_commands import ablation_table, format_ablation

    m = trained.evaluate()
    mean = m["mean"]
    for k in ("psnr", "psnr_input", "psnr_deconv", "psnr_network_only", "energy_outside_max"):
        assert k in mean and np.isfinite(mean[k])
    table = ablation_table({"designed": m, "baseline": m})
    assert set(table["designed"]) == {"sensor image", "network only", "deconvolution only", "reconstruction"}
    text = format_ablation(table, "wiener")
    assert "deconvolution + network" in text and text.count("\n") == 9


def test_psf_gradient_flows_through_the_deconvolution(trained):
    """The reconstruction depends on the PSFs it deconvolves with: ∂(restored)/∂PSF is non-zero and finite."""
    tr = trained
    pm = tr.stage2_map
    img = tr.eval_images_tensor()[:1]
    psf = pm.psf.clone().requires_grad_(True)
    ext = tr._extent(img.shape[-2:], (0.0, 0.0))
    rec = tr.reconstruct(img, psf, pm.centers, [ext], pm.positions)
    rec.square().mean().backward()
    assert psf.grad is not None and torch.isfinite(psf.grad).all() and psf.grad.abs().max() > 0


def test_warnings_surface_once_per_run(tiny_lens, tmp_path):
    tr = Trainer(_cfg(tmp_path, tiny_lens, deconv="none"), tmp_path / "w", progress=False)
    with pytest.warns(UserWarning, match="phase slope 1.5"):
        for v in (1.5, 1.7, 1.5):
            with tr.surface_warnings():
                warnings.warn(f"phase slope {v} × Nyquist", UserWarning)
    lines = (tmp_path / "w" / "warnings.jsonl").read_text().splitlines()
    assert len(lines) == 1  # the same warning with other numbers is the same warning
    shown = warnings.formatwarning(*_last_warning(tr, "phase slope 2.5 × Nyquist"))
    assert shown.count("phase slope") == 1  # the console shows it once (not again as the JSON record's "source line")
    from raywave.hybrid import DOEApertureWarning

    with pytest.warns(DOEApertureWarning, match="blocks 40"):  # a warning class with attributes re-issues too
        with tr.surface_warnings():
            warnings.warn(DOEApertureWarning("", [(0.4, 1.0, "field [0, 9] at 0.5 µm")], (2.0, 2.0)))


def _last_warning(tr, message):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tr._warn_once(message, RuntimeWarning)
    (w,) = caught
    return w.message, w.category, w.filename, w.lineno
