"""The memory estimate (issue 45, item 2): every allocation that scales with user input is checked by
raywave.utils.errors.check_allocation before it starts, against the memory available or a configured limit
(RAYWAVE_MEMORY_LIMIT / raywave --memory-limit); a refusal names the option and the likely unit slip."""

import os

import pytest

from raywave.cli.main import main
from raywave.utils.errors import (MEMORY_LIMIT_ENV, MemoryLimitError, check_allocation, memory_limit,
                                  parse_bytes)


@pytest.mark.parametrize("text,n", [("1024", 1024), ("8G", 8 * 1024**3), ("512MiB", 512 * 1024**2),
                                    ("1.5GB", 1_500_000_000), ("2k", 2048)])
def test_parse_bytes(text, n):
    assert parse_bytes(text) == n


@pytest.mark.parametrize("text", ["", "lots", "-1G", "0", "3X", "inf"])
def test_parse_bytes_refuses(text):
    with pytest.raises(ValueError, match="not a memory size"):
        parse_bytes(text)


def test_the_configured_limit_refuses_what_would_fit_otherwise(monkeypatch):
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    assert memory_limit() is None
    check_allocation(1e6, "a small array", "no knob")
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1M")
    with pytest.raises(MemoryLimitError, match=r"a 2 MB array needs about 1.91 MiB.*only 1 MiB is allowed.*"
                                                 r"RAYWAVE_MEMORY_LIMIT.*the knob"):
        check_allocation(2e6, "a 2 MB array", "the knob")
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "much")
    with pytest.raises(ValueError, match="RAYWAVE_MEMORY_LIMIT"):
        check_allocation(1.0, "x", "y")


def test_the_doe_grid_is_estimated_before_anything_is_traced(monkeypatch):
    """load_hybrid refuses a DOE grid over the limit itself (no PSF call needed), naming the options."""
    from raywave.assembly.build import load_hybrid
    from raywave.hybrid import HybridLens

    monkeypatch.setenv(MEMORY_LIMIT_ENV, "10M")

    def no_trace(*a, **k):  # pragma: no cover - reached only if the check came too late
        raise AssertionError("traced before the memory check")

    monkeypatch.setattr(HybridLens, "doe_fields", no_trace)
    with pytest.raises(MemoryLimitError, match=r"3000×3000-pixel DOE.*--doe-pitch, in mm.*--oversample.*--doe-size"):
        load_hybrid("hybrid_asphere")  # 3000² pixels of 1 µm
    with pytest.raises(MemoryLimitError, match=r"0.0001 µm, finer than any DOE pixel: pitches are in mm"):
        load_hybrid("singlet", doe_pitch=1e-7)


def test_cli_memory_limit_option_and_its_scope(capsys, monkeypatch):
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    assert main(["--memory-limit", "10M", "psf", "hybrid_asphere", "--ks", "8", "--rays", "8"]) == 2
    err = capsys.readouterr().err
    assert "needs about" in err and "--memory-limit" in err and "--doe-pitch" in err and "Traceback" not in err
    assert MEMORY_LIMIT_ENV not in os.environ  # one command's limit
    assert main(["--memory-limit", "lots", "info", "singlet"]) == 2
    assert "--memory-limit" in capsys.readouterr().err


def test_doe_pitch_given_in_um_is_refused_before_any_work(capsys):
    """Before: `raywave psf hybrid_asphere --doe-pitch 1` grew to 21 GB (a raw RuntimeError from torch.cdist under
    a memory limit). Now the CLI refuses the option itself, naming mm and µm."""
    assert main(["psf", "hybrid_asphere", "--doe-pitch", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--doe-pitch" in err and "1 mm = 1000 µm" in err and "0.001 mm = 1 µm" in err
