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
