"""The pre-stage's restorability term (raywave.training.losses.wiener_restoration_error /
psf_restorability_loss): closed forms of the Wiener error, and a Monte-Carlo restoration that measures the
error it predicts."""

import math

import pytest
import torch

from raywave.training.baselines import objective_settings, psf_objective
from raywave.training.config import PreStageConfig
from raywave.training.losses import _image_spectrum, psf_restorability_loss, wiener_restoration_error

KS = 32


def _delta(dy=0, dx=0):
    p = torch.zeros(KS, KS, dtype=torch.float64)
    p[KS // 2 + dy, KS // 2 + dx] = 1.0
    return p


def _box(w):
    p = torch.zeros(KS, KS, dtype=torch.float64)
    c = KS // 2
    p[c - w // 2:c + w // 2 + 1, c - w // 2:c + w // 2 + 1] = 1.0
    return p / p.sum()


def _gauss(s):
    y = torch.arange(KS, dtype=torch.float64) - KS // 2
    g = torch.exp(-(y[:, None] ** 2 + y[None, :] ** 2) / (2 * s * s))
    return g / g.sum()


def test_one_depth_is_the_wiener_minimum_mean_square_error():
    """D = 1: the error is the classic MMSE mean_f P r / (|K|² P + r) (an independent closed form)."""
    r = 2e-3
    for psf in (_delta(), _box(5), _gauss(2.0)):
        k = torch.fft.fft2(torch.fft.ifftshift(psf))
        p = _image_spectrum(KS, KS, torch.float64, "cpu")
        want = 10 * math.log10(float((p * r / (k.abs() ** 2 * p + r)).mean()))
        got = float(wiener_restoration_error(psf[None], r)[0])
        assert got == pytest.approx(want, abs=1e-10)


def test_depth_mean_of_errors_is_the_closed_form_minimum():
    """Averaged over the depths, the error of the one filter is mean_f (P − |mean K|² P² / (mean|K|² P + r))."""
    r = 1e-3
    psf = torch.stack([_delta(), _box(7), _gauss(1.5)])
    k = torch.fft.fft2(torch.fft.ifftshift(psf, dim=(-2, -1)))
    p = _image_spectrum(KS, KS, torch.float64, "cpu")
    a, b = k.abs().square().mean(0), k.mean(0)
    want = float((p - b.abs().square() * p * p / (a * p + r)).mean())
    got = (10 ** (wiener_restoration_error(psf, r) / 10)).mean()
    assert float(got) == pytest.approx(want, rel=1e-10)


def test_a_depth_that_disagrees_costs_and_a_sharp_psf_restores_best():
    r = 1e-3
    same = wiener_restoration_error(torch.stack([_delta(), _delta()]), r)
    shifted = wiener_restoration_error(torch.stack([_delta(), _delta(0, 3)]), r)
    p = _image_spectrum(KS, KS, torch.float64, "cpu")
    assert float(same[0]) == pytest.approx(10 * math.log10(float((p * r / (p + r)).mean())), abs=1e-10)
    assert (shifted > same + 10).all()  # a shift between depths is unrestorable by one filter
    e = [float(wiener_restoration_error(torch.stack([_gauss(s)] * 2), r)[0]) for s in (0.7, 1.5, 3.0)]
    assert e[0] < e[1] < e[2]


def test_monte_carlo_restoration_measures_the_predicted_error():
    """Random images with the model spectrum, blurred circularly by each depth's PSF, white noise of variance
    r added, restored by the one filter: the measured MSE / signal variance matches the prediction (3 %)."""
    g = torch.Generator().manual_seed(0)
    r = 1e-3
    psf = torch.stack([_delta(), _gauss(2.0)])
    k = torch.fft.fft2(torch.fft.ifftshift(psf, dim=(-2, -1)))
    p = _image_spectrum(KS, KS, torch.float64, "cpu")
    filt = k.mean(0).conj() * p / (k.abs().square().mean(0) * p + r)
    n = 400
    white = torch.randn(n, KS, KS, dtype=torch.float64, generator=g)
    img = torch.fft.ifft2(torch.fft.fft2(white) * p.sqrt()).real  # spectrum P, unit variance per pixel
    mse = []
    for d in range(2):
        blurred = torch.fft.ifft2(torch.fft.fft2(img) * k[d]).real
        noisy = blurred + math.sqrt(r) * torch.randn(n, KS, KS, dtype=torch.float64, generator=g)
        rest = torch.fft.ifft2(torch.fft.fft2(noisy) * filt).real
        mse.append(float((rest - img).square().mean() / img.square().mean()))
    want = 10 ** (wiener_restoration_error(psf, r) / 10)
    assert mse == pytest.approx(want.tolist(), rel=0.03)


def test_restorability_loss_leans_to_the_worst_depth_and_has_gradients():
    psf = torch.stack([_delta(), _gauss(2.5)])[:, None].repeat(1, 3, 1, 1).requires_grad_(True)
    e = wiener_restoration_error(psf.detach(), 1e-3)
    hard = float(psf_restorability_loss(psf.detach(), 1e-3, temperature=1e-3))
    assert hard == pytest.approx(float(e.max(0).values.mean()), abs=1e-2)
    soft = psf_restorability_loss(psf, 1e-3, temperature=1.0)
    assert float(e.mean(0).mean()) < float(soft.detach()) <= float(e.max(0).values.mean()) + 1e-12
    soft.backward()
    assert psf.grad is not None and torch.isfinite(psf.grad).all() and psf.grad.abs().sum() > 0


def test_psf_objective_adds_the_term_only_when_weighted():
    psf = torch.stack([_delta(), _gauss(2.0)])[:, None]
    pc = PreStageConfig(similarity_weight=1.0, about="center")
    base = psf_objective(psf, **objective_settings(pc))
    assert set(objective_settings(pc)) == {"similarity_weight", "about"}  # stored baseline designs stay reusable
    pc.restore_weight, pc.restore_noise = 2.0, 1e-3
    full = psf_objective(psf, **objective_settings(pc))
    assert float(full - base) == pytest.approx(2.0 * float(psf_restorability_loss(psf, 1e-3)), rel=1e-12)
    with pytest.raises(ValueError, match="noise"):
        wiener_restoration_error(psf, 0.0)


def test_own_filter_is_each_depths_mmse_and_ignores_shifts():
    """``filter="own"`` (the select reconstruction): each depth's classic MMSE, so a shift between depths costs
    nothing (the shared filter pays > 10 dB for it), and a Monte-Carlo restoration with each depth's own filter
    measures the predicted error (3 %)."""
    r = 1e-3
    p = _image_spectrum(KS, KS, torch.float64, "cpu")
    psf = torch.stack([_delta(), _delta(0, 3), _gauss(2.0)])
    own = wiener_restoration_error(psf, r, filter="own")
    k = torch.fft.fft2(torch.fft.ifftshift(psf, dim=(-2, -1)))
    want = 10 * torch.log10((p * r / (k.abs().square() * p + r)).mean((-2, -1)))
    assert torch.allclose(own, want, atol=1e-10)
    assert float(own[0]) == pytest.approx(float(own[1]), abs=1e-10)
    assert float(wiener_restoration_error(psf[:2], r)[1]) > float(own[1]) + 10
    g = torch.Generator().manual_seed(1)
    n = 400
    img = torch.fft.ifft2(torch.fft.fft2(torch.randn(n, KS, KS, dtype=torch.float64, generator=g)) * p.sqrt()).real
    mse = []
    for d in range(3):
        noisy = torch.fft.ifft2(torch.fft.fft2(img) * k[d]).real
        noisy = noisy + math.sqrt(r) * torch.randn(n, KS, KS, dtype=torch.float64, generator=g)
        filt = k[d].conj() * p / (k[d].abs().square() * p + r)
        rest = torch.fft.ifft2(torch.fft.fft2(noisy) * filt).real
        mse.append(float((rest - img).square().mean() / img.square().mean()))
    assert mse == pytest.approx((10 ** (own / 10)).tolist(), rel=0.03)
    with pytest.raises(ValueError, match="filter"):
        wiener_restoration_error(psf, r, filter="mean")


def test_own_filter_reaches_the_objective_and_float32_gradients_stay_finite():
    psf = torch.stack([_delta(), _gauss(2.0)])[:, None].float().requires_grad_(True)
    pc = PreStageConfig(similarity_weight=0.0, about="center", restore_weight=1.5, restore_filter="own")
    kw = objective_settings(pc)
    assert kw["restore_filter"] == "own"
    loss = psf_objective(psf, **kw)
    want = psf_objective(psf.detach(), about="center") + 1.5 * psf_restorability_loss(psf.detach(), 1e-3,
                                                                                      filter="own")
    assert float(loss) == pytest.approx(float(want), rel=1e-6)
    loss.backward()  # the delta's spectrum has no exact zero, but a zero PSF region must not give NaN either
    assert torch.isfinite(psf.grad).all()
