"""The sensor model: noise mean and variance against the Poisson–Gaussian formulas, saturation, bit depth,
reproducibility through generators, gradients, and the sRGB transfer function's reference values."""

import math

import pytest
import torch

from raywave.imaging import Sensor, apply_gamma, linear_to_srgb, srgb_to_linear

D = torch.float64
N = 400_000


def stats(y):
    return float(y.mean()), float(y.var())


def within(value, expected, sd, k=5.0):
    """|value − expected| < k standard errors."""
    return abs(value - expected) < k * sd


@pytest.mark.parametrize("x", [0.02, 0.3, 0.8])
def test_poisson_gaussian_mean_and_variance_match_the_model(x):
    """Electrons: full well 5000 e⁻, read noise 3 e⁻, gain 2 → a = 4e-4, σ = 1.2e-3: E = x, Var = a·x + σ²."""
    s = Sensor.from_electrons(full_well=5000, read_noise=3.0, gain=2.0, bit_depth=None, clip=False)
    assert s.shot == pytest.approx(4e-4) and s.read == pytest.approx(1.2e-3)
    y = s(torch.full((N,), x, dtype=D), generator=torch.Generator().manual_seed(1))
    m, v = stats(y)
    var = 4e-4 * x + 1.2e-3**2
    assert within(m, x, math.sqrt(var / N))
    # standard error of a sample variance: sqrt((μ4 − σ⁴)/N) ≈ σ² sqrt(2/N) (+ Poisson excess kurtosis, small)
    assert within(v, var, var * math.sqrt(2.0 / N) * 1.2)
    # the counts are Poisson: (y − read noise) / a is integer-valued when there is no read noise
    s0 = Sensor.normalised(shot=1e-3, read=0.0, bit_depth=None, clip=False)
    c = s0(torch.full((1000,), x, dtype=D), generator=torch.Generator().manual_seed(2)) / 1e-3
    assert torch.allclose(c, torch.round(c), atol=1e-9)


def test_gaussian_approximation_has_the_same_moments_and_is_differentiable():
    s = Sensor.normalised(shot=2e-3, read=5e-3, bit_depth=None, clip=False, noise="gaussian")
    x = torch.full((N,), 0.4, dtype=D, requires_grad=True)
    y = s(x, generator=torch.Generator().manual_seed(3))
    m, v = stats(y.detach())
    var = 2e-3 * 0.4 + 5e-3**2
    assert within(m, 0.4, math.sqrt(var / N)) and within(v, var, var * math.sqrt(2.0 / N))
    y.sum().backward()
    # d/dx [x + sqrt(a x + σ²) n] = 1 + a n / (2 sqrt(a x + σ²)): mean 1
    assert float(x.grad.mean()) == pytest.approx(1.0, abs=5 * 2e-3 / (2 * math.sqrt(var)) / math.sqrt(N))


def test_quantisation_adds_a_step_squared_over_twelve_and_clipping_saturates():
    s = Sensor.normalised(shot=1e-4, read=2e-3, bit_depth=8, clip=True)
    y = s(torch.full((N,), 0.5, dtype=D), generator=torch.Generator().manual_seed(4))
    step = 1 / 255
    assert torch.allclose(y * 255, torch.round(y * 255), atol=1e-9)  # on the ADC levels
    var = 1e-4 * 0.5 + 2e-3**2 + step**2 / 12
    m, v = stats(y)
    assert within(m, 0.5, math.sqrt(var / N)) and within(v, var, var * math.sqrt(2.0 / N) * 1.5)
    sat = s(torch.tensor([1.5, -0.2, 1.0], dtype=D), generator=torch.Generator().manual_seed(5))
    assert float(sat.max()) <= 1.0 and float(sat.min()) >= 0.0 and float(sat[0]) == 1.0


def test_noise_is_reproducible_through_the_generator_only():
    s = Sensor()
    x = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0), dtype=D)
    a = s(x, generator=torch.Generator().manual_seed(9))
    torch.manual_seed(123)  # the global RNG plays no part
    b = s(x, generator=torch.Generator().manual_seed(9))
    c = s(x, generator=torch.Generator().manual_seed(10))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_straight_through_gradients_and_no_noise_mode():
    x = torch.rand(64, dtype=D, requires_grad=True)
    y = Sensor(noise="poisson")(x * 0.9, generator=torch.Generator().manual_seed(0))
    y.sum().backward()
    assert torch.allclose(x.grad, torch.full_like(x, 0.9))
    z = Sensor(noise="none", bit_depth=None)(x.detach())
    assert torch.equal(z, x.detach().clamp(0, 1))


def test_pitch_resolution_and_bad_input():
    from raywave.lens.build import bundled_lens_path, load_lens

    s = Sensor.from_lens(load_lens(bundled_lens_path("asphere_hk51")))
    assert s.pitch == pytest.approx(0.003) and s.resolution == (1920, 1080)
    assert s.size == pytest.approx((5.76, 3.24))
    with pytest.raises(ValueError, match="bit_depth"):
        Sensor(bit_depth=0)
    with pytest.raises(ValueError, match="noise"):
        Sensor(noise="speckle")
    with pytest.raises(ValueError, match="read"):
        Sensor(read=-1)
    with pytest.raises(ValueError, match="full_well"):
        Sensor.from_electrons(full_well=0)
    with pytest.raises(TypeError, match="float"):
        Sensor()(torch.zeros(3, dtype=torch.uint8))


def test_srgb_transfer_function_reference_values():
    """IEC 61966-2-1: linear 0.5 → 0.7354, 0.0031308 → 0.04045 (the knee), 0.18 → 0.4614; round trip."""
    x = torch.tensor([0.0, 0.0031308, 0.18, 0.5, 1.0], dtype=D)
    e = linear_to_srgb(x)
    assert e.tolist() == pytest.approx([0.0, 0.04045, 0.46135, 0.73536, 1.0], abs=2e-5)
    t = torch.linspace(0, 1, 101, dtype=D)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(t)), t, atol=1e-12)
    assert float(apply_gamma(torch.tensor(0.25, dtype=D), 2.0)) == pytest.approx(0.5)
    assert torch.equal(Sensor.display(t, "linear"), t)
