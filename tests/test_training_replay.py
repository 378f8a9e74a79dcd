"""Memory-saving replay: on a real ray-wave hybrid lens the replayed gradient equals the full-graph gradient
(float64, to 1e-10), randomness is replayed exactly, a non-replayable chunk is caught, and the autograd memory
of the replay does not grow with the number of PSFs while the full graph's does."""

import warnings

import pytest
import torch

from raywave.doe import PixelDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import ideal_lens
from raywave.training.replay import OpticsStep, ReplayMismatchError, chunk_ranges

KS = 16
CHOICES = torch.tensor([[0.62, 0.66, 0.70], [0.50, 0.53, 0.56], [0.45, 0.47, 0.49]], dtype=torch.float64)


def small_hybrid(seed=0, stop_edge="doe"):
    """f = 2 mm ideal lens at F/8, 128² random-phase pixel DOE (2 µm) 0.5 mm behind it: PSFs in ~10 ms."""
    lens = ideal_lens(2.0, f_number=8.0, wavelengths=(0.55,))
    phase = 0.5 * torch.randn(128, 128, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return HybridLens(lens, PixelDOE(phase, 2e-3), 0.5, sensor_pitch=2e-3, stop_edge=stop_edge)


def field_grid(n):
    """n×n field angles (deg) over ±3°, row-major, (n*n, 2)."""
    t = torch.linspace(-3.0, 3.0, n, dtype=torch.float64)
    return torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2).flip(-1)


def one_wavelength_per_channel(g):
    return CHOICES[torch.arange(3), torch.randint(0, 3, (3,), generator=g)]


def make_step(hl, n, per_chunk, generator):
    fields = field_grid(n)
    ranges = chunk_ranges(len(fields), per_chunk)

    def compute(ctx):
        # PSFs of the chunk's fields at the step's three wavelengths: (Fk, 3, ks, ks); the centre (Fk, 3, 2)
        res = hl.psf_result(fields[list(ranges[ctx.index])], ctx.draws, ks=KS, rays=20)
        return res.psf, res.center

    return OpticsStep.draw(compute, len(ranges), one_wavelength_per_channel, generator)


def fft_conv(img, psf):
    """Circular convolution of img (..., H, W) with a centred psf (..., k, k) (k ≤ H, W)."""
    H, W = img.shape[-2:]
    k = psf.shape[-1]
    pad = torch.zeros(*psf.shape[:-2], H, W, dtype=psf.dtype, device=psf.device)
    pad[..., :k, :k] = psf
    pad = torch.roll(pad, (-(k // 2), -(k // 2)), (-2, -1))
    return torch.fft.irfft2(torch.fft.rfft2(img) * torch.fft.rfft2(pad), s=(H, W))


def render_and_loss(psf, center, patches, target, weight):
    """Patch-wise blur (patch f with PSF f, channel c with wavelength c), a small non-linear 'network', a loss
    that also sees the PSF centres (distortion)."""
    blurred = fft_conv(patches, psf)  # (F, 3, H, W)
    out = torch.nn.functional.conv2d(torch.tanh(2 * blurred), weight, padding=1)
    return (out - target).square().mean() + 1e3 * center.square().mean()


def params(hl):
    return [hl.doe.phase_map, hl.lens.surfaces[0].thickness, hl.lens.surfaces[0].interaction.focal_length]


def grads(hl):
    return [p.grad.clone() for p in params(hl)]


@pytest.fixture(scope="module")
def data():
    g = torch.Generator().manual_seed(1)
    patches = torch.rand(9, 3, 24, 24, dtype=torch.float64, generator=g)
    target = torch.rand(9, 3, 24, 24, dtype=torch.float64, generator=g)
    weight = 0.3 * torch.randn(3, 3, 3, 3, dtype=torch.float64, generator=g)
    return patches, target, weight


@pytest.mark.parametrize("stop_edge", ["doe", pytest.param("exit_pupil", marks=pytest.mark.slow)])
def test_replayed_gradient_equals_full_graph_gradient(data, stop_edge, device):
    """Also with the stop's edge at the exit pupil (the field built on the exit-pupil plane and propagated to the
    DOE plane by the angular spectrum; ~10 s, slow), and on every device (the lens on the GPU; the field angles
    and the drawn wavelengths stay CPU tensors, as a user passes them)."""
    patches, target, weight = (t.to(device) for t in data)
    hl = small_hybrid(stop_edge=stop_edge).to(device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # reference: the full autograd graph
        step = make_step(hl, 3, 2, torch.Generator().manual_seed(7))
        psf, center = step.full_graph()
        render_and_loss(psf, center, patches, target, weight).backward()
        full = grads(hl)
        hl.zero_grad(set_to_none=True)
        # replay: same generator seed → same draws
        step = make_step(hl, 3, 2, torch.Generator().manual_seed(7))
        psf_leaf, center_leaf = step.leaves()
        assert not psf_leaf.grad_fn and psf_leaf.requires_grad and psf_leaf.shape == (9, 3, KS, KS)
        render_and_loss(psf_leaf, center_leaf, patches, target, weight).backward()
        step.backward()
        rep = grads(hl)
    # HybridLens places the sensor at a fixed (detached) z, so the thickness gradient is 0 in both paths
    assert float(full[0].abs().max()) > 0 and float(full[2].abs().max()) > 0
    for name, a, b in zip(("doe", "thickness", "focal length"), full, rep):
        scale = float(a.abs().max())
        err = float((a - b).abs().max())
        print(f"{name}: max |grad| {scale:.3e}, replay − full {err:.2e} (relative {err / max(scale, 1e-300):.2e})")
        assert err <= 1e-10 * max(scale, 1e-300)
    assert step.draws.shape == (3,) and all(float(w) in CHOICES[c].tolist() for c, w in enumerate(step.draws))


def test_draws_come_from_the_generator_and_chunks_get_private_streams():
    seen = []

    def compute(ctx):
        x = torch.rand(2, generator=ctx.generator, dtype=torch.float64)
        seen.append((ctx.index, x.clone()))
        return x

    a = OpticsStep.draw(compute, 3, lambda g: torch.randint(0, 9, (3,), generator=g), torch.Generator().manual_seed(4))
    b = OpticsStep.draw(compute, 3, lambda g: torch.randint(0, 9, (3,), generator=g), torch.Generator().manual_seed(4))
    assert torch.equal(a.draws, b.draws) and a.seed == b.seed
    va = a.forward()[0]
    assert va.shape == (6,)
    # replaying chunks in reverse order gives the same values
    assert torch.equal(torch.cat([a._chunk(k)[0] for k in reversed(range(3))]),
                       torch.cat([va[4:6], va[2:4], va[0:2]]))
    assert len({tuple(x.tolist()) for _, x in seen}) == 3  # chunks have different streams


def test_a_chunk_using_the_global_rng_is_caught():
    p = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    step = OpticsStep(lambda ctx: p + torch.rand(4, dtype=torch.float64), 1)
    (leaf,) = step.leaves()
    leaf.sum().backward()
    with pytest.raises(ReplayMismatchError, match="global RNG"):
        step.backward()


def test_backward_without_gradients_is_an_error():
    step = OpticsStep(lambda ctx: torch.zeros(2), 1)
    with pytest.raises(RuntimeError, match="loss.backward"):
        step.backward()


# ------------------------------------------------------------------ memory
class SavedBytes:
    """Live and peak bytes of tensors saved for backward (autograd's memory), via saved-tensor hooks."""

    def __init__(self):
        self.live = self.peak = 0

    def __enter__(self):
        counter = self

        class Box:
            def __init__(self, t):
                # detached alias (same storage): holding t itself would make a saved output reference its own
                # grad_fn, a cycle that keeps never-backpropagated graph fragments alive
                self.t, self.n = t.detach(), t.numel() * t.element_size()
                counter.live += self.n
                counter.peak = max(counter.peak, counter.live)

            def __del__(self):
                counter.live -= self.n

        self._hooks = torch.autograd.graph.saved_tensors_hooks(Box, lambda box: box.t)
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc):
        self._hooks.__exit__(*exc)


def _peak_graph_bytes(n, replay):
    hl = small_hybrid()
    g = torch.Generator().manual_seed(0)
    patches = torch.rand(n * n, 3, 24, 24, dtype=torch.float64, generator=g)
    target = torch.rand(n * n, 3, 24, 24, dtype=torch.float64, generator=g)
    weight = 0.3 * torch.randn(3, 3, 3, 3, dtype=torch.float64, generator=g)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        step = make_step(hl, n, 1, torch.Generator().manual_seed(7))
        step.forward()  # the no-grad forward is not measured: it saves nothing
        if replay:
            with SavedBytes() as mem_render:
                psf, center = step.leaves()
                render_and_loss(psf, center, patches, target, weight).backward()
            with SavedBytes() as mem_optics:
                step.backward()
            return mem_optics.peak, mem_render.peak
        with SavedBytes() as mem:
            psf, center = step.full_graph()
            render_and_loss(psf, center, patches, target, weight).backward()
        return mem.peak, None


@pytest.mark.slow  # CI time (README: Slow suite)
def test_replay_autograd_memory_does_not_grow_with_the_number_of_psfs():
    """Optics part of the peak autograd memory (bytes saved for backward): with replay it is one PSF's graph,
    the same for 2×2 and 4×4 maps; the full graph grows ~4× from 4 to 16 PSFs."""
    rep2, render2 = _peak_graph_bytes(2, True)
    rep4, render4 = _peak_graph_bytes(4, True)
    full2, _ = _peak_graph_bytes(2, False)
    full4, _ = _peak_graph_bytes(4, False)
    print(f"peak bytes saved for backward: replay of the optics 2x2 {rep2 / 1e6:.2f} MB, 4x4 {rep4 / 1e6:.2f} MB "
          f"(render+loss {render2 / 1e6:.2f} / {render4 / 1e6:.2f} MB); full graph 2x2 {full2 / 1e6:.2f} MB, "
          f"4x4 {full4 / 1e6:.2f} MB")
    assert rep4 <= 1.05 * rep2  # one chunk's graph whatever the number of chunks
    assert full4 > 3 * full2
    assert rep4 + render4 < 0.25 * full4


def test_auto_chunk_takes_a_quarter_of_the_accelerators_free_memory(monkeypatch):
    """``optics.chunk: auto``: on a CPU 4 field points (at most the map's); on a GPU as many as a quarter of its free
    memory holds at REPLAY_BYTES_PER_DOE_SAMPLE per DOE sample and source (mem_get_info stubbed: no GPU needed)."""
    import raywave.training.replay as replay

    assert replay.auto_chunk(100, 3, 9_000_000, "cpu") == replay.CPU_AUTO_CHUNK == 4
    assert replay.auto_chunk(2, 3, 9_000_000, "cpu") == 2
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (130e9, 141e9))
    per_point = 3 * 9_000_000 * replay.REPLAY_BYTES_PER_DOE_SAMPLE
    assert replay.auto_chunk(1000, 3, 9_000_000, "cuda") == int(0.25 * 130e9 // per_point) == 150
    assert replay.auto_chunk(100, 3, 9_000_000, "cuda") == 100  # the whole map in one chunk
    assert replay.auto_chunk(1000, 3, 9_000_000, "cuda", traced=True) == int(
        0.25 * 130e9 // (3 * 9_000_000 * replay.REPLAY_BYTES_PER_DOE_SAMPLE_TRACED))  # the lens traced: a larger graph
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (1e6, 141e9))
    assert replay.auto_chunk(100, 3, 9_000_000, "cuda") == 1  # never less than one field point
    assert replay.auto_chunk(100, 3, 0, "cuda") == 4  # no DOE grid to size it by: the CPU's choice


def test_the_chunk_setting_takes_a_count_or_auto(tmp_path):
    """The config accepts ``chunk: auto`` or an integer ≥ 1, and names the setting when it gets anything else."""
    from raywave.training.config import ConfigError, load_config

    for value, ok in (("auto", True), (3, True), (0, False), ("big", False)):
        p = tmp_path / "c.yaml"
        p.write_text(f"name: t\noptics:\n  chunk: {value}\n")
        if ok:
            assert load_config(p).optics.chunk == value
        else:
            with pytest.raises(ConfigError, match="chunk"):
                load_config(p)
