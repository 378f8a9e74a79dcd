"""The batched engine (issue 17, part 3): one ``psf_result`` call over fields × wavelengths builds every DOE-plane
field together (footprints, DOE-clipping diagnostics and the accurate constructions' ray traces batched across
all of them, :func:`raywave.hybrid.coherent.run_batched`). It must give the PSFs of one call per field and
wavelength: each ray is traced on its own, so the batch changes nothing but the number of kernel launches."""

import warnings

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.hybrid import coherent
from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens

WLS = [0.47, 0.55, 0.66]


def _ideal(stop_edge):
    lens = ideal_lens(5.0, f_number=4.0, wavelengths=(0.55,))
    return HybridLens(lens, BlankDOE(200, 2e-3), 1.0, sensor_pitch=2e-3, stop_edge=stop_edge)


def _asphere():
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    return HybridLens(lens, BlankDOE(500, 4e-3), 0.7, sensor_pitch=4e-3)


def _one_by_one(hl, fields, wls, **kw):
    rows = [[hl.psf_result(f, wl, **kw) for wl in wls] for f in fields]

    def stack(attr):
        return torch.stack([torch.stack([getattr(r, attr)[0, 0] for r in row]) for row in rows])

    return {a: stack(a) for a in ("psf", "center", "energy_outside", "doe_clipped")}


@pytest.mark.parametrize("build,fields,wls", [
    # (0, 40): the beam lands far off the 0.4 mm DOE (an all-zero PSF)
    (lambda: _ideal("doe"), [(0.0, 3.0), (2.0, -1.5), (0.0, 40.0)], [0.47, 0.66]),
    pytest.param(lambda: _ideal("exit_pupil"), [(0.0, 0.0), (1.0, 2.0)], [0.47, 0.66], marks=pytest.mark.slow),
    pytest.param(_asphere, [(0.0, 0.0), (0.0, 10.0), (4.0, 8.0)], WLS, marks=pytest.mark.slow),
], ids=["ideal_doe_edge_vignetted", "ideal_exit_pupil_edge", "asphere"])
def test_batched_psfs_equal_one_call_per_field_and_wavelength(build, fields, wls):
    hl = build()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            batch = hl.psf_result(fields, wls, ks=12, rays=16)
            single = _one_by_one(hl, fields, wls, ks=12, rays=16)
    for attr in ("psf", "center", "energy_outside"):
        err = float((getattr(batch, attr) - single[attr]).abs().max())
        assert err <= 1e-12, f"{attr}: max |Δ| = {err:.3g}"
    # the DOE-aperture diagnostic: rays aimed together (the aim's iteration runs over the batch)
    assert torch.allclose(batch.doe_clipped, single["doe_clipped"], rtol=0, atol=1e-9)
    if (0.0, 40.0) in fields:
        assert float(batch.psf[-1].abs().max()) == 0.0 and float(batch.psf[:-1].sum()) > 0


def test_the_traces_of_a_call_are_batched_across_fields_and_wavelengths(monkeypatch):
    """One psf_result call over 3 fields × 2 wavelengths: the field constructions' traces go in batches (one per
    round, the wavelengths together: each row of the batch carries its own), far fewer trace calls than one
    construction at a time."""
    sizes = []
    real = coherent._trace_group

    def spy(reqs):
        sizes.append(len(reqs))
        return real(reqs)

    monkeypatch.setattr(coherent.tracing, "_trace_group", spy)  # the module whose run_batched calls it
    hl = _ideal("doe")
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        hl.psf_result([(0.0, 0.0), (0.0, 3.0), (2.0, -1.5)], [0.47, 0.66], ks=8, rays=16)
    assert max(sizes) == 6 and sum(sizes) / len(sizes) > 4


@pytest.mark.slow
def test_batched_psfs_keep_their_gradients():
    """With autograd: the batched construction differentiates like one call per field (the lens's last thickness,
    i.e. focus, through the traced rays and the sensor distance)."""
    hl = _asphere()
    t = hl.lens.surfaces[-1].thickness
    fields = [(0.0, 0.0), (0.0, 10.0)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = torch.linspace(0, 1, 12 * 12, dtype=torch.float64).reshape(12, 12)
        (g_batch,) = torch.autograd.grad((hl.psf(fields, [0.47, 0.66], ks=12, rays=16) * w).sum(), t)
        loss = sum((hl.psf(f, wl, ks=12, rays=16) * w).sum() for f in fields for wl in (0.47, 0.66))
        (g_single,) = torch.autograd.grad(loss, t)
    assert float(g_single.abs()) > 0
    assert float((g_batch - g_single).abs()) <= 1e-10 * float(g_single.abs())


@pytest.mark.parametrize("ks, ps, p", [(32, 0.003, 0.001), (64, 0.002, 0.001), (48, 0.00345, 0.00115)])
def test_output_window_does_not_depend_on_the_last_bits_of_the_chief_ray(ks, ps, p):
    """The output window's half width is the ceil of spans that are exact integers in samples when the sensor pixel is
    a whole number of simulation samples: the chief ray's position rounded differently (1e-13 mm) must not add a
    sample (issue 46: one sample more moved a grating's PSF by 1.1e-5). Before SPAN_ROUNDING, ks 64 / 2 µm / 1 µm gave
    73 or 74 samples depending on where the chief ray landed."""
    import random

    from raywave.hybrid.batched import SensorWindow, out_half_width

    rng = random.Random(0)
    s = SensorWindow(ks, ps, 2)
    widths = {out_half_width(s, p, (xc + d, 0.0)) for xc in (rng.uniform(-3.0, 3.0) for _ in range(500))
              for d in (0.0, 1e-13, -1e-13, 3e-13)}
    assert len(widths) == 1
    kk = widths.pop()
    assert 2 * kk + 1 >= ks * ps / p  # the window still covers the crop
