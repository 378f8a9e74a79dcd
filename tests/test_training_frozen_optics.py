"""Training with frozen optics (a baseline DOE, frozen lens): the stage-1 map of every wavelength is computed once
and each step picks its draw's PSFs, which equal the step's own map; the run's random stream is not touched by
it; a baseline shares the designed run's DOE-field cache."""

import torch

from raywave.training.config import load_config
from raywave.training.trainer import Trainer

CFG = """name: tiny_frozen
seed: 3
dtype: float64
baseline: blank
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.256, doe_distance: 0.5}}
optics: {{grid: [2, 2], eval_grid: [2, 2], ks: 16, rays: 20, depths: [.inf],
          wavelengths: {{R: [0.62, 0.66], G: [0.50, 0.55], B: [0.45, 0.48]}}}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 4, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1}}
stage1: {{max_steps: 1, batch_size: 2, warmup_steps: 0}}
stage2: {{max_steps: 1, batch_size: 2, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0}}
"""


def test_a_frozen_baseline_computes_each_wavelength_once_and_picks_the_draw(tmp_path, tiny_lens_file):
    (tmp_path / "c.yaml").write_text(CFG.format(lens=tiny_lens_file))
    cfg = load_config(tmp_path / "c.yaml")
    designed = Trainer(cfg, tmp_path / "d", progress=False)
    tr = Trainer(cfg, tmp_path / "b", baseline=True, progress=False, field_cache=designed.cache)
    assert tr.cache is designed.cache and not any(p.requires_grad for p in tr.hl.parameters())
    fields, _ = tr.step_nodes()
    seen = set()
    for _ in range(6):
        step = tr.optics_step(fields)
        state = tr.gen.get_state()
        psf, cen = tr._frozen_map(fields, step.draws)
        assert torch.equal(tr.gen.get_state(), state)  # the memo draws nothing
        want_psf, want_cen = step.forward()
        assert psf.shape == want_psf.shape == (4, 3, 16, 16)
        assert torch.allclose(psf, want_psf, rtol=0, atol=1e-12 * float(want_psf.abs().max()))
        assert torch.allclose(cen, want_cen, rtol=0, atol=1e-12)
        seen.add(tuple(step.draws.tolist()))
    assert len(seen) > 1 and list(tr._frozen_maps) == ["all"]  # several draws, one map of all six wavelengths
