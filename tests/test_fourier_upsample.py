"""raywave.wave.field.fourier_upsample (issue 46: the exact edge step's coarse lattice upsampled to the DOE pitch),
computed as ``factor`` shifted sample sets per axis, against its definition: the inverse FFT of the spectrum
zero-padded to ``factor`` times the length (an even length's Nyquist term split in halves), values and gradients."""

import pytest
import torch

from raywave.wave.field import fourier_upsample


def _padded(spec, n_big, dim):
    n = spec.shape[dim]
    h = n // 2
    zeros = list(spec.shape)
    if n % 2:
        zeros[dim] = n_big - n
        return torch.cat([spec.narrow(dim, 0, h + 1), spec.new_zeros(zeros), spec.narrow(dim, h + 1, h)], dim)
    nyq = spec.narrow(dim, h, 1) * 0.5
    zeros[dim] = n_big - n - 1
    return torch.cat([spec.narrow(dim, 0, h), nyq, spec.new_zeros(zeros), nyq, spec.narrow(dim, h + 1, h - 1)], dim)


def _definition(u, f):
    ny, nx = u.shape[-2:]
    spec = _padded(_padded(torch.fft.fft2(u), f * ny, -2), f * nx, -1)
    return torch.fft.ifft2(spec) * float(f * f)


@pytest.mark.parametrize("shape", [(11, 13), (12, 13), (11, 14), (2, 16, 10)])
@pytest.mark.parametrize("factor", [2, 3, 4])
def test_fourier_upsample_is_the_padded_spectrum(shape, factor):
    g = torch.Generator().manual_seed(11)
    u = torch.complex(torch.randn(shape, generator=g, dtype=torch.float64),
                      torch.randn(shape, generator=g, dtype=torch.float64)).requires_grad_()
    got = fourier_upsample(u, factor)
    ref = _definition(u, factor)
    assert got.shape == ref.shape
    assert float((got - ref).abs().max()) <= 1e-14 * float(ref.abs().max())
    assert torch.allclose(got[..., ::factor, ::factor], u, rtol=0, atol=1e-14)  # the input's own samples
    w = torch.complex(torch.randn(ref.shape, generator=g, dtype=torch.float64),
                      torch.randn(ref.shape, generator=g, dtype=torch.float64))
    g_got, = torch.autograd.grad(got, u, w)
    g_ref, = torch.autograd.grad(ref, u, w)
    assert float((g_got - g_ref).abs().max()) <= 1e-14 * float(g_ref.abs().max())


def test_fourier_upsample_by_one_is_the_input():
    u = torch.ones((3, 4), dtype=torch.complex128)
    assert fourier_upsample(u, 1) is u
    with pytest.raises(ValueError, match="factor"):
        fourier_upsample(u, 0)
