"""The Fresnel integrals in torch (:func:`raywave.utils.fresnel.fresnel`) against two independent references:
scipy (cephes) and mpmath (arbitrary precision); odd symmetry, limits, dtype and device; the knife-edge factor's
CPU table (:func:`raywave.hybrid.coherent.stop_edge._fresnel_table_values`) against both; the knife-edge factor's
three backends (:data:`raywave.hybrid.coherent.stop_edge.FRESNEL_CPU`) agree."""

import math

import mpmath as mp
import numpy as np
import pytest
import torch
from scipy.special import fresnel as scipy_fresnel

from raywave.utils.fresnel import X_SPLIT, fresnel

#: the accuracy goal (absolute; relative where |C|, |S| are small near 0)
TOL = 2e-15


def _scipy(x: np.ndarray):
    s_, c_ = scipy_fresnel(x)
    return c_, s_


def _scipy_tol(x: np.ndarray) -> np.ndarray:
    """TOL plus cephes' own error for large |x|: it rounds the phase ``πx²/2`` (~``|x|·2e-16`` in C, S: ~1e-12 at
    x = 1e4; mpmath agrees with this module there, :func:`test_against_mpmath`)."""
    return TOL + 4.5e-16 * np.abs(x)


def _sample() -> np.ndarray:
    rng = np.random.default_rng(47)
    dense = np.linspace(0.0, 10.0, 200_001)
    wide = rng.uniform(-1e4, 1e4, 50_000)
    logs = 10.0 ** rng.uniform(-8, 4, 20_000)
    near = X_SPLIT + rng.uniform(-1e-3, 1e-3, 2_000)
    return np.concatenate([dense, -dense, wide, logs, -logs, near, [X_SPLIT, -X_SPLIT, np.nextafter(X_SPLIT, 0)]])


def test_against_scipy():
    x = _sample()
    c_, s_ = (t.numpy() for t in fresnel(torch.from_numpy(x)))
    c_ref, s_ref = _scipy(x)
    tol = _scipy_tol(x)
    assert np.all(np.abs(c_ - c_ref) <= tol), float(np.max(np.abs(c_ - c_ref) - tol))
    assert np.all(np.abs(s_ - s_ref) <= tol), float(np.max(np.abs(s_ - s_ref) - tol))
    # on the knife-edge factor's range (|ν| ≤ 23) both are at the float64 floor
    m = np.abs(x) <= 23.0
    assert np.max(np.abs(c_ - c_ref)[m]) <= TOL and np.max(np.abs(s_ - s_ref)[m]) <= TOL


def test_relative_near_zero():
    x = np.concatenate([10.0 ** np.linspace(-300, 0, 601), np.linspace(1e-3, 0.5, 500)])
    c_, s_ = (t.numpy() for t in fresnel(torch.from_numpy(x)))
    c_ref, s_ref = _scipy(x)
    assert np.max(np.abs(c_ / c_ref - 1.0)) <= TOL
    ok = s_ref > 1e-290  # S ≈ πx³/6 underflows below
    assert np.max(np.abs(s_[ok] / s_ref[ok] - 1.0)) <= TOL
    assert np.all(s_[~ok] >= 0.0) and np.all(s_[~ok] <= 1e-290)


@pytest.mark.parametrize("x", [1e-6, 0.3, 1.0, 1.5999, 1.6, 1.61, 2.5, math.sqrt(2.0), 5.0, 7.071067811865476,
                               12.345, 100.5, 1234.567, 9999.999])
def test_against_mpmath(x):
    mp.mp.dps = 40
    c_ref, s_ref = float(mp.fresnelc(mp.mpf(x))), float(mp.fresnels(mp.mpf(x)))
    c_, s_ = (float(t) for t in fresnel(torch.tensor([x], dtype=torch.float64)))
    for v, ref in ((c_, c_ref), (s_, s_ref)):
        tol = TOL if abs(ref) >= 0.25 else TOL * abs(ref)  # relative where small (near 0)
        assert abs(v - ref) <= tol, (x, v, ref)


def test_odd_and_limits():
    x = torch.linspace(0.0, 50.0, 10_001, dtype=torch.float64)
    c_, s_ = fresnel(x)
    cn, sn = fresnel(-x)
    assert torch.equal(cn, -c_) and torch.equal(sn, -s_)
    special = torch.tensor([0.0, -0.0, math.inf, -math.inf, 2.0 ** 60, -1e300, math.nan], dtype=torch.float64)
    c_, s_ = fresnel(special)
    assert c_[0] == 0.0 and s_[0] == 0.0 and math.copysign(1.0, float(c_[1])) == -1.0
    assert c_[2:6].tolist() == [0.5, -0.5, 0.5, -0.5] and s_[2:6].tolist() == [0.5, -0.5, 0.5, -0.5]
    assert math.isnan(c_[6]) and math.isnan(s_[6])
    # the first maximum of C (at x = 1): 0.7798934003768228
    assert abs(float(fresnel(torch.tensor(1.0, dtype=torch.float64))[0]) - 0.7798934003768228) <= TOL


def test_dtype_shape_no_graph():
    x = torch.linspace(-3.0, 3.0, 24, dtype=torch.float32).reshape(2, 3, 4).requires_grad_()
    c_, s_ = fresnel(x)
    assert c_.dtype == s_.dtype == torch.float64 and c_.shape == s_.shape == (2, 3, 4)
    assert not c_.requires_grad
    ref_c, ref_s = fresnel(x.detach().double())
    assert torch.equal(c_, ref_c) and torch.equal(s_, ref_s)
    ci, si = fresnel(torch.arange(-3, 4))
    assert ci.dtype == torch.float64 and abs(float(ci[4]) - 0.7798934003768228) <= TOL
    e = fresnel(torch.empty(0, dtype=torch.float64))
    assert e[0].shape == (0,)
    with pytest.raises(TypeError, match="real"):
        fresnel(torch.zeros(2, dtype=torch.complex128))
    with pytest.raises(TypeError, match="torch.Tensor"):
        fresnel(np.zeros(2))


def test_derivative_is_the_integrand():
    """dC/dx = cos(πx²/2), dS/dx = sin(πx²/2) (what the knife edge's backward uses) by central differences."""
    x = torch.linspace(0.05, 8.0, 400, dtype=torch.float64)
    h = 2e-6
    cp, sp = fresnel(x + h)
    cm, sm = fresnel(x - h)
    ph = 0.5 * math.pi * x * x
    assert float(((cp - cm) / (2 * h) - torch.cos(ph)).abs().max()) < 5e-9
    assert float(((sp - sm) / (2 * h) - torch.sin(ph)).abs().max()) < 5e-9


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    x = torch.from_numpy(_sample())
    c_, s_ = fresnel(x)
    cg, sg = fresnel(x.cuda())
    assert cg.device.type == "cuda" and cg.dtype == torch.float64
    # the device's sin/cos and fused multiply-adds differ from the CPU's by an ulp or so
    assert float((cg.cpu() - c_).abs().max()) <= TOL and float((sg.cpu() - s_).abs().max()) <= TOL


def test_knife_edge_backends_agree():
    """The knife-edge factor with scipy's and with torch's Fresnel integrals (FRESNEL_CPU): the same to ~1e-15."""
    from raywave.hybrid.coherent import stop_edge as se

    nu = torch.linspace(-8.0, 6.0, 7007, dtype=torch.float64).reshape(7, 1001)
    kap = torch.full_like(nu, 0.1)
    amp, angle = torch.rand_like(nu), torch.rand_like(nu)
    outs = {}
    old = se.FRESNEL_CPU
    try:
        for k in ("scipy", "torch", "table"):
            se.FRESNEL_CPU = k
            outs[k] = (se.stop_edge_factor(nu, 1.0, 5.0, torch.full_like(nu, 2.0), 1e-3, kap),
                       se.edge_envelope(amp, angle, nu, 1.0, 5.0, 2.0, 1e-3, kap))
        se.FRESNEL_CPU = "bogus"
        with pytest.raises(ValueError, match="FRESNEL_CPU"):
            se.stop_edge_factor(nu, 1.0, 5.0, torch.full_like(nu, 2.0), 1e-3, kap)
    finally:
        se.FRESNEL_CPU = old
    for k in ("torch", "table"):
        for a, b in zip(outs["scipy"], outs[k]):
            assert float((a - b).abs().max()) <= 5e-15


def test_cpu_table_against_scipy_and_mpmath():
    """The knife-edge factor's CPU Fresnel integrals (quintic Hermite table, FRESNEL_CPU='table'): within 2e-15 of
    scipy on the default band's range (|x| ≤ 8), 5e-14 on the widest band's (|x| ≤ √2·16), and of mpmath at points
    between the table's nodes; the same bits whichever range's table a call uses; scipy's own values beyond its range
    (|x| ≥ 32) and for an empty input."""
    from raywave.hybrid.coherent import stop_edge as se

    rng = np.random.default_rng(4747)
    for lim, tol in ((8.0, 2e-15), (math.sqrt(2.0) * se.MAX_RIPPLE_ZONES, 5e-14)):
        x = np.concatenate([rng.uniform(-lim, lim, 400_000), np.linspace(-lim * 0.999, lim * 0.999, 10_001)])
        c_, s_ = se._fresnel_table_values(torch.from_numpy(x))
        cr, sr = _scipy(x)
        assert float(np.abs(c_.numpy() - cr).max()) <= tol and float(np.abs(s_.numpy() - sr).max()) <= tol
    mp.mp.dps = 30
    pts = rng.uniform(-7.1, 7.1, 40)
    c_, s_ = se._fresnel_table_values(torch.from_numpy(pts))
    for x, c, s in zip(pts, c_.tolist(), s_.tolist()):  # mpmath's fresnelc/fresnels: the same πt²/2 convention
        assert abs(c - float(mp.fresnelc(mp.mpf(x)))) <= 3e-15 and abs(s - float(mp.fresnels(mp.mpf(x)))) <= 3e-15, x
    # a value's integrals do not depend on the table the call picks (a batch of windows and each window alone)
    x = torch.from_numpy(rng.uniform(-7.9, 7.9, 10_000))
    one = se._fresnel_table_values(x)
    wide = se._fresnel_table_values(torch.cat([x, torch.tensor([20.0, -31.0], dtype=torch.float64)]))
    assert all(torch.equal(a, b[:x.numel()]) for a, b in zip(one, wide))
    big = torch.tensor([-40.0, 0.5, 33.0], dtype=torch.float64)
    c_, s_ = se._fresnel_table_values(big)
    cr, sr = _scipy(big.numpy())
    assert np.array_equal(c_.numpy(), cr) and np.array_equal(s_.numpy(), sr)
    empty = torch.empty(0, dtype=torch.float64)
    assert all(t.numel() == 0 for t in se._fresnel_table_values(empty))


@pytest.mark.slow
def test_fit_script_reproduces_the_coefficients():
    """tools/fit_fresnel.py (mpmath) prints exactly the module's coefficients (~10 s)."""
    import pathlib
    import subprocess
    import sys

    import raywave.utils.fresnel as mod

    root = pathlib.Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(root / "tools" / "fit_fresnel.py")], capture_output=True, text=True,
                         check=True).stdout
    seen = 0
    for line in out.splitlines():
        if "=" in line and not line.startswith("#"):
            name, value = (t.strip() for t in line.split("=", 1))
            assert getattr(mod, name) == eval(value), name  # noqa: S307 (our own script's literals)
            seen += 1
    assert seen == 7
