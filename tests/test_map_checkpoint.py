"""A resumable PSF map (``psf_map(..., checkpoint=FOLDER)``, issue 43): interrupted and run again it computes only
the chunks it had not finished, and gives the same map bit for bit as one uninterrupted run; a folder of another
map is refused before any PSF is computed."""

import json

import pytest
import torch

import raywave.imaging.psfmap as psfmap_module
from raywave.assembly.build import load_hybrid
from raywave.cli.main import main
from raywave.doe import CubicDOE
from raywave.imaging import psf_map
from raywave.lens.build import bundled_lens_path

KS = 16
MAP = {"grid": (2, 2), "wavelengths": (0.53,), "ks": KS, "batch": 1, "rays": 16}
pytestmark = pytest.mark.filterwarnings("ignore::raywave.imaging.psfmap.PSFCropWarning")


@pytest.fixture(scope="module")
def hl():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


@pytest.fixture(scope="module")
def whole(hl):
    return psf_map(hl, **MAP)


REAL = psfmap_module.psf_map_points


class Interrupt(Exception):
    pass


def _counting(monkeypatch, stop_after=None):
    """Count the model calls of psf_map (one per chunk); raise Interrupt on call ``stop_after + 1``."""
    calls = []
    real = REAL

    def wrapped(*a, **k):
        if stop_after is not None and len(calls) == stop_after:
            raise Interrupt
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(psfmap_module, "psf_map_points", wrapped)
    return calls


def test_an_interrupted_map_resumes_where_it_stopped_and_equals_one_run(hl, whole, tmp_path, monkeypatch):
    folder = tmp_path / "map"
    _counting(monkeypatch, stop_after=2)
    with pytest.raises(Interrupt):
        psf_map(hl, checkpoint=folder, **MAP)
    assert sorted(p.name for p in folder.glob("d*.pt")) == ["d0_0_1.pt", "d0_1_2.pt"]
    calls = _counting(monkeypatch)
    again = psf_map(hl, checkpoint=folder, **MAP)
    assert len(calls) == 2  # the two chunks not yet done (4 field points, one per call)
    for name in ("psf", "centers", "energy_outside", "fields"):
        assert torch.equal(getattr(again, name), getattr(whole, name)), name
    assert again.pitch == whole.pitch
    calls = _counting(monkeypatch)
    done = psf_map(hl, checkpoint=folder, **MAP)
    assert len(calls) == 0 and torch.equal(done.psf, whole.psf)


def test_a_folder_of_another_map_is_refused_before_any_psf(hl, tmp_path, monkeypatch):
    folder = tmp_path / "map"
    psf_map(hl, checkpoint=folder, **{**MAP, "grid": (1, 1)})
    calls = _counting(monkeypatch)
    with pytest.raises(ValueError, match=r"holds another map \(its .*n_fields"):
        psf_map(hl, checkpoint=folder, **MAP)
    other = hl.with_doe(CubicDOE(0.0, hl.doe.shape, hl.doe.pitch))
    psf_map(other, checkpoint=tmp_path / "cubic", **{**MAP, "grid": (1, 1)})
    with torch.no_grad():
        other.doe.alpha.add_(1.0)  # the DOE's phase, not only the lens, is part of the map's identity
    with pytest.raises(ValueError, match=r"model\.state"):
        psf_map(other, checkpoint=tmp_path / "cubic", **{**MAP, "grid": (1, 1)})
    assert len(calls) == 1  # the cubic DOE's own map only
    with pytest.raises(ValueError, match="grad=True"):
        psf_map(hl, checkpoint=tmp_path / "g", grad=True, **MAP)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        psf_map(hl, checkpoint=tmp_path / "file", **MAP)


def test_the_psfmap_command_resumes_from_its_checkpoint_folder(tmp_path, capsys):
    folder = tmp_path / "ck"
    args = ["psfmap", "hybrid_asphere", "--grid", "1", "--wavelengths", "0.53", "--ks", "16", "--rays", "16",
            "--checkpoint", str(folder), "--json", "--quiet"]
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (folder / "map.json").exists() and len(list(folder.glob("d*.pt"))) == 1
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == first
    assert main([*args[:3], "2", *args[4:]]) != 0
    assert "--checkpoint" in capsys.readouterr().err


def test_the_trainers_evaluation_map_replaces_a_stale_folder_and_removes_its_own(hl, tmp_path):
    """The trainer keeps a large evaluation map's chunks in the run folder while it computes it (resumable), replaces
    a folder that another map left there (optics changed before a resume), and removes the folder once the map is
    whole."""
    from raywave.training.trainer import _resumable_map

    folder = tmp_path / "eval_map_HybridLens"
    psf_map(hl, checkpoint=folder, **{**MAP, "grid": (1, 1)})  # another map's folder
    pm = _resumable_map(folder, hl, **MAP)
    assert not folder.exists()
    assert torch.equal(pm.psf, psf_map(hl, **MAP).psf)
