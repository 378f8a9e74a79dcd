"""The training's lens set-up for any lens a user names: bundled names beside a folder of that name, the sensor
of a lens file without one, and a pixel DOE too large to train refused before anything is allocated."""

import math
import os

import pytest

from raywave.lens.build import BUNDLED, resolve_lens_path
from raywave.training.config import LensConfig, apply_overrides, load_config
from raywave.training.trainer import PIXEL_DOE_TRAIN_BYTES, build_hybrid
from raywave.utils.errors import MemoryLimitError


def test_a_bundled_name_is_not_shadowed_by_a_folder_of_that_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "singlet").mkdir()  # e.g. the run folder of `raywave train -o singlet`
    assert resolve_lens_path("singlet") == BUNDLED / "singlet.json"
    (tmp_path / "mine.json").write_text("{}")
    assert resolve_lens_path("mine.json").resolve() == tmp_path / "mine.json"
    with pytest.raises(FileNotFoundError, match="nor a bundled lens"):
        resolve_lens_path("no_such_lens")


def test_sensor_size_key_replaces_the_lens_files_sensor(tmp_path):
    cfg = load_config(os.path.join(os.path.dirname(__file__), "..", "configs", "aberration_demo.yaml"))
    cfg = apply_overrides(cfg, ["lens.file=singlet", "lens.sensor_size=[4.0, 3.0]", "lens.doe_size=2.0"])
    hl = build_hybrid(cfg.lens)
    assert hl.lens.sensor_size == (4.0, 3.0)
    with pytest.raises(ValueError, match=r"lens.sensor_size\[1\] must be > 0"):
        apply_overrides(cfg, ["lens.sensor_size=[4.0, -3.0]"])


def test_a_pixel_doe_too_large_to_train_is_refused_before_allocation(monkeypatch):
    import raywave.utils.errors as errors

    lc = LensConfig(file="hybrid_asphere", doe_pitch=0.001)  # 3000² pixels
    need = 3000 * 3000 * PIXEL_DOE_TRAIN_BYTES
    monkeypatch.setattr(errors, "available_memory", lambda: int(1.5 * need))  # < need / 0.5
    with pytest.raises(MemoryLimitError, match=r"3000×3000 pixel DOE of hybrid_asphere.*lens.doe_size"):
        build_hybrid(lc)
    monkeypatch.setattr(errors, "available_memory", lambda: int(2.5 * need))
    hl = build_hybrid(lc)
    assert tuple(hl.doe.shape) == (3000, 3000) and math.isclose(hl.doe.pitch, 0.001)


def test_training_patches_avoid_map_nodes_that_receive_no_light(tmp_path):
    """A DOE smaller than the corner beams leaves those PSFs dark: a stage-2 patch there is a black image the
    network would learn to invent, so patches are drawn around lit nodes only (with a warning); a fully lit map
    draws exactly as before (the same random stream)."""
    from types import SimpleNamespace

    import torch

    from raywave.imaging import normalised_grid
    from raywave.training.trainer import DarkRegionWarning, Trainer, _nearest_node

    tr = Trainer.__new__(Trainer)  # only the patch placement: no lens, no data
    tr.pitch, tr.sensor_size, tr.gen, tr.run_dir, tr._seen_warnings = 0.003, (5.76, 3.24), None, tmp_path, set()
    pos = normalised_grid((3, 3))
    psf = torch.rand(1, 3, 3, 3, 4, 4)
    lit_map = SimpleNamespace(psf=psf, positions=pos)
    tr.gen = torch.Generator().manual_seed(0)
    a = [tr._random_extent((32, 32), lit_map) for _ in range(20)]
    tr.gen = torch.Generator().manual_seed(0)
    assert a == [tr._random_extent((32, 32)) for _ in range(20)]  # all lit: unchanged draws
    dark = psf.clone()
    dark[..., 0, :, :, :] = 0.0  # the bottom row of nodes (v = −2/3) is dark at one wavelength
    dark[:, 1, 1, 2] = 0.0  # and the centre-right node
    dark_map = SimpleNamespace(psf=dark, positions=pos)
    tr.gen = torch.Generator().manual_seed(1)
    with pytest.warns(DarkRegionWarning, match="4 of the 9 nodes"):
        ext = [tr._random_extent((32, 32), dark_map) for _ in range(200)]
    for u0, u1, v0, v1 in ext:
        i, j = _nearest_node(pos, torch.tensor([(u0 + u1) / 2, (v0 + v1) / 2], dtype=torch.float64))
        assert i != 0 and (i, j) != (1, 2)
    with pytest.raises(ValueError, match="no node of the PSF map receives light"):
        tr._random_extent((32, 32), SimpleNamespace(psf=torch.zeros_like(psf), positions=pos))


def test_stage1_patches_avoid_the_steps_dark_nodes(tmp_path, tiny_lens_file):
    """Stage 1 places its patches from this step's own map: with a DOE that only the centre beam reaches (0.03 mm
    at 1.5 mm behind an ideal f = 2 mm lens, the DOE-plane stop edge: the other 8 nodes' PSFs are exactly 0),
    every training patch of stages 1 and 2 lies around the centre node, and the run says why, once per map."""
    import torch

    from raywave.training.trainer import Trainer, _nearest_node

    cfg = tmp_path / "dark.yaml"
    cfg.write_text(f"""name: dark
seed: 3
dtype: float64
lens: {{file: {tiny_lens_file}, doe_pitch: 0.002, doe_size: 0.03, doe_distance: 1.5, stop_edge: doe}}
optics: {{grid: [3, 3], eval_grid: [3, 3], ks: 16, rays: 20}}
data: {{source: dead_leaves, patch_size: 16, dead_leaves_count: 8, eval_size: 16}}
network: {{kind: unet, width: 4, depth: 1}}
pre_stage: {{steps: 0}}
stage1: {{max_steps: 2, batch_size: 4, warmup_steps: 0}}
stage2: {{max_steps: 1, batch_size: 4, warmup_steps: 0}}
""")
    tr = Trainer(load_config(cfg), tmp_path / "run", progress=False)
    placed, lit_uv = [], tr._lit_uv
    tr._lit_uv = lambda uv, positions, lit: placed.append((lit_uv(uv, positions, lit), positions)) or placed[-1][0]
    with pytest.warns(UserWarning):
        tr.run()
    assert len(placed) == 2 * 4 + 4
    for uv, positions in placed:
        assert _nearest_node(positions, torch.tensor(uv, dtype=torch.float64)) == (1, 1)
    logged = (tmp_path / "run" / "warnings.jsonl").read_text()
    assert logged.count("DarkRegionWarning") == 1 and "8 of the 9 nodes" in logged
