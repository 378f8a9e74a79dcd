"""Free-space propagation core (raywave.wave.propagation), each result against an independent reference."""

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from window_calls import transfer as _wt, window as _pw  # noqa: E402

from raywave.wave import (
    angular_spectrum,
    fast_fft_size,
    grid_coordinates,
    nyquist_check,
    pixel_integrate,
)

F64 = torch.float64
C128 = torch.complex128


def k_mm(lam_um, n=1.0):
    return 2 * math.pi * n / (lam_um * 1e-3)


def gaussian(x, y, z, lam_um, w0, n=1.0):
    """Paraxial Gaussian beam (exp(-iωt) convention, waist at z = 0), complex amplitude at (x[ix], y[iy])."""
    k = k_mm(lam_um, n)
    zr = k * w0**2 / 2
    q = complex(z, -zr)
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    return (complex(0, -zr) / q) * complex(math.cos(k * z), math.sin(k * z)) * torch.exp(1j * k * r2 / (2 * q))


def centred(n, p):
    return grid_coordinates(n, p, -(n - 1) / 2 * p)


def rel_err(a, b):
    return float((a - b).abs().max() / b.abs().max())


# ----------------------------------------------------------------------------------------------------------
# Gaussian beam vs the analytic paraxial solution (w0 = 50 µm ≫ λ: non-paraxial terms ~1e-6)
# ----------------------------------------------------------------------------------------------------------
LAM, P, W0 = 0.5, 2e-3, 0.05


@pytest.mark.parametrize("z", [1.0, 5.0])
def test_gaussian_beam_angular_spectrum(z, device):
    c = centred(384, P).to(device)
    u0 = gaussian(c, c, 0.0, LAM, W0)
    out = angular_spectrum(u0, P, LAM, z)
    ref = gaussian(c, c, z, LAM, W0)
    amp_err = float((out.abs() - ref.abs()).abs().max() / ref.abs().max())
    lit = ref.abs() > 1e-2 * ref.abs().max()
    ph_err = float(torch.angle(out * ref.conj())[lit].abs().max())
    assert amp_err < 3e-6 and ph_err < 3e-6, (amp_err, ph_err)
    assert out.dtype == C128 and out.shape == u0.shape and out.device.type == device


@pytest.mark.parametrize("q", [2, 4])
def test_upsampled_intensity_of_a_band_limited_field_is_exact(q, device):
    """A periodic field made of a few plane waves below Nyquist, sampled on (ny, nx): its q-times upsampled
    intensity equals |u|² of the analytic field on the q-times finer grid (sample [q·i, q·j] on input [i, j])."""
    from raywave.wave.field import upsampled_intensity

    ny, nx = 12, 16
    waves = [(1.0 + 0.5j, 0, 0), (0.7 - 0.2j, 3, -5), (0.3j, -5, 7), (0.4, 2, 1)]  # (amplitude, ky, kx) cycles

    def field(ty, tx):
        return sum(a * torch.exp(2j * math.pi * (ky * ty[:, None] + kx * tx[None, :])) for a, ky, kx in waves)

    def axis(n, m):
        return torch.arange(m, dtype=F64, device=device) / m

    u = field(axis(ny, ny), axis(nx, nx))
    want = field(axis(ny, q * ny), axis(nx, q * nx)).abs().square()
    got = upsampled_intensity(u, q)
    assert got.shape == (q * ny, q * nx) and got.device.type == device
    assert torch.allclose(got, want, atol=1e-12, rtol=0)


@pytest.mark.parametrize("q, shape", [(2, (21, 21)), (3, (24, 19)), (4, (213, 213)), (4, (30, 44))])
def test_integrated_upsampled_intensity_is_the_q_grid_integral(q, shape, device):
    """The PSF's pixel integral computed on the 2× grid (the folded weights) equals the cubic integral of the
    q×-upsampled intensity to round-off, values and the derivative with respect to where the pixels sit
    (the intensity of N samples a period holds |m| ≤ N − 1, which 2N samples carry exactly)."""
    from raywave.wave.field import upsampled_intensity
    from raywave.wave.propagation import integrated_upsampled_intensity, pixel_integrate

    g = torch.Generator().manual_seed(sum(shape) + q)
    ny, nx = shape
    y = torch.arange(ny, dtype=F64) - ny / 2
    x = torch.arange(nx, dtype=F64) - nx / 2
    u = torch.exp(-(y[:, None] ** 2 + x[None, :] ** 2) / (0.04 * ny * nx) + 1j * (0.4 * x[None, :] - 0.2 * y[:, None]))
    u = (u + 0.05 * torch.randn(ny, nx, dtype=C128, generator=g)).to(device)
    window = torch.rand(ny, nx, dtype=F64, generator=g).to(device)
    p, ps, org = 1e-3, 2.7e-3, (0.1, -0.2)
    k = (int(nx * p / ps) - 2, int(ny * p / ps) - 2)
    want_o = torch.tensor([org[0] + 0.0113, org[1] + 0.0127], dtype=F64, device=device, requires_grad=True)
    got_o = want_o.detach().clone().requires_grad_(True)
    want = pixel_integrate(upsampled_intensity(u, q, window).to(F64), p / q, ps, org, want_o, (k[1], k[0]),
                           kernel="cubic")
    got = integrated_upsampled_intensity(u, q, p, org, ps, got_o, (k[1], k[0]), window)
    assert got.dtype == F64 and got.shape == want.shape and got.device.type == device
    assert float((got - want).detach().abs().max()) < 1e-13 * float(want.detach().abs().max())
    w = torch.rand(want.shape, dtype=F64, generator=g).to(device)
    (gw,) = torch.autograd.grad((want * w).sum(), want_o)
    (gg,) = torch.autograd.grad((got * w).sum(), got_o)
    assert torch.allclose(gg, gw, rtol=1e-11, atol=1e-13 * float(gw.abs().max()))


def test_gaussian_beam_window_subpixel_offset():
    c = centred(384, P)
    u0 = gaussian(c, c, 0.0, LAM, W0)
    z, out_origin = 5.0, (-0.0373, 0.0211)  # not a multiple of the pitch
    out = _pw(u0, P, LAM, z, (float(c[0]), float(c[0])), out_origin, (96, 128))
    xo = grid_coordinates(128, P, out_origin[0])
    yo = grid_coordinates(96, P, out_origin[1])
    ref = gaussian(xo, yo, z, LAM, W0)
    amp_err = float((out.abs() - ref.abs()).abs().max() / ref.abs().max())
    lit = ref.abs() > 1e-2 * ref.abs().max()
    assert lit.sum() > 2000
    ph_err = float(torch.angle(out * ref.conj())[lit].abs().max())
    assert amp_err < 3e-6 and ph_err < 3e-6, (amp_err, ph_err)
    assert out.shape == (96, 128)


# ----------------------------------------------------------------------------------------------------------
# Energy (Parseval)
# ----------------------------------------------------------------------------------------------------------
def test_parseval_unitary_random_field():
    g = torch.Generator().manual_seed(0)
    u = torch.randn(64, 48, dtype=C128, generator=g)
    out = angular_spectrum(u, 1e-3, 0.5, 3.0, pad=1, band_limit=False)  # |H| = 1 everywhere (no evanescent)
    assert abs(float(out.abs().square().sum() / u.abs().square().sum()) - 1) < 1e-12


def test_parseval_gaussian_both_paths():
    c = centred(384, P)
    u0 = gaussian(c, c, 0.0, LAM, W0)
    e0 = u0.abs().square().sum()
    a = angular_spectrum(u0, P, LAM, 5.0)
    o = (float(c[0]), float(c[0]))
    w = _pw(u0, P, LAM, 5.0, o, o, (384, 384))
    for out in (a, w):
        assert abs(float(out.abs().square().sum() / e0) - 1) < 1e-12


def test_window_zero_distance_is_a_shift():
    g = torch.Generator().manual_seed(1)
    u = torch.randn(20, 30, dtype=C128, generator=g)
    p = 1e-3
    same = _pw(u, p, 0.5, 0.0, (0.0, 0.0), (0.0, 0.0), (20, 30))
    assert rel_err(same, u) < 1e-13
    shifted = _pw(u, p, 0.5, 0.0, (0.0, 0.0), (5 * p, 3 * p), (10, 12))
    assert rel_err(shifted, u[3:13, 5:17]) < 1e-13


# ----------------------------------------------------------------------------------------------------------
# Windowed path vs the full-grid reference
# ----------------------------------------------------------------------------------------------------------
def _embed(full_shape, sub, iy, ix):
    big = torch.zeros(full_shape, dtype=sub.dtype)
    big[iy : iy + sub.shape[0], ix : ix + sub.shape[1]] = sub
    return big


def test_window_matches_full_grid_on_axis():
    p, lam, w0, z = 1e-3, 0.55, 0.02, 2.0
    n_full = 512
    c = centred(n_full, p)  # pixel centres at (i - 255.5)·p
    i0 = 256 - 150
    sub = gaussian(c[i0 : i0 + 300], c[i0 : i0 + 300], 0.0, lam, w0)
    full = angular_spectrum(_embed((n_full, n_full), sub, i0, i0), p, lam, z)
    jy, jx = 230, 270
    win = _pw(sub, p, lam, z, (float(c[i0]), float(c[i0])), (float(c[jx]), float(c[jy])), (64, 48))
    assert rel_err(win, full[jy : jy + 64, jx : jx + 48]) < 1e-10


@pytest.mark.parametrize("n", [1.0, 1.5])
def test_window_matches_full_grid_tilted_with_carrier(n):
    p, lam, w0, z, theta = 0.5e-3, 0.55, 0.015, 1.0, math.radians(15.0)
    alpha = math.sin(theta)  # direction cosine in the medium
    fc = n * alpha / (lam * 1e-3)
    nx, ny = 1024, 512
    x = grid_coordinates(nx, p, -240 * p)
    y = centred(ny, p)
    ix0, iy0, m = 240 - 200, 256 - 200, 400  # 400×400 input window centred on the waist at (0, 0)
    env = gaussian(x[ix0 : ix0 + m], y[iy0 : iy0 + m], 0.0, lam, w0, n)
    field = env * torch.exp(1j * 2 * math.pi * fc * x[ix0 : ix0 + m])[None, :]
    full = angular_spectrum(_embed((ny, nx), field, iy0, ix0), p, lam, z, n=n)
    tan_t = alpha / math.sqrt(1 - alpha**2)
    jx = 240 + round(z * tan_t / p) - 64  # 128-pixel window centred on z·tanθ
    jy = 256 - 64
    win = _pw(
        env, p, lam, z, (float(x[ix0]), float(y[iy0])), (float(x[jx]), float(y[jy])), (128, 128), n=n,
        carrier=(alpha, 0.0),
    )
    true = win * torch.exp(1j * 2 * math.pi * fc * x[jx : jx + 128])[None, :]
    ref = full[jy : jy + 128, jx : jx + 128]
    assert float(ref.abs().max()) > 0.5 * float(full.abs().max())  # the window does hold the beam
    assert rel_err(true, ref) < 1e-10


def test_tilted_beam_lands_at_z_tan_theta():
    p, lam, w0, z, theta = 2e-3, 0.5, 0.05, 5.0, math.radians(15.0)
    alpha = math.sin(theta)  # carrier 518 cycles/mm: far above this grid's Nyquist (250), the envelope is not
    m = 320
    c = centred(m, p)
    env = gaussian(c, c, 0.0, lam, w0)
    xc = z * math.tan(theta)
    out_origin = (xc + float(c[0]) + 0.3 * p, float(c[0]))  # deliberately not pixel-aligned
    out = _pw(env, p, lam, z, (float(c[0]), float(c[0])), out_origin, (m, m), carrier=(alpha, 0.0))
    inten = out.abs().square()
    xo = grid_coordinates(m, p, out_origin[0])
    yo = grid_coordinates(m, p, out_origin[1])
    cx = float((inten.sum(0) * xo).sum() / inten.sum())
    cy = float((inten.sum(1) * yo).sum() / inten.sum())
    assert abs(cx - xc) < 0.1 * p and abs(cy) < 0.1 * p, (cx - xc, cy)
    # the same power arrives (nothing lost by the band limit or the window)
    assert abs(float(inten.sum() / env.abs().square().sum()) - 1) < 1e-9


# ----------------------------------------------------------------------------------------------------------
# Focusing by an ideal lens: Airy ring and on-axis intensity
# ----------------------------------------------------------------------------------------------------------
def _lens_field(n_pix, p, lam, f, a, sub=8):
    """Uniform disk of radius a (area-weighted edge pixels) times exp(-ik(sqrt(r²+f²) - f))."""
    c = grid_coordinates(n_pix, p, -(n_pix // 2) * p)  # pixel n_pix//2 sits on the axis
    s = (torch.arange(sub, dtype=F64) + 0.5) / sub - 0.5
    xs = (c[:, None] + s[None, :] * p).reshape(-1)
    inside = (xs[None, :] ** 2 + xs[:, None] ** 2 <= a * a).to(F64)
    cover = inside.reshape(n_pix, sub, n_pix, sub).mean(dim=(1, 3))
    r2 = c[None, :] ** 2 + c[:, None] ** 2
    k = k_mm(lam)
    return cover * torch.exp(-1j * k * (torch.sqrt(r2 + f * f) - f)), c


@pytest.mark.parametrize("path", ["full", "window"])
def test_focus_airy_ring_and_peak(path):
    lam, f, a, p = 0.5, 2.0, 0.1, 0.5e-3
    n_pix = 449
    u0, c = _lens_field(n_pix, p, lam, f, a)
    h = 32
    if path == "full":
        out = angular_spectrum(u0, p, lam, f)[n_pix // 2 - h : n_pix // 2 + h + 1, n_pix // 2 - h : n_pix // 2 + h + 1]
    else:
        o = float(c[0])
        out = _pw(u0, p, lam, f, (o, o), (-h * p, -h * p), (2 * h + 1, 2 * h + 1))
    inten = out.abs().square()
    # on-axis: Rayleigh–Sommerfeld of the converging spherical wave, |U(0)| = (π f/λ)·ln(1 + a²/f²)
    # (Fresnel: π a²/(λ f), larger by a²/(2f²) ≈ 1.2e-3 here)
    lam_mm = lam * 1e-3
    i0 = (math.pi * f / lam_mm * math.log1p(a * a / (f * f))) ** 2
    assert abs(float(inten[h, h]) / i0 - 1) < 1e-3
    assert int(torch.argmax(inten)) == h * (2 * h + 1) + h
    # first dark ring of the Airy pattern at 1.22 λ f / D (search along +x, -x, +y, -y)
    r_dark = 1.22 * lam_mm * f / (2 * a)
    for prof in (inten[h, h:], inten[h, : h + 1].flip(0), inten[h:, h], inten[: h + 1, h].flip(0)):
        j = next(i for i in range(1, h) if prof[i] < prof[i - 1] and prof[i] <= prof[i + 1])
        assert abs(j * p - r_dark) < p, (j * p, r_dark)
        assert float(prof[j]) < 1e-3 * float(prof[0])


def test_focus_window_guard_vs_wide_reference():
    """The smooth roll-off (guard) of the window band limit removes the sharp-cut truncation error."""
    lam, f, a, p = 0.5, 2.0, 0.1, 0.5e-3
    n_pix, h = 449, 32  # the aperture edge is only 12 µm (0.4 Fresnel zone) inside the input window
    u0, c = _lens_field(n_pix, p, lam, f, a)
    sl = slice(n_pix // 2 - h, n_pix // 2 + h + 1)
    ref = angular_spectrum(u0, p, lam, f, pad=4)[sl, sl]  # kernel range ±448 µm vs ±116 µm needed
    o = float(c[0])
    errs = {}
    for guard in (0.0, 2.0):
        w = _pw(u0, p, lam, f, (o, o), (-h * p, -h * p), (2 * h + 1, 2 * h + 1), guard=guard)
        errs[guard] = rel_err(w, ref)
    assert errs[2.0] < 2e-4, errs
    assert errs[0.0] > 10 * errs[2.0], errs  # the sharp band limit (paper) is much worse here


# ----------------------------------------------------------------------------------------------------------
# Robustness: evanescent waves, huge angles, batches, dtypes, autograd
# ----------------------------------------------------------------------------------------------------------
def _finite_grad(fn, u):
    u = u.clone().requires_grad_(True)
    out = fn(u)
    assert torch.isfinite(torch.view_as_real(out)).all()
    out.abs().square().sum().backward()
    assert torch.isfinite(torch.view_as_real(u.grad)).all()
    return out


@pytest.mark.parametrize("z", [0.0, 0.003, -0.05, 0.2])
def test_no_nan_evanescent_and_huge_angles(z):
    g = torch.Generator().manual_seed(2)
    u = torch.randn(2, 32, 40, dtype=C128, generator=g)
    p, lam = 0.15e-3, 0.5  # Nyquist 3333 cycles/mm > n/λ = 2000: the corners of the spectrum are evanescent
    _finite_grad(lambda v: angular_spectrum(v, p, lam, z), u)
    _finite_grad(lambda v: angular_spectrum(v, p, lam, z, band_limit=False), u)
    for carrier in [(0.0, 0.0), (0.9, 0.3)]:
        _finite_grad(lambda v: _pw(v, p, lam, z, (0.0, 0.0), (z * 0.9, -0.001), (24, 16), carrier=carrier), u)
    # |carrier| >= 1 is no direction: the Field refuses it (issue 43); the transfer function itself stays finite, and
    # with α = -3 every envelope frequency (|f| < 3333) maps to |f + f_c| > n/λ: all evanescent, exactly 0
    from raywave.wave.propagation.transfer import WindowSource, _window_transfer

    for carrier in [(0.99, 0.5), (-3.0, 0.0)]:
        with pytest.raises(ValueError, match="carrier"):
            _pw(u, p, lam, z, (0.0, 0.0), (z * 0.9, -0.001), (24, 16), carrier=carrier)
        src = WindowSource((32, 40), (0.0, 0.0), (z * 0.9, -0.001), lam, z, 1.0, carrier)
        band = _window_transfer(src, (24, 16), p, (0.5, 2.0), None, True).band
        assert bool(torch.isfinite(torch.view_as_real(band)).all())
        if carrier[0] == -3.0:
            assert float(band.abs().max()) == 0.0 if band.numel() else True


def test_z_tensor_gradient_finite():
    g = torch.Generator().manual_seed(3)
    u = torch.randn(16, 16, dtype=C128, generator=g)
    z = torch.tensor(0.2, dtype=F64, requires_grad=True)
    out = _pw(u, 0.2e-3, 0.5, z, (0.0, 0.0), (0.0, 0.0), (8, 8), carrier=(0.3, 0.0))
    out.abs().square().sum().backward()
    assert torch.isfinite(z.grad)
    # d/dz with the band-limit weights held fixed (they use the detached z); guard=0 keeps them constant
    # under gradcheck's finite differences too
    zz = torch.tensor(0.05, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda t: _pw(u[:5, :6], 1e-3, 0.6, t, (0.0, 0.0), (1e-3, 0.0), (4, 3), carrier=(0.1, 0.0),
                                   guard=0.0),
        (zz,),
    )
    assert torch.autograd.gradcheck(lambda t: angular_spectrum(u[:5, :6], 1e-3, 0.6, t), (zz,))


def test_window_forward_then_backward_recovers_input():
    p, lam, w0, z, alpha = 2e-3, 0.5, 0.05, 4.0, math.sin(math.radians(25.0))
    m = 320
    c = centred(m, p)
    env = gaussian(c, c, 0.0, lam, w0)
    o_in = (float(c[0]), float(c[0]))
    o_out = (o_in[0] + z * alpha / math.sqrt(1 - alpha**2) + 0.37 * p, o_in[1] - 0.21 * p)
    fwd = _pw(env, p, lam, z, o_in, o_out, (m, m), n=1.33, carrier=(alpha, 0.0))
    back = _pw(fwd, p, lam, -z, o_out, o_in, (m, m), n=1.33, carrier=(alpha, 0.0))
    assert rel_err(back, env) < 1e-10


def test_gradcheck_tiny():
    g = torch.Generator().manual_seed(4)
    u = torch.randn(5, 6, dtype=C128, generator=g, requires_grad=True)
    p, lam = 1e-3, 0.6
    assert torch.autograd.gradcheck(lambda v: angular_spectrum(v, p, lam, 0.01), (u,))
    assert torch.autograd.gradcheck(
        lambda v: _pw(v, p, lam, 0.01, (0.0, 0.0), (1.5e-3, -0.7e-3), (4, 3), carrier=(0.1, -0.05)),
        (u,),
    )
    assert torch.autograd.gradcheck(
        lambda v: pixel_integrate(v.abs().square(), p, 2.3e-3, (0.0, 0.0), (1e-3, 0.5e-3), (3, 3)), (u,)
    )


def test_batch_and_complex64():
    g = torch.Generator().manual_seed(5)
    u = torch.randn(2, 3, 24, 20, dtype=C128, generator=g)
    args = (1e-3, 0.5, 0.4, (0.0, 0.0), (2e-3, 1e-3), (10, 12))
    kw = dict(carrier=(0.2, 0.1))
    out = _pw(u, *args, **kw)
    one = _pw(u[1, 2], *args, **kw)
    assert out.shape == (2, 3, 10, 12) and rel_err(out[1, 2], one) < 1e-14
    out32 = _pw(u.to(torch.complex64), *args, **kw)
    assert out32.dtype == torch.complex64 and rel_err(out32.to(C128), out) < 1e-5
    a = angular_spectrum(u, 1e-3, 0.5, 0.4)
    a32 = angular_spectrum(u.to(torch.complex64), 1e-3, 0.5, 0.4)
    assert a32.dtype == torch.complex64 and rel_err(a32.to(C128), a) < 1e-5
    assert rel_err(a[0, 1], angular_spectrum(u[0, 1], 1e-3, 0.5, 0.4)) < 1e-14


def test_fast_fft_size():
    for n in [1, 7, 97, 1000, 3128, 6001]:
        m = fast_fft_size(n)
        assert m >= n
        r = m
        for q in (2, 3, 5):
            while r % q == 0:
                r //= q
        assert r == 1
        assert all(fast_fft_size(j) == fast_fft_size(n) for j in range(n, m + 1))
    assert fast_fft_size(3128) == 3200 and fast_fft_size(727) == 729


# ----------------------------------------------------------------------------------------------------------
# Nyquist check
# ----------------------------------------------------------------------------------------------------------
def test_nyquist_check_lens_phase():
    lam, f, p, n_pix = 0.5, 1.0, 1e-3, 201
    c = centred(n_pix, p)
    r2 = c[None, :] ** 2 + c[:, None] ** 2
    phase = -k_mm(lam) * (torch.sqrt(r2 + f * f) - f)
    rep = nyquist_check(phase, p, lam, origin=(float(c[0]), float(c[0])))
    # analytic local frequency along x: x/(λ sqrt(r²+f²)), largest at the edge midpoints (|x| = xm, y = 0);
    # ratio = 2p·f_x, the finite difference sees it half a pixel inside
    xm = float(c[-1])
    xe = xm - p / 2
    expect = 2 * p * xe / (lam * 1e-3 * math.sqrt(xe * xe + f * f))
    assert abs(rep.max_ratio / expect - 1) < 1e-3 and rep.ok
    pos = sorted(abs(v) for v in rep.position)
    assert pos[0] < 1e-12 and abs(pos[1] - xm) < 1e-12
    # the complex field gives the same map while below Nyquist
    rep_c = nyquist_check(torch.exp(1j * phase), p, lam)
    assert abs(rep_c.max_ratio - rep.max_ratio) < 1e-9
    # a grid 4x coarser is flagged
    rep4 = nyquist_check(phase[::4, ::4], 4 * p, lam)
    assert not rep4.ok and rep4.max_ratio > 1 and "too coarse" in str(rep4)


def test_nyquist_check_carrier_removed():
    lam, p, alpha = 0.5, 2e-3, math.sin(math.radians(15.0))
    x = grid_coordinates(64, p, 0.0)
    phase = (k_mm(lam) * alpha * x)[None, :].expand(32, 64)
    assert nyquist_check(phase, p, lam).max_ratio > 2  # the full tilted field is aliased on this grid
    assert nyquist_check(phase, p, lam, carrier=(alpha, 0.0)).max_ratio < 1e-9  # the envelope is fine
    m = torch.zeros(32, 64, dtype=torch.bool)
    assert nyquist_check(phase, p, lam, mask=m).max_ratio == 0.0


# ----------------------------------------------------------------------------------------------------------
# Pixel integration
# ----------------------------------------------------------------------------------------------------------
def test_pixel_integrate_block_sums():
    g = torch.Generator().manual_seed(6)
    inten = torch.rand(3, 40, 48, dtype=F64, generator=g)
    p, q = 1e-3, 4e-3  # out pixel (0, 0) covers input pixels 0..3 (centres 0..3 µm → centre 1.5 µm)
    blocks = inten.reshape(3, 10, 4, 12, 4).sum(dim=(2, 4))
    kw = dict(in_origin=(0.0, 0.0), out_origin=(1.5e-3, 1.5e-3), out_shape=(10, 12))
    assert torch.allclose(pixel_integrate(inten, p, q, mode="sum", **kw), blocks, rtol=1e-14, atol=0)
    assert torch.allclose(pixel_integrate(inten, p, q, **kw), blocks * p * p, rtol=1e-14, atol=0)
    assert torch.allclose(pixel_integrate(inten, p, q, mode="mean", **kw), blocks / 16, rtol=1e-14, atol=0)


def test_pixel_integrate_energy_non_integer_ratio():
    g = torch.Generator().manual_seed(7)
    inten = torch.rand(70, 90, dtype=F64, generator=g)
    p, q = 1e-3, 3.45e-3
    # output covers the whole input: total energy conserved
    out = pixel_integrate(inten, p, q, (0.2e-3, -0.1e-3), (-2e-3, -3e-3), (24, 30))
    assert abs(float(out.sum() / (inten.sum() * p * p)) - 1) < 1e-13
    # partial cover: energy of the common area (computed independently by 100x supersampling in 1-D/axis)
    out_origin, shape = (30.3e-3, 20.1e-3), (5, 7)
    part = pixel_integrate(inten, p, q, (0.0, 0.0), out_origin, shape)
    s = 100
    fine = inten.repeat_interleave(s, 0).repeat_interleave(s, 1)  # sub-samples at (i - 0.5 + (j+0.5)/s)·p
    xf = (torch.arange(90 * s, dtype=F64) + 0.5) / s * p - 0.5 * p
    yf = (torch.arange(70 * s, dtype=F64) + 0.5) / s * p - 0.5 * p
    inx = (xf >= out_origin[0] - q / 2) & (xf < out_origin[0] + (shape[1] - 0.5) * q)
    iny = (yf >= out_origin[1] - q / 2) & (yf < out_origin[1] + (shape[0] - 0.5) * q)
    common = float(fine[iny][:, inx].sum()) * (p / s) ** 2
    assert abs(float(part.sum()) / common - 1) < 2e-3  # the supersampled reference is itself ~1/s accurate
    assert (part >= 0).all()


def test_band_convolution_backward_is_the_adjoint():
    """The band convolution's hand-written backward (``_BandConvolve``, which keeps the inputs instead of four
    band-sized intermediates): gradcheck in the field and the transfer function, with and without leading batch
    dimensions, equal to autograd through the plain operations to rounding, and the forward values unchanged."""
    from raywave.wave.propagation.band import BandConvolve as _BandConvolve
    from raywave.wave.propagation.band import convolve_band as _convolve_band

    g = torch.Generator().manual_seed(6)
    rows, cols = torch.tensor([0, 1, 2, 5, 9, 14, 15]), torch.tensor([0, 3, 4, 7, 16, 17])
    size, noy, nox = (16, 18), 6, 5
    for lead in ((), (2,)):
        u = torch.randn(*lead, 7, 9, dtype=C128, generator=g, requires_grad=True)
        h = torch.randn(len(rows), len(cols), dtype=C128, generator=g, requires_grad=True)

        def band(v, t):
            return _BandConvolve.apply(v, t, size, rows, cols, noy, nox)

        assert torch.autograd.gradcheck(band, (u, h))
        w = torch.randn(*lead, noy, nox, dtype=C128, generator=g)
        mine = torch.autograd.grad((band(u, h) * w.conj()).real.sum(), (u, h))
        ref = torch.autograd.grad((_convolve_band(u, h, size, rows, cols, noy, nox) * w.conj()).real.sum(), (u, h))
        assert all(float((a - b).abs().max()) < 1e-14 for a, b in zip(mine, ref))
        assert torch.equal(band(u, h).detach(), _convolve_band(u.detach(), h.detach(), size, rows, cols, noy, nox))


def _band_case():
    """A field, a window transfer with its weight derivatives and an output gradient (off-axis carrier)."""
    from raywave.wave.propagation import window_transfer

    g = torch.Generator().manual_seed(5)
    u = torch.randn(2, 300, 260, dtype=torch.complex128, generator=g)
    tr = _wt((300, 260), (97, 97), 1e-3, 0.53, 2.0, (0.0, 0.0), (0.04, 0.07), carrier=(0.1, 0.05),
                         weight_derivative=True)
    gout = torch.randn(2, 97, 97, dtype=torch.complex128, generator=g)
    return u, tr, gout


def test_band_convolution_in_column_chunks_equals_the_whole_band(monkeypatch):
    """A band taller than BAND_CHUNK_BYTES goes through in column blocks, forward and backward: the same 1-D
    transforms, so the same values and gradients to rounding."""
    import raywave.wave.propagation.band as W

    u0, tr, gout = _band_case()
    results = []
    for limit in (2**60, 2**16):  # whole band, then many chunks
        monkeypatch.setattr(W, "BAND_CHUNK_BYTES", limit)
        u = u0.clone().requires_grad_()
        h = tr.band.clone().requires_grad_()
        out = W.BandConvolve.apply(u, h, tr.size, tr.rows, tr.cols, 97, 97)
        gu, gh = torch.autograd.grad(out, (u, h), gout)
        with torch.no_grad():
            plain = W.convolve_band(u0, tr.band, tr.size, tr.rows, tr.cols, 97, 97)
        results.append((out.detach(), plain, gu, gh))
    assert W.band_chunks(u0, tr.size[0], tr.cols.numel()) > 4
    for whole, chunked in zip(*results):
        assert float((whole - chunked).abs().max()) <= 1e-14 * float(whole.abs().max())


def test_roll_off_on_the_lines_that_can_roll_off_equals_every_line(monkeypatch):
    """The window transfer evaluates the band-limit roll-off only on the lines whose lateral shift can leave the
    band (the others' factor is exactly 1): bit for bit what evaluating every line gives, with the weight
    derivatives."""
    import raywave.wave.propagation.transfer as T

    args = ((300, 260), (97, 97), 1e-3, 0.53, 2.0, (0.0, 0.0), (0.04, 0.07))
    real, counts = T._ramp_lines, []

    def spy(g, *a):
        lines = real(g, *a)
        counts.append((lines.numel(), g.numel()))
        return lines

    monkeypatch.setattr(T, "_ramp_lines", spy)
    fast = _wt(*args, carrier=(0.1, 0.05), weight_derivative=True)
    assert all(n < total for n, total in counts)  # some lines were skipped on both axes
    monkeypatch.setattr(T, "_ramp_lines", lambda g, *a: torch.arange(g.numel()))
    full = _wt(*args, carrier=(0.1, 0.05), weight_derivative=True)
    assert torch.equal(fast.band, full.band)
    assert torch.equal(fast.band_rel.abs(), full.band_rel.abs())  # the skipped lines' zeros may differ in sign


@pytest.mark.parametrize("shape", [(213, 213), (12, 17), (20, 9)])
def test_double_grid_intensity_is_the_2x_upsampled_intensity(shape, device):
    """The 2× upsampled intensity as four interleaved sample sets (the field and its half-sample shifts) equals
    the zero-padded-spectrum upsampling, odd and even sizes, batched, and with the same gradient."""
    from raywave.wave.field import double_grid_intensity, upsampled_intensity

    g = torch.Generator().manual_seed(sum(shape))
    ny, nx = shape
    u = torch.randn(3, ny, nx, dtype=C128, generator=g).to(device).requires_grad_(True)
    window = torch.rand(ny, nx, dtype=F64, generator=g).to(device)
    want = upsampled_intensity(u, 2, window)
    blocks = double_grid_intensity(u, window)
    assert blocks.shape == (3, 2, 2, ny, nx)
    got = blocks.permute(0, 3, 1, 4, 2).reshape(3, 2 * ny, 2 * nx)  # [i, a, j, b] -> [2i + a, 2j + b]
    assert float((got - want).detach().abs().max()) < 1e-13 * float(want.detach().abs().max())
    w = torch.rand(want.shape, dtype=F64, generator=g).to(device)
    (gw,) = torch.autograd.grad((want * w).sum(), u)
    (gg,) = torch.autograd.grad((got * w).sum(), u)
    assert torch.allclose(gg, gw, rtol=1e-11, atol=1e-12 * float(gw.abs().max()))
    with torch.no_grad():
        assert torch.allclose(double_grid_intensity(u, window), blocks.detach(), rtol=0, atol=0)


def test_half_sample_shift_of_a_large_prime_length_is_the_plain_fft_shift(monkeypatch):
    """field._half_sample_shift of a length with a large prime factor (213 = 3·71, the PSF windows') runs as a
    circular convolution through zero-padded FFTs of a 5-smooth length (issue 43, CPU): the plain FFT shift's values
    and gradients to rounding, along rows and columns, batched, with and without autograd; small helpers exact."""
    import raywave.wave.field as F

    assert [F._largest_prime_factor(n) for n in (1, 2, 12, 213, 225, 97, 1440)] == [1, 2, 3, 71, 5, 97, 5]
    for m in (1, 7, 425, 433, 1441):
        s = F.fast_fft_size(m)
        assert s >= m and F._largest_prime_factor(s) <= 5
        assert all(F._largest_prime_factor(k) > 5 for k in range(m, s))
    assert F.fast_fft_size(425) == 432
    g = torch.Generator().manual_seed(43)
    u = torch.complex(torch.randn(3, 2, 213, 213, generator=g, dtype=F64), torch.randn(3, 2, 213, 213, generator=g,
                                                                                       dtype=F64))
    w = torch.complex(torch.randn(u.shape, generator=g, dtype=F64), torch.randn(u.shape, generator=g, dtype=F64))
    for dim in (-1, -2):
        x = u.clone().requires_grad_()
        got = F._half_sample_shift(x, dim)
        (g_got,) = torch.autograd.grad((got * w).real.sum(), x)
        with torch.no_grad():
            got_ng = F._half_sample_shift(u, dim)
        monkeypatch.setattr(F, "SHIFT_SMOOTH_PRIME", 10 ** 9)  # the plain FFT shift
        want = F._half_sample_shift(x, dim)
        (g_want,) = torch.autograd.grad((want * w).real.sum(), x)
        monkeypatch.undo()
        scale = float(want.detach().abs().max())
        assert float((got - want).detach().abs().max()) < 1e-14 * scale
        assert torch.equal(got_ng, got.detach())
        assert float((g_got - g_want).abs().max()) < 1e-14 * float(g_want.abs().max())


def test_band_convolution_kept_spectrum_equals_the_recomputed_one(monkeypatch):
    """One field's band convolution keeps the input's band spectrum from the forward for the transfer function's
    gradient (KEEP_SPECTRUM_BYTES) instead of recomputing it in the backward, and transforms the field's gradient
    along x in blocks of rows (_x_inverse): the same values and gradients as recomputing, for
    rows in one run (the kept spectrum a copy, not a view the in-place product overwrites) and in several, one
    column block and many."""
    import raywave.wave.propagation.band as W

    g = torch.Generator().manual_seed(9)
    size, noy, nox = (16, 18), 6, 5
    u0 = torch.randn(7, 9, dtype=C128, generator=g)
    w = torch.randn(noy, nox, dtype=C128, generator=g)
    cols = torch.tensor([0, 3, 4, 7, 16, 17])
    for rows in (torch.tensor([0, 1, 2, 5, 9, 14, 15]), torch.arange(3, 11)):
        h0 = torch.randn(len(rows), len(cols), dtype=C128, generator=g)
        for limit in (2**60, 64):
            monkeypatch.setattr(W, "BAND_CHUNK_BYTES", limit)
            results = []
            for keep in (0, 2**60):
                monkeypatch.setattr(W, "KEEP_SPECTRUM_BYTES", keep)
                u, h = u0.clone().requires_grad_(), h0.clone().requires_grad_()
                out = W.BandConvolve.apply(u, h, size, rows, cols, noy, nox)
                results.append((out.detach(), *torch.autograd.grad((out * w.conj()).real.sum(), (u, h))))
            with torch.enable_grad():
                u, h = u0.clone().requires_grad_(), h0.clone().requires_grad_()
                plain = W.convolve_band(u, h, size, rows, cols, noy, nox)
                results.append((plain.detach(), *torch.autograd.grad((plain * w.conj()).real.sum(), (u, h))))
            for other in results[1:]:
                for a, b in zip(other, results[0]):
                    assert float((a - b).abs().max()) <= 1e-14 * float(b.abs().max())


def test_x_inverse_is_the_whole_arrays_inverse_bit_for_bit():
    """_x_inverse (the band's columns placed in a full-width buffer and transformed along x in blocks of rows) is
    the inverse transform of the whole zero-filled array, bit for bit, scaled or not."""
    import raywave.wave.propagation.band as W

    g = torch.Generator().manual_seed(10)
    for rows, mx, runs in ((83, 250, ((0, 120), (140, 250))), (503, 375, ((0, 180), (200, 375))), (37, 64, ((3, 60),))):
        n_cols = sum(b - a for a, b in runs)
        band = torch.randn(rows, n_cols, dtype=C128, generator=g)
        full = W.put(torch.zeros(rows, mx, dtype=C128), runs, band)
        keep = min(rows, mx) - 3
        for scale in (None, float(mx)):
            ref = torch.fft.ifft(full, dim=-1)[..., :keep]
            ref = ref if scale is None else ref * scale
            assert torch.equal(W._x_inverse(band, mx, runs, keep, scale), ref)


def test_band_convolution_field_by_field_equals_the_batch(monkeypatch):
    """On a CPU a batch's band convolution runs field by field (cache-sized blocks): the same values and gradients as
    the whole batch at once (the accelerator's way), for two leading axes, a per-field and a shared transfer."""
    import raywave.wave.propagation.band as W

    g = torch.Generator().manual_seed(7)
    rows, cols = torch.tensor([0, 1, 2, 5, 9, 14, 15]), torch.tensor([0, 3, 4, 7, 16, 17])
    size, noy, nox = (16, 18), 6, 5
    per_field = W.per_field
    assert per_field(torch.zeros(1), (2, 3)) and not per_field(torch.zeros(1), (1,))
    u0 = torch.randn(2, 3, 7, 9, dtype=C128, generator=g)
    w = torch.randn(2, 3, noy, nox, dtype=C128, generator=g)
    for h0 in (torch.randn(2, 3, 7, 6, dtype=C128, generator=g), torch.randn(7, 6, dtype=C128, generator=g)):
        results = []
        for batch in (False, True):
            monkeypatch.setattr(W, "per_field", (lambda u, lead: False) if batch else per_field)
            u, h = u0.clone().requires_grad_(), h0.clone().requires_grad_()
            out = W.BandConvolve.apply(u, h, size, rows, cols, noy, nox)
            results.append((out.detach(), *torch.autograd.grad((out * w.conj()).real.sum(), (u, h))))
        for a, b in zip(*results):
            assert float((a - b).abs().max()) <= 1e-14 * float(b.abs().max())


def test_band_convolution_on_an_accelerator_equals_the_cpu_plan(monkeypatch):
    """An accelerator's band convolution (the band's rows and columns by indexed gathers and copies, the x transform
    in one pass) equals the CPU's (slices of the runs, row blocks) to rounding: a batch, a shared transfer, column
    chunks, and with autograd through the plain operations."""
    import raywave.utils.devices as devices
    import raywave.wave.propagation.band as W

    g = torch.Generator().manual_seed(8)
    rows, cols = torch.tensor([0, 1, 2, 5, 9, 14, 15]), torch.tensor([0, 3, 4, 7, 16, 17])
    size, noy, nox = (16, 18), 6, 5
    u0 = torch.randn(2, 3, 7, 9, dtype=C128, generator=g)
    w = torch.randn(2, 3, noy, nox, dtype=C128, generator=g)
    for h0 in (torch.randn(2, 3, 7, 6, dtype=C128, generator=g), torch.randn(7, 6, dtype=C128, generator=g)):
        for limit in (2**60, 64):  # one block, then a block per column
            results = []
            for accel in (False, True):
                monkeypatch.setattr(devices, "accelerator", lambda x, a=accel: a)
                monkeypatch.setattr(W, "BAND_CHUNK_BYTES", limit)
                monkeypatch.setattr(W, "BAND_CHUNK_BYTES_ACCELERATOR", limit)
                with torch.no_grad():
                    plain = W.convolve_band(u0, h0, size, rows, cols, noy, nox)
                u, h = u0.clone().requires_grad_(), h0.clone().requires_grad_()
                out = W.convolve_band(u, h, size, rows, cols, noy, nox)
                results.append((plain, out.detach(), *torch.autograd.grad((out * w.conj()).real.sum(), (u, h))))
            for a, b in zip(*results):
                assert float((a - b).abs().max()) <= 1e-14 * float(b.abs().max())
