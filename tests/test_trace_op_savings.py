"""Issue 43 (h43j): the cheaper trace paths give the values of the paths they replace, bit for bit."""

import math

import torch

from raywave.assembly.build import load_hybrid
from raywave.lens.build import bundled_lens_path
from raywave.lens.sources import rays_through


def _rays(lens, n=500):
    g = torch.Generator().manual_seed(1)
    uv = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 14.0  # out to where rays miss or meet TIR
    fields = torch.rand(n, 2, generator=g, dtype=torch.float64) * 14.0
    wls = torch.tensor([0.47, 0.53, 0.66], dtype=torch.float64)[torch.arange(n) % 3]
    return rays_through(lens, uv[:, None, None], fields, "angle", wls.reshape(-1, 1, 1))


def test_asphere_trace_without_autograd_equals_the_differentiable_trace():
    # without autograd the Newton intersection's last step is the iteration's own (one sag evaluation); with it, one
    # differentiable step from the converged point: the same numbers
    lens = load_hybrid(bundled_lens_path("hybrid_asphere")).lens
    rays = _rays(lens)
    with torch.no_grad():
        a = lens.trace(rays, apertures=False)
    b = lens.trace(rays, apertures=False)
    assert b.o.requires_grad
    assert torch.equal(a.o, b.o.detach()) and torch.equal(a.d, b.d.detach()) and torch.equal(a.valid, b.valid)
    assert torch.equal(a.opl, b.opl.detach())
    assert bool(a.valid.any()) and not bool(a.valid.all())  # both kinds of rays compared


def test_exit_pupils_of_several_wavelengths_equal_their_own_calls():
    for name in ("hybrid_asphere", "cooke_triplet", "double_gauss"):
        hl = load_hybrid(bundled_lens_path(name))
        wls = [0.66, 0.53, 0.47]
        single = [hl.exit_pupil_z(w) for w in wls]
        assert hl._exit_pupil_zs(wls) == single, name
        assert all(math.isfinite(z) for z in single)


def test_a_float32_trace_stays_float32():
    """The asphere's Newton constants take the rays' dtype: a float32 trace (raywave.hybrid.precision's comparison)
    is not promoted to float64 by them."""
    import warnings as _w

    from raywave.lens.build import bundled_lens_path, load_lens
    from raywave.lens.sources import point_source_rays

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    g = torch.linspace(-1, 1, 9, dtype=torch.float64)
    px, py = torch.meshgrid(g, g, indexing="xy")
    keep = px**2 + py**2 <= 1
    with _w.catch_warnings():
        _w.simplefilter("ignore")
        rays = point_source_rays(lens, (0.0, 0.0), 0.55, pupil=(px[keep], py[keep]), aim="chief", depth=1e4,
                                 dtype=torch.float32)
        out = lens.trace(rays)
    assert rays.o.dtype == torch.float32
    assert out.o.dtype == out.d.dtype == out.opl.dtype == torch.float32
