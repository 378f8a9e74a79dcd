"""Device correctness without a GPU: the user paths run with :class:`device_guard.StrayTensors` active, so a tensor
that raywave makes without a device on the data path (a CPU tensor beside a GPU lens's tensors) fails here, on
the CPU, as it would on CUDA (tests/test_device_paths.py runs the same paths on a GPU where one is present).

Covered: PSF maps (default exit-pupil edge, the DOE-plane edge, the DOE-field cache), the replayed training step
of a hybrid lens (both edges) and a tiny end-to-end training run (pre-stage, stage 1 with the quantised DOE,
stage 2, evaluation, export)."""

from __future__ import annotations

import warnings

import pytest
import torch

from device_guard import StrayTensors
from raywave.assembly.build import load_hybrid
from raywave.imaging import DOEFieldCache, psf_map


@pytest.mark.parametrize("stop_edge", [None, "doe"])
def test_psf_map_makes_no_stray_tensors(stop_edge):
    hl = load_hybrid("hybrid_asphere", stop_edge=stop_edge)
    cache = DOEFieldCache(max_bytes=None)
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        maps = [psf_map(hl, (1, 2), wavelengths=(0.53,), ks=32, cache=c) for c in (None, cache, cache)]
    assert all(torch.isfinite(m.psf).all() for m in maps)


@pytest.mark.parametrize("stop_edge", ["doe", "exit_pupil"])
def test_replayed_step_makes_no_stray_tensors(stop_edge):
    import test_training_replay as t

    g = torch.Generator().manual_seed(1)
    patches, target = (torch.rand(9, 3, 24, 24, dtype=torch.float64, generator=g) for _ in range(2))
    weight = 0.3 * torch.randn(3, 3, 3, 3, dtype=torch.float64, generator=g)
    hl = t.small_hybrid(stop_edge=stop_edge)
    step = t.make_step(hl, 3, 2, torch.Generator().manual_seed(7))
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        psf, center = step.leaves()
        t.render_and_loss(psf, center, patches, target, weight).backward()
        step.backward()
    assert hl.doe.phase_map.grad is not None and torch.isfinite(hl.doe.phase_map.grad).all()


def test_training_run_makes_no_stray_tensors(tiny_lens_file, tmp_path):
    from test_training_e2e import _cfg

    from raywave.training.trainer import Trainer

    tr = Trainer(_cfg(tmp_path, tiny_lens_file), tmp_path / "run", progress=False)
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        tr.run()
        tr.evaluate()
        folder = tr.export()
    assert (folder / "masks" / "masks.gds").exists()


def test_the_guard_catches_a_stray_tensor():
    """The guard itself: a raywave function that makes a tensor without a device fails under it."""
    from raywave.imaging.psfmap import normalised_grid

    with StrayTensors():
        assert normalised_grid((2, 2)).device.type == "meta"  # device=None: the caller's choice, here none
        assert normalised_grid((2, 2), device="cpu").device.type == "cpu"


def _model_names():
    from raywave.models.interface import MODEL_NAMES

    return list(MODEL_NAMES)


@pytest.mark.parametrize("name", _model_names())
def test_comparison_models_make_no_stray_tensors(name):
    """Every PSF model of raywave.models (and the engine through the same interface), on axis and off axis."""
    from test_models_compare import LAM, ideal_hybrid

    from raywave.models.interface import make_model

    m = make_model(name, ideal_hybrid(n=1100), **({"n_pupil": 64} if name == "exit_pupil" else {}))
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        r = m.psf_result([(0.0, 0.0), (0.0, 2.0)], [LAM], ks=16)
    assert torch.isfinite(r.psf).all() and r.psf.shape == (2, 1, 16, 16)


def test_edof_run_with_the_paraxial_baseline_makes_no_stray_tensors(tiny_lens_file, tmp_path):
    """Several depths, the EDoF loss and the paraxial baseline's DOE design (built inside the guard too)."""
    from test_training_baselines import CFG

    from raywave.training.config import load_config
    from raywave.training.trainer import Trainer

    p = tmp_path / "edof.yaml"
    p.write_text(CFG.format(lens=tiny_lens_file, baseline="paraxial"))
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        for baseline in (False, True):
            tr = Trainer(load_config(p), tmp_path / f"run{int(baseline)}", baseline=baseline, progress=False)
            tr.run()
            tr.evaluate()


def test_cli_psf_and_render_make_no_stray_tensors(tmp_path):
    """``raywave psf`` and ``raywave render`` (map, blur, sensor noise) compute inside the guard."""
    import imageio.v3 as iio
    import numpy as np

    from raywave.cli.main import main

    iio.imwrite(tmp_path / "in.png", (np.random.default_rng(0).random((24, 40, 3)) * 255).astype(np.uint8))
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        assert main(["psf", "hybrid_asphere", "--field", "0", "5", "--ks", "16", "--rays", "16", "--json"]) == 0
        assert main(["render", "hybrid_asphere", str(tmp_path / "in.png"), "--grid", "1", "2", "--ks", "16",
                     "--rays", "16", "--noise", "-o", str(tmp_path / "out.png")]) == 0


def test_cli_compare_makes_no_stray_tensors(tmp_path):
    """``raywave compare`` (every model, the Debye ground truth, the table) computes inside the guard."""
    from raywave.cli.main import main
    from raywave.lens.build import ideal_lens, save_lens

    save_lens(ideal_lens(5.0, f_number=4.0, wavelengths=(0.55,)), tmp_path / "ideal.json")
    with warnings.catch_warnings(), StrayTensors():
        warnings.simplefilter("ignore")
        assert main(["compare", str(tmp_path / "ideal.json"), "--fields", "0", "0,2", "--ks", "16", "--sensor-pitch",
                     "0.001", "--doe-distance", "1", "--device", "cpu", "-o", str(tmp_path / "cmp")]) == 0
