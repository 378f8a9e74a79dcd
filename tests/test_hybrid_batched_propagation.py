"""The batched propagation of issue 43 (raywave.wave.propagation.batch, raywave.hybrid.batched) against the
one-source path it replaces (``propagate_window`` / ``HybridLens.propagate``): the same values and gradients.

On one FFT size the batch is the single path to rounding (1e-13); a batch's common (larger) FFT grid samples each
source's rolled-off kernel spectrum more finely, which moves a PSF by ≤ 1e-7 relative L1 (the issue's bound: 1e-6)."""

import math
import warnings
import sys
from pathlib import Path

import pytest
import torch

from raywave.doe import PixelDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import ideal_lens
from raywave.wave.propagation.batch import WindowBatch, WindowSource, batch_transfer, propagate_batch

sys.path.insert(0, str(Path(__file__).parent))
from window_calls import window as _pw  # noqa: E402

P = 1e-3


def _sources(shapes):
    g = torch.Generator().manual_seed(3)
    geo = [((0.0, 0.01), (0.05, 0.06), (0.1, 0.05)), ((-0.02, 0.0), (0.03, 0.04), (0.08, 0.02)),
           ((0.0, 0.0), (0.02, 0.01), (0.0, 0.0))]
    us = [torch.randn(*s, dtype=torch.complex128, generator=g) for s in shapes]
    srcs = [WindowSource(tuple(s), i, o, 0.53, 1.5, 1.0, c) for s, (i, o, c) in zip(shapes, geo)]
    return us, srcs


def _run(wb, u, tr, **kw):
    """:func:`propagate_batch` of the padded envelopes ``u`` (B, Ny, Nx) of ``wb``'s sources: the output envelopes."""
    return propagate_batch(wb.field(u), wb.out_grids(), wb.distances(), transfer=tr, **kw).envelope


def _padded(us, shape):
    ny, nx = shape
    return torch.stack([torch.nn.functional.pad(u, (0, nx - u.shape[1], 0, ny - u.shape[0])) for u in us])


@pytest.mark.parametrize("weight_derivative", [False, True])
def test_batch_equals_propagate_window_on_one_fft_size(weight_derivative):
    us, srcs = _sources([(120, 100)] * 3)
    wb = WindowBatch(tuple(srcs), (41, 41), P)
    out = _run(wb, _padded(us, wb.in_shape()), batch_transfer(wb, weight_derivative=weight_derivative))
    for b, (s, u) in enumerate(zip(srcs, us)):
        ref = _pw(u, P, s.wavelength, s.z, s.in_origin, s.out_origin, (41, 41), n=s.n, carrier=s.carrier)
        assert float((out[b] - ref).abs().max() / ref.abs().max()) < 1e-13


def test_batch_of_different_windows_stays_close_to_each_ones_own_propagation():
    """Windows of three sizes on the largest one's FFT grid (random fields: the worst case for the kernel's
    spectral sampling; smooth physical fields move ≤ 1e-7, see the HybridLens test below)."""
    us, srcs = _sources([(120, 100), (90, 130), (60, 60)])
    wb = WindowBatch(tuple(srcs), (41, 41), P)
    assert wb.in_shape() == (120, 130)
    out = _run(wb, _padded(us, wb.in_shape()), batch_transfer(wb))
    for b, (s, u) in enumerate(zip(srcs, us)):
        ref = _pw(u, P, s.wavelength, s.z, s.in_origin, s.out_origin, (41, 41), n=s.n, carrier=s.carrier)
        assert float((out[b] - ref).abs().max() / ref.abs().max()) < 1e-3


def test_batch_gradients_of_field_shift_and_distance_equal_the_single_path():
    us, srcs = _sources([(120, 100)] * 3)
    wb = WindowBatch(tuple(srcs), (41, 41), P)
    tr = batch_transfer(wb, weight_derivative=True)
    w = torch.randn(3, 41, 41, dtype=torch.complex128, generator=torch.Generator().manual_seed(5))
    sh = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
    u = _padded(us, wb.in_shape()).requires_grad_(True)
    (_run(wb, u, tr, shift=sh, dz=dz) * w).real.sum().backward()
    dz_sum = 0.0
    for b, (s, ub) in enumerate(zip(srcs, us)):
        sb = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        d = torch.zeros((), dtype=torch.float64, requires_grad=True)
        ub = ub.clone().requires_grad_(True)
        ref = _pw(ub, P, s.wavelength, s.z, s.in_origin, s.out_origin, (41, 41), n=s.n,
                               carrier=s.carrier, shift=sb, dz=d)
        (ref * w[b]).real.sum().backward()
        assert torch.allclose(sh.grad[b], sb.grad, rtol=1e-10, atol=1e-9 * float(sb.grad.abs().max()))
        assert torch.allclose(u.grad[b, :120, :100], ub.grad, rtol=1e-10, atol=1e-14)
        dz_sum += float(d.grad)
    assert math.isclose(float(dz.grad), dz_sum, rel_tol=1e-10)


def test_batch_refuses_a_sharp_band_limit():
    us, srcs = _sources([(60, 60)])
    with pytest.raises(ValueError, match="roll-off"):
        batch_transfer(WindowBatch(tuple(srcs), (21, 21), P, guard=0.0))


# ------------------------------------------------------------------ HybridLens.propagate_fields
def _smooth(n, amp, seed, sigma_px=20.0):
    r = torch.randn(n, n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    f = torch.fft.fftfreq(n, dtype=torch.float64)
    g = torch.exp(-0.5 * (f[:, None] ** 2 + f[None, :] ** 2) * (2 * math.pi * sigma_px) ** 2)
    p = torch.fft.ifft2(torch.fft.fft2(r) * g).real
    return amp * p / p.std()


def _hybrid():
    lens = ideal_lens(5.0, f_number=8.0, wavelengths=(0.55, 0.45))
    return HybridLens(lens, PixelDOE(_smooth(600, 2.0, 0), 1e-3), 1.0, sensor_pitch=1e-3)


FIELDS = [(0.0, 0.0), (0.0, 0.6), (0.4, -0.3)]


def _single(hl, fds, ks):
    rows = [[hl.propagate(fd, ks) for fd in row] for row in fds]
    return tuple(torch.stack([torch.stack([r[i] for r in row]) for row in rows]) for i in range(3))


def test_hybrid_batched_psfs_equal_the_one_source_path():
    hl = _hybrid()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fds = hl.doe_fields(FIELDS, [0.55, 0.45])
        psf, cen, out, _ = hl.propagate_fields(fds, 24)
        ref, ref_c, ref_o = _single(hl, fds, 24)
    rel = (psf - ref).abs().sum((-2, -1)) / ref.abs().sum((-2, -1))
    assert float(rel.max()) < 1e-7
    assert torch.equal(cen, ref_c)
    assert float((out - ref_o).abs().max()) < 1e-9


def test_hybrid_batched_gradients_equal_the_one_source_path():
    """d(weighted PSFs)/d(DOE phase, last thickness) through the batch = through one source at a time (the DOE's
    window phasors, the window shifts and the sensor distance's dz)."""
    w = torch.randn(3, 2, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    grads = []
    for batched in (True, False):
        hl = _hybrid()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fds = hl.doe_fields(FIELDS, [0.55, 0.45])
        psf = hl.propagate_fields(fds, 24)[0] if batched else _single(hl, fds, 24)[0]
        (psf * w).sum().backward()
        grads.append((hl.doe.phase_map.grad.clone() if hasattr(hl.doe, "phase_map") else
                      next(p for p in hl.doe.parameters()).grad.clone(), hl.lens.surfaces[-1].thickness.grad.clone()))
    (gd_b, gt_b), (gd_s, gt_s) = grads
    assert float((gd_b - gd_s).abs().max()) < 1e-6 * float(gd_s.abs().max())
    assert math.isclose(float(gt_b), float(gt_s), rel_tol=1e-6)


def test_roll_off_derivatives_kept_on_their_lines_equal_the_dense_ones(monkeypatch):
    """The roll-off weights' derivatives are kept on the roll-off lines only (``RollOffRel``): their sums against a
    band-sized array and the perturbed amplitude equal the dense ``(B, 3, R, C)`` array's (zero off the lines), for
    the union's evaluation and each source's own band, and a non-zero window shift perturbs the same."""
    import raywave.wave.propagation.batch as batch_mod
    from raywave.wave.propagation.batch import RollOffRel

    us, srcs = _sources([(120, 100), (90, 130), (60, 60)])
    wb = WindowBatch(tuple(srcs), (41, 41), P)
    monkeypatch.setattr(batch_mod, "_by_source", lambda device, b: False)
    tr = batch_transfer(wb, weight_derivative=True)
    rel = tr.rel
    assert isinstance(rel, RollOffRel) and (rel.x or rel.y)
    dense = rel.dense()
    assert tuple(dense.shape) == (3, 3, *tr.band.shape[1:])
    q = torch.randn(tr.band.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    for c in range(3):
        ref = (q * dense[:, c]).sum((-2, -1), keepdim=True)
        assert torch.allclose(rel.sums(q, c), ref, rtol=1e-13, atol=1e-13 * float(ref.abs().max()))
    sx, sy = (torch.full((3, 1, 1), v, dtype=torch.float64) for v in (1e-3, -2e-3))
    dz = torch.tensor(3e-3, dtype=torch.float64)
    assert torch.equal(rel.amplitude(sx, sy, dz), 1.0 + (sx * dense[:, 1] + sy * dense[:, 2] + dz * dense[:, 0]))
    one = rel.source(1)
    assert one.shape == (1, *rel.shape[1:]) and torch.equal(one.dense()[0], dense[1])


def _mirror_images(in_shape, in_origin, out_origin, carrier, nout):
    """A source and its three mirror images (x, y, both): windows mirrored about the axes, carriers negated."""
    (niy, nix), (x0, y0), (cx, cy), (ax, ay) = in_shape, in_origin, out_origin, carrier
    out = []
    for sx, sy in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        xi = x0 if sx > 0 else -(x0 + (nix - 1) * P)
        yi = y0 if sy > 0 else -(y0 + (niy - 1) * P)
        xo = cx if sx > 0 else -(cx + (nout - 1) * P)
        yo = cy if sy > 0 else -(cy + (nout - 1) * P)
        out.append(WindowSource(in_shape, (xi, yi), (xo, yo), 0.53, 1.5, 1.0, (sx * ax, sy * ay)))
    return out


@pytest.mark.parametrize("in_shape, in_origin, out_origin, carrier", [
    ((120, 100), (0.01, -0.03), (0.05, 0.02), (0.03, -0.02)),   # even FFT sizes, off-axis in x and y
    ((121, 101), (-0.06, -0.06), (-0.02, -0.02), (0.0, 0.0)),    # on axis, its window symmetric in y
    ((90, 131), (0.2, -0.045), (0.27, -0.02), (0.12, 0.0)),      # a large carrier along x only
])
def test_lazily_evaluated_bands_equal_the_single_window_transfer(monkeypatch, in_shape, in_origin, out_origin, carrier):
    """On the CPU each source's transfer function is evaluated where the band convolution uses it (one compiled loop,
    :class:`~raywave.wave.propagation.kernels.TransferBand`): its band (rows, columns) and values equal the
    single-window :func:`window_transfer` of that source alone on the same FFT size, and the eager chain's values
    (to the phases' rounding, ~1e-12 of the band for phases of ~1e4 rad), its column blocks are the band's columns bit for bit, and the propagated
    fields equal the union's evaluation (an accelerator's plan) to 1e-12."""
    import raywave.wave.propagation.batch as batch_mod
    import raywave.wave.propagation.transfer as transfer_mod
    from raywave.wave.grid import Field, Grid

    nout = 41
    srcs = _mirror_images(in_shape, in_origin, out_origin, carrier, nout)
    wb = WindowBatch(tuple(srcs), (nout, nout), P)
    lazy = batch_transfer(wb)
    assert lazy.parts is not None and all(p.values is not None for p in lazy.parts)
    my, mx = lazy.size
    fx = torch.fft.fftfreq(mx, d=P, dtype=torch.float64)
    fy = torch.fft.fftfreq(my, d=P, dtype=torch.float64)
    for s, part, geo in zip(srcs, lazy.parts, wb.geometries()):
        field = Field(torch.zeros(s.in_shape, dtype=torch.complex128), Grid(s.in_origin, P, s.in_shape),
                      s.wavelength, s.n, s.carrier)
        ref = transfer_mod.window_transfer(field, Grid(s.out_origin, P, (nout, nout)), s.z)
        assert ref.size == lazy.size and torch.equal(ref.rows, part.rows) and torch.equal(ref.cols, part.cols)
        band = part.band
        assert torch.equal(band, ref.band)  # the single window's transfer: the same compiled loop
        eager = transfer_mod._eager_band_values(geo, fx, fy, (part.rows, part.cols), False)[0]
        scale = float(eager.abs().max())
        assert scale > 0 and float((band - eager).abs().max()) <= 1e-11 * scale
        c = band.shape[1]
        assert torch.equal(part.values.block(3, c - 2), band[:, 3:c - 2].T)
    monkeypatch.setattr(batch_mod, "_by_source", lambda device, b: False)
    union = batch_transfer(wb)
    monkeypatch.undo()
    assert union.parts is None
    g = torch.Generator().manual_seed(5)
    u = torch.randn((4, *in_shape), dtype=torch.complex128, generator=g)
    v_lazy, v_union = _run(wb, u, lazy), _run(wb, u, union)
    assert float((v_lazy - v_union).abs().max()) <= 1e-12 * float(v_union.abs().max())


@pytest.mark.parametrize("in_shape, in_origin, out_origin, carrier", [
    ((120, 100), (0.01, -0.03), (0.05, 0.02), (0.03, -0.02)),
    ((90, 131), (0.2, -0.045), (0.27, -0.02), (0.12, 0.0)),
])
def test_lazily_evaluated_bands_carry_the_union_gradients(monkeypatch, in_shape, in_origin, out_origin, carrier):
    """With autograd the lazily evaluated bands (``_TransferConvolve``: the forward without the band-sized transfer
    function, the backward evaluating it once more) give the window-shift, distance and field gradients of the
    union's evaluation (the materialised band through ``_Perturbed`` and ``BandConvolve``) to 1e-10, and the forward
    equals the one without autograd bit for bit."""
    import raywave.wave.propagation.batch as batch_mod

    nout = 41
    wb = WindowBatch(tuple(_mirror_images(in_shape, in_origin, out_origin, carrier, nout)), (nout, nout), P)
    lazy = batch_transfer(wb, weight_derivative=True)
    monkeypatch.setattr(batch_mod, "_by_source", lambda device, b: False)
    union = batch_transfer(wb, weight_derivative=True)
    monkeypatch.undo()
    assert lazy.parts is not None and union.parts is None
    g = torch.Generator().manual_seed(7)
    u0 = torch.randn((4, *in_shape), dtype=torch.complex128, generator=g)
    w = torch.randn((4, nout, nout), dtype=torch.complex128, generator=g)
    grads, outs = [], []
    for transfer in (lazy, union):
        u = u0.clone().requires_grad_()
        shift = torch.zeros((4, 2), dtype=torch.float64, requires_grad=True)
        dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
        out = _run(wb, u, transfer, shift=shift, dz=dz)
        grads.append(torch.autograd.grad((out * w.conj()).real.sum(), (u, shift, dz)))
        outs.append(out.detach())
    with torch.no_grad():
        assert torch.equal(outs[0], _run(wb, u0, lazy))
    assert float((outs[0] - outs[1]).abs().max()) <= 1e-12 * float(outs[1].abs().max())
    for a, b in zip(*grads):
        assert float((a - b).abs().max()) <= 1e-10 * float(b.abs().max())


