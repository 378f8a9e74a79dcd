"""Progress on every long command (issue 45, item 4): tqdm bars in the user's units with an ETA, --quiet before or
after any command turns them off, and doomed work fails before the expensive part."""

import argparse
import re
import time

import pytest

from raywave.cli import progress
from raywave.cli.main import _leaf_parsers, build_parser, main
from raywave.lens.build import ideal_lens, save_lens


@pytest.fixture
def no_delay(monkeypatch):
    monkeypatch.setattr(progress, "DELAY_S", 0.0)


def test_quiet_is_accepted_before_and_after_every_command():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for p in _leaf_parsers(sub):
        assert any("--quiet" in a.option_strings for a in p._actions), p.prog
    args = parser.parse_args(["--quiet", "info", "singlet"])
    assert progress.is_quiet(args)
    assert progress.is_quiet(parser.parse_args(["info", "singlet", "--quiet"]))
    assert not progress.is_quiet(parser.parse_args(["info", "singlet"]))


def test_a_bar_counts_units_and_ticks_during_one_long_unit(no_delay, capsys):
    args = argparse.Namespace(quiet=False)
    pbar = progress.bar(args, 2, "PSF", "demo")
    with pbar, progress.ticking(pbar, every_s=0.05):
        time.sleep(0.3)  # one long unit: the elapsed time is redrawn meanwhile
        pbar.update(2)
    err = capsys.readouterr().err
    assert "demo" in err and "PSF" in err and "2/2" in err
    assert err.count("0/2") >= 3  # redrawn while the unit ran
    quiet = progress.bar(argparse.Namespace(quiet=True), 2, "PSF", "demo")
    assert quiet.disable


def test_psf_shows_a_bar_and_quiet_hides_it(no_delay, capsys):
    assert main(["psf", "singlet", "--ks", "8", "--rays", "8"]) == 0
    assert "psf:" in capsys.readouterr().err
    assert main(["--quiet", "psf", "singlet", "--ks", "8", "--rays", "8"]) == 0
    assert "psf:" not in capsys.readouterr().err


def test_compare_counts_models_times_fields(no_delay, tmp_path, capsys):
    """Before: `raywave compare ... --models all` ran 12 min without output."""
    path = tmp_path / "ideal.json"
    save_lens(ideal_lens(5.0, f_number=4.0, wavelengths=(0.55,)), path)
    assert main(["compare", str(path), "--field", "0", "--field", "0,2", "--models", "raywave,paraxial", "--ks", "8",
                 "--sensor-pitch", "0.001", "--doe-distance", "1", "-o", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    # the bar counts 4 PSFs (2 models × 2 fields); which counts get drawn depends on tqdm's redraw interval
    assert re.search(r"\b[0-4]/4\b", err) and "PSF" in err


def test_a_dark_field_fails_before_the_wave_computation(monkeypatch, capsys):
    """Before: `raywave psf hybrid_asphere --field 40` worked 206 s, then said no light reached the sensor. The beam
    misses the 3 mm DOE: refused from one trace, before any PSF is computed."""
    from raywave.hybrid import HybridLens

    def no_psf(*a, **k):  # pragma: no cover - reached only if the check came too late
        raise AssertionError("the PSF was computed")

    monkeypatch.setattr(HybridLens, "psf_result", no_psf)
    assert main(["psf", "hybrid_asphere", "--field", "40"]) == 2
    err = capsys.readouterr().err
    assert "misses the 3×3 mm DOE aperture" in err and err.count("\n") == 1
    assert main(["compare", "hybrid_asphere", "--field", "0", "--field", "40", "--models", "paraxial", "--reference", "paraxial"]) == 2
    assert "(0, 40)" in capsys.readouterr().err


def test_a_field_far_outside_the_lens_is_one_clean_error(capsys):
    """(A lens file without a DOE: the default DOE sized for an 80° beam is refused by the memory estimate.)"""
    assert main(["--quiet", "psf", "singlet", "--field", "80", "--ks", "8", "--rays", "8"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("raywave: error:") and err.count("\n") == 1 and "Traceback" not in err


def test_a_bar_drawn_only_by_its_ticks_is_cleared_before_an_error(capsys):
    """Under load a long unit of work (one PSF that ends in an error) outlasted the bar's delay, so only the ticking
    thread drew the bar; tqdm did not clear it on close, and the error line joined the bar (as a terminal shows it:
    what follows the last carriage return of the line)."""
    pbar = progress.tqdm(total=1, unit="PSF", desc="psf", file=progress.sys.stderr, delay=0.05, leave=False)
    with pytest.raises(ValueError):
        with pbar, progress.ticking(pbar, every_s=0.02):
            time.sleep(0.3)
            raise ValueError("no light")
    print("raywave: error: no light", file=progress.sys.stderr)
    err = capsys.readouterr().err
    assert "psf:" in err  # the bar was drawn
    shown = [ln.rsplit("\r", 1)[-1] for ln in err.split("\n") if ln.rsplit("\r", 1)[-1].strip()]
    assert shown == ["raywave: error: no light"], shown
