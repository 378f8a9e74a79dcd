"""The engine's block sizes (issue 43): the lens traces' chunks, the edge envelope's row blocks and the band
convolution's column chunks are loops over blocks that bound memory on the CPU; an accelerator takes larger blocks
(fewer ops to launch). The values must not depend on them, and the pixel integration's weights, built once per
geometry, must be those built per call."""

import pytest
import torch

import raywave.hybrid.coherent.stop_edge as edge_mod
import raywave.lens.lens as lens_mod
import raywave.wave.propagation.band as window_mod
from raywave.assembly.build import load_hybrid
from raywave.hybrid.batched import GeometryMemo
from raywave.lens.build import bundled_lens_path
from raywave.wave.propagation import integrated_upsampled_intensity, upsampled_pixel_weights


def test_block_sizes_per_device():
    """The CPU's sizes on the CPU, the accelerator's elsewhere (a meta tensor stands in for a CUDA one)."""
    assert lens_mod.trace_chunk("cpu") == lens_mod.TRACE_CHUNK
    assert lens_mod.trace_chunk(torch.device("cuda", 0)) == lens_mod.TRACE_CHUNK_ACCELERATOR
    for dev, samples in (("cpu", edge_mod.ENVELOPE_BLOCK_SAMPLES), ("meta", edge_mod.ENVELOPE_BLOCK_SAMPLES_ACCELERATOR)):
        nu = torch.zeros((2, 1000), dtype=torch.float64, device=dev)
        assert edge_mod._block_rows(nu) == max(edge_mod.ENVELOPE_BLOCK_ROWS, samples // 1000)
    # a 4096-row band of 4096 columns, complex128: 256 MB per field
    for dev, limit in (("cpu", window_mod.BAND_CHUNK_BYTES), ("meta", window_mod.BAND_CHUNK_BYTES_ACCELERATOR)):
        u = torch.zeros((1, 4, 4), dtype=torch.complex128, device=dev)
        assert window_mod.band_chunks(u, 4096, 4096) == min(4096, -(-(4096 * 4096 * 16) // limit))


@pytest.fixture(scope="module")
def asphere_psfs():
    """The bundled hybrid asphere (default exit-pupil edge) and its PSFs on axis and off axis at 0.53 µm with the
    CPU's default block sizes."""
    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    with torch.no_grad():
        return hl, hl.psf_result(FIELDS, [0.53], ks=32).psf


FIELDS = [(0.0, 0.0), (3.0, 4.0)]


@pytest.mark.parametrize("mod, name, size, exact", [
    (lens_mod, "TRACE_CHUNK", 4096, True),  # hundreds of trace chunks
    (lens_mod, "TRACE_CHUNK", lens_mod.TRACE_CHUNK_ACCELERATOR, True),
    (edge_mod, "ENVELOPE_BLOCK_SAMPLES", 4096, True),  # blocks of 64 rows
    (edge_mod, "ENVELOPE_BLOCK_SAMPLES", edge_mod.ENVELOPE_BLOCK_SAMPLES_ACCELERATOR, True),
    # other column blocks: the same transforms on other shapes of arrays: rounding apart
    (window_mod, "BAND_CHUNK_BYTES", 2**16, False),
    (window_mod, "BAND_CHUNK_BYTES", window_mod.BAND_CHUNK_BYTES_ACCELERATOR, False),
], ids=["trace-small", "trace-accelerator", "envelope-small", "envelope-accelerator", "band-small",
        "band-accelerator"])
def test_psfs_do_not_depend_on_the_block_sizes(asphere_psfs, monkeypatch, mod, name, size, exact):
    """The PSFs with another block size (small ones: many loops; the accelerator's: one block) equal the default's
    bit for bit (the trace and the edge envelope are elementwise), the band convolution's to rounding."""
    hl, ref = asphere_psfs
    monkeypatch.setattr(mod, name, size)
    with torch.no_grad():
        got = hl.psf_result(FIELDS, [0.53], ks=32).psf
    if exact:
        assert torch.equal(got, ref)
    else:
        rel = (got - ref).abs().sum((-2, -1)) / ref.abs().sum((-2, -1))
        assert float(rel.max()) < 1e-14


def test_pixel_weights_built_once_are_those_built_per_call():
    g = torch.Generator().manual_seed(1)
    u = torch.randn((3, 41, 41), dtype=torch.complex128, generator=g)
    args = (4, 2e-3, (-0.05, -0.05), 3e-3, (0.0, 0.0), (16, 16))
    direct = integrated_upsampled_intensity(u, *args, refine=True)
    w = upsampled_pixel_weights(u.shape[-2:], *args, device=u.device, refine=True)
    assert torch.equal(integrated_upsampled_intensity(u, *args, refine=True, weights=w), direct)
    memo = GeometryMemo()
    calls = []
    for _ in range(2):
        got = memo.cached(("k", 1), lambda: calls.append(1) or w)
        assert got is w
    assert len(calls) == 1 and len(memo) == 1


def test_transfer_per_source_on_a_cpu_equals_the_union_evaluation(monkeypatch):
    """A CPU evaluates each source's transfer function on its own band and roll-off lines and places it into the
    batch's union (an accelerator evaluates the union at once): the same tensor bit for bit, with and without the
    roll-off weights' derivatives, for sources whose carriers, windows and bands differ (mirror images, a shifted
    window, another size)."""
    import raywave.wave.propagation.batch as batch_mod
    from raywave.wave.propagation.batch import WindowBatch, batch_transfer
    from raywave.wave.propagation.transfer import WindowSource

    assert batch_mod._by_source("cpu", 4) and batch_mod._by_source("cpu", 1)
    assert not batch_mod._by_source(torch.device("cuda", 0), 4)
    p, z = 1e-3, 4.0
    sources = tuple(WindowSource(shape, (x0, y0), (x0 + dx, y0 + dy), 0.53, z, 1.0, carrier)
                    for shape, (x0, y0), (dx, dy), carrier in (
                        ((180, 150), (-0.30, -0.10), (0.02, 0.01), (0.08, 0.03)),
                        ((180, 150), (0.15, -0.10), (-0.02, 0.01), (-0.08, 0.03)),
                        ((170, 160), (-0.05, 0.12), (0.0, -0.03), (0.0, -0.05))))
    wb = WindowBatch(sources, (41, 41), p)
    for wd in (False, True):
        monkeypatch.setattr(batch_mod, "_by_source", lambda device, b: False)
        union = batch_transfer(wb, "cpu", wd)
        monkeypatch.setattr(batch_mod, "_by_source", lambda device, b: b > 1)
        real_empty = torch.empty
        # uninitialised memory filled with NaN: any entry of the union neither written nor zeroed would show
        monkeypatch.setattr(torch, "empty", lambda *a, **k: real_empty(*a, **k).fill_(float("nan")))
        own = batch_transfer(wb, "cpu", wd)
        assert own.band is None and own.count == 3  # each source's own band, placed on demand
        placed = own.placed()
        monkeypatch.setattr(torch, "empty", real_empty)
        assert torch.equal(union.rows, placed.rows) and torch.equal(union.cols, placed.cols)
        assert torch.equal(union.band, placed.band)
        assert (union.rel is None and placed.rel is None) or torch.equal(union.rel.dense(union.band != 0), placed.rel)
        # every source has light on the band, and some of the union lies outside each source's own band
        assert all(bool((b != 0).any()) and bool((b == 0).any()) for b in placed.band)
        # an accelerator's plan: the band's lines from host arithmetic, the roll-off on every line without the
        # weights' derivatives: the same tensor bit for bit
        monkeypatch.setattr(batch_mod.devices, "accelerator", lambda x: True)
        accel = batch_transfer(wb, "cpu", wd)
        monkeypatch.undo()
        assert torch.equal(union.rows, accel.rows) and torch.equal(union.cols, accel.cols)
        assert torch.equal(union.band, accel.band)
        assert (union.rel is None and accel.rel is None) or torch.equal(union.rel.dense(), accel.rel.dense())


def test_the_accelerator_plan_forced_on_a_cpu_keeps_the_psfs(asphere_psfs, monkeypatch):
    """One switch (:func:`raywave.utils.devices.accelerator`) picks every accelerator-plan choice (block sizes, whole
    batches, dense interpolation, the union transfer, shared FFT sizes): forced on the CPU (how
    ``benchmarks/ops_breakdown.py --accelerator`` counts a GPU's ops) the PSFs stay within the shared FFT sizes'
    1e-7 (measured ≤ 3e-8 on the 10×10×3 map), and the CPU's own plan is the default."""
    import raywave.utils.devices as devices

    assert not devices.accelerator("cpu") and not devices.accelerator(None) and devices.accelerator("meta")
    assert not devices.accelerator(torch.zeros(1)) and devices.accelerator(torch.device("cuda", 0))
    hl, ref = asphere_psfs
    monkeypatch.setattr(devices, "accelerator", lambda x: True)
    with torch.no_grad():
        got = hl.psf_result(FIELDS, [0.53], ks=32).psf
    rel = (got - ref).abs().sum((-2, -1)) / ref.abs().sum((-2, -1))
    assert float(rel.max()) < 1e-7


@pytest.mark.parametrize("refine", [False, True])
def test_planned_pixel_integration_equals_the_cpu_plan(refine):
    """An accelerator's pixel integration (:func:`~raywave.wave.propagation.resample.integrated_intensity_planned`:
    the weights, window and ramps laid out once per geometry, both weight sets from two batched products) equals
    :func:`integrated_upsampled_intensity` to rounding, with its gradient; with ``refine`` for PSFs that do and do
    not take the refined integral."""
    from raywave.wave.propagation.resample import integrated_intensity_planned, pixel_plan

    g = torch.Generator().manual_seed(2)
    ny = nx = 41
    yy, xx = torch.meshgrid(torch.arange(ny) - 20.0, torch.arange(nx) - 20.0, indexing="ij")
    sharp = torch.exp(-(xx**2 + yy**2) / 2.0).to(torch.complex128)  # a PSF as sharp as the grid: refined
    u = torch.stack([torch.randn((ny, nx), dtype=torch.complex128, generator=g), sharp,
                     torch.exp(-(xx**2 + yy**2) / 60.0).to(torch.complex128)]).requires_grad_()
    window = 1.0 - 0.01 * torch.rand((ny, nx), dtype=torch.float64, generator=g)
    args = (4, 2e-3, (-0.04, -0.04), 3e-3, (0.0, 0.0), (12, 12))
    want = integrated_upsampled_intensity(u, *args, window, refine=refine)
    if refine:  # the sharp PSF takes the refined integral, the smooth one not
        plain = integrated_upsampled_intensity(u, *args, window)
        assert not torch.equal(want[1], plain[1]) and torch.equal(want[2], plain[2])
    plan = pixel_plan(upsampled_pixel_weights(u.shape[-2:], *args, device=u.device, refine=refine), window, u.dtype)
    got = integrated_intensity_planned(u, plan)
    assert got.shape == want.shape and plan.sets == (2 if refine else 1)
    assert float((got - want).detach().abs().max()) <= 1e-13 * float(want.detach().abs().max())
    wt = torch.rand(want.shape, dtype=torch.float64, generator=g)
    (gw,) = torch.autograd.grad((want * wt).sum(), u)
    (gg,) = torch.autograd.grad((got * wt).sum(), u)
    assert float((gg - gw).abs().max()) <= 1e-12 * float(gw.abs().max())
