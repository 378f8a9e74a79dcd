"""The caustic fallback's carry and its memory (issue 47, h47m): the estimate of each exit (the plain carry from the
fallback's plane or a farther plane before the fold, and the scaled carry) counts the windowed angular spectrum's FFT
grid (raywave.hybrid.coherent.geometry.CARRY_BYTES, measured by benchmarks/fallback_memory.py), the plane's fit test
uses it, and the carry is refused before anything of its size is allocated. The bundled singlet 5 mm before focus
(tests/test_caustic_fallback.py): its fallback's plane 7.6 mm before the DOE plane, ~322 samples a side."""

import math
import warnings

import pytest
import torch

import raywave.hybrid.coherent.exit_pupil as ep
import raywave.hybrid.coherent.geometry as g
from raywave.assembly.build import load_hybrid
from raywave.hybrid.coherent import StopEdgeWarning
from raywave.hybrid.coherent.settings import Source
from raywave.utils.errors import MEMORY_LIMIT_ENV, MemoryLimitError
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import window_transfer

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")

NEAR, PITCH = 93.5, 2e-3


def _singlet():
    return load_hybrid("singlet", doe_distance=NEAR, doe_size=2.0, fields=[[0.0, 0.0]], sensor_pitch=PITCH)


def test_the_fft_grid_is_the_propagations_own_and_the_estimate_counts_it():
    """carry_fft_shape is window_transfer's FFT size (host numbers, nothing allocated); the estimate grows with the
    graph and the scaled carry's sphere; a refusal names the carry, its windows, its FFT grid and what to do."""
    for n_from, n_doe, dz, carrier in (((300, 280), (120, 90), 7.6, (0.0, 0.0)), ((41, 77), (64, 64), 0.3,
                                                                                  (0.2, -0.1))):
        env = torch.zeros(n_from, dtype=torch.complex128)
        f = Field(env, Grid((0.0, 0.0), 2e-3, n_from), 0.55, 1.0, carrier)
        size = window_transfer(f, Grid((0.01, -0.02), 2e-3, n_doe), dz).size
        assert g.carry_fft_shape(n_from, n_doe, 2e-3, dz, (0.55, 1.0), carrier) == tuple(size)
    fft = (5000, 4000)
    plain = g.carry_bytes((2000, 2000), fft, graph=False)
    assert plain == g.CARRY_BYTES[False][0] * 2e7 + g.CARRY_BYTES[False][1] * 4e6
    assert g.carry_bytes((2000, 2000), fft, graph=True) > plain
    # the scaled carry: its sphere's factor after the propagation (the larger of the two), here the propagation
    assert g.carry_bytes((2000, 2000), fft, (1000, 1000), graph=False) == plain
    big = g.carry_bytes((2000, 2000), fft, (9000, 9000), graph=False)
    assert big == g.CARRY_BYTES[False][1] * 4e6 + g.CARRY_BYTES[False][2] * 8.1e7 > plain
    # the old estimate, 120 B a sample of the larger window, admitted under half of what this carry needs
    assert plain > 2 * 2000 * 2000 * g.WINDOW_BYTES[("fallback", False)]


def test_a_carry_over_the_limit_is_refused_with_its_windows_named(monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1GiB")
    g.check_carry_memory((2000, 2000), (900, 800), (3000, 3000), 1e-3, graph=False)  # 0.62 GB
    with pytest.raises(MemoryLimitError, match=r"caustic fallback's scaled carry of the 4000×4000-sample field "
                                               r"\(simulation pitch 1 µm\) to the 900×800-sample DOE-plane window "
                                               r"\(a 5000×5000 FFT grid\).*coarser DOE pitch"):
        g.check_carry_memory((4000, 4000), (900, 800), (5000, 5000), 1e-3, scaled=True, graph=False)


def _fallback_case(monkeypatch):
    """The singlet's fallback: its source, planes, the fallback plane and the others, and the carry's plan as the
    engine makes it (captured from a PSF call stopped there)."""
    hl = _singlet()
    lens, wl = hl.lens, hl.lens.primary_wavelength
    src = Source((0.0, 0.0), wl, None, lens.field_type)
    seen = {}
    orig = ep._fallback_fits

    class Stop(Exception):
        pass

    def capture(*a, **k):
        seen["plan"] = k["carry"]
        raise Stop

    monkeypatch.setattr(ep, "_fallback_fits", capture)
    with torch.no_grad(), warnings.catch_warnings(), pytest.raises(Stop):
        warnings.simplefilter("ignore")
        hl.psf_result((0.0, 0.0), ks=32)
    monkeypatch.setattr(ep, "_fallback_fits", orig)
    with torch.no_grad():
        z_from, est, others = ep._fallback_planes(lens, src, hl.exit_pupil_z(wl), hl.doe_z())
    return hl, src, (z_from, est, others), seen["plan"]


def _carry_estimate(hl, src, plan, z):
    """The fit test's estimate (bytes) of the plain carry from the plane ``z``."""
    p = hl.doe.pitch
    side, xb = ep._plane_side(hl.lens, src, z, p)
    n_from = ep._from_window(plan, xb, z, p)
    assert n_from[0] >= 1.2 * (xb[3] - xb[2]) / p and n_from[1] >= 1.2 * (xb[1] - xb[0]) / p
    fft = g.carry_fft_shape(n_from, plan.window, p, plan.z_doe - z, plan.medium, plan.carrier)
    return g.carry_bytes(n_from, fft, graph=False), n_from


def test_the_fit_test_counts_the_carry_and_steps_to_a_plane_that_fits(monkeypatch):
    """With a limit between the carry's estimate from the fallback's plane and that from the next plane, the
    fallback steps to the next plane (where the old per-window estimate, 120 B a sample, admitted the first); below
    both, no plane fits the plain carry (None: the caller tries the scaled carry)."""
    hl, src, (z_from, est, others), plan = _fallback_case(monkeypatch)
    assert plan.window[0] > 10 and plan.window[1] > 10 and plan.z_doe == pytest.approx(hl.doe_z())
    first, n_first = _carry_estimate(hl, src, plan, z_from)
    z_next = others[0][0]
    second, _ = _carry_estimate(hl, src, plan, z_next)
    assert second < first
    limit = int(0.5 * (first + second))
    assert n_first[0] * n_first[1] * g.WINDOW_BYTES[("fallback", False)] < limit  # the old estimate's verdict: fits
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(limit))
    with torch.no_grad(), pytest.warns(StopEdgeWarning, match="where the geometric-optics field is off by"):
        assert ep._fallback_fits(hl.lens, src, z_from, hl.doe_z(), hl.doe.pitch, est, others, carry=plan) == z_next
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(int(0.5 * second)))
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        small = [z for z, _ in others if _carry_estimate(hl, src, plan, z)[0] <= 0.5 * second]
        if not small:
            assert ep._fallback_fits(hl.lens, src, z_from, hl.doe_z(), hl.doe.pitch, est, others, final=False,
                                     carry=plan) is None


def test_a_carry_that_does_not_fit_is_refused_before_it_is_allocated(monkeypatch):
    """The fit test bypassed (the fallback's plane taken whatever its size) and the carry's bytes a sample raised so
    that its estimate exceeds a 1 GiB limit that every other step fits: the PSF raises MemoryLimitError naming the
    carry before the angular spectrum runs (no propagate_window call)."""
    hl, src, (z_from, est, others), plan = _fallback_case(monkeypatch)
    first, _ = _carry_estimate(hl, src, plan, z_from)
    # the fit test's estimate is of a window ≥ the construction's (1.8× its samples on this singlet since the
    # short-reach band): 4 GiB by it puts the carry's own estimate well over the 1 GiB limit
    scale = math.ceil(4 * 2**30 / first)
    monkeypatch.setitem(g.CARRY_BYTES, False, tuple(b * scale for b in g.CARRY_BYTES[False]))
    monkeypatch.setattr(ep, "_fallback_fits", lambda *a, **k: a[2])
    calls = []
    monkeypatch.setattr(ep, "propagate_window", lambda *a, **k: calls.append(1))
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1GiB")
    with torch.no_grad(), warnings.catch_warnings(), pytest.raises(
            MemoryLimitError, match=r"caustic fallback's carry of the \d+×\d+-sample field .* FFT grid"):
        warnings.simplefilter("ignore")
        hl.psf_result((0.0, 0.0), ks=32)
    assert not calls
