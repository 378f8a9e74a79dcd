"""Steps 2–4 of the engine for many sources at once (issue 43): the DOE's phase, the propagation to the sensor and
the pixel integration of a group of DOE-plane fields as batched tensor operations.

The sources of a call are grouped (:func:`plan_groups`): one group per wavelength, medium, distance, mode and
the FFT size each source needs on its own (with :data:`COMMON_FFT`: not the FFT size, each batch on the largest its
members need), cut into batches whose FFT-grid arrays stay within :data:`BATCH_BYTES`.
Every discrete choice (the padded window shape, the FFT size, the band's rows and columns, the output window) is
made once per batch on the host from the sources' geometry (host floats that the fields carry), so the hot path
has no per-PSF device→host round trip. A batch then runs (:func:`propagate_group`):

1. the envelopes zero-padded to a common window ``(B, Ny, Nx)`` (each keeps its origin: padding is at the end);
2. the DOE's ``exp(iφ)`` of every window from one phase evaluation (:meth:`raywave.doe.DOE.window_phasors`);
3. one windowed angular-spectrum propagation (:func:`raywave.wave.propagation.batch.propagate_batch`): a common
   FFT size, each source with its own band limit, carrier and output window on the lattice through its chief
   ray's image point; with autograd, the zero-valued ``dz`` (sensor distance) and window shifts (the crop following
   the chief ray) carry their first-order derivatives as in :func:`~raywave.wave.propagate_window`;
4. ``|U|²`` Fourier-upsampled and integrated over the sensor pixels with one set of weights (every output window
   sits at the same offset from its crop), normalised per PSF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from raywave.doe.base import has_zero_phase
from raywave.utils import devices
from raywave.utils.safe import safe_div
from raywave.wave.propagation import integrated_upsampled_intensity, upsampled_pixel_weights
from raywave.wave.propagation.resample import integrated_intensity_planned, pixel_plan
from raywave.wave.propagation.batch import WindowBatch, WindowSource, batch_transfer, propagate_batch
from raywave.wave.propagation.transfer import _geometry
from raywave.hybrid.coherent.record import EnvelopeRow

#: a batch holds at most this many bytes of FFT-grid arrays (B × (Ny + n) × (Nx + n) complex samples): it bounds the
#: batched intermediates (the band spectra, the transfer functions), i.e. the peak memory of one batch
BATCH_BYTES = 2**28
#: :data:`BATCH_BYTES` on an accelerator (CUDA: every op a kernel launch, memory aplenty), where the sources of a
#: group also share one FFT size (:func:`plan_groups`): a 10×10×3 map of the bundled asphere's 3000² DOE runs in a few
#: batches instead of ~100
BATCH_BYTES_ACCELERATOR = 2**32
#: samples of simulation pitch around the PSF window (keeps the periodic upsampling's edge effects out of it)
OUT_MARGIN = 8


@dataclass(frozen=True)
class SensorWindow:
    """The sensor side of a call: ``ks`` × ``ks`` pixels of ``pitch`` mm, the intensity upsampling ``q``."""

    ks: int
    pitch: float
    q: int


@dataclass(frozen=True)
class Planned:
    """One source of a batch: its index in the call, its DOE-plane field (:class:`~raywave.hybrid.coherent.DOEField`)
    and the chief ray's image point ``(x, y)`` mm on the sensor (host floats)."""

    index: int
    fd: object
    center: tuple[float, float]


#: a window's sample count is the ``ceil`` of a span in samples that is often an exact integer (ks sensor pixels of a
#: whole number of simulation samples): spans within this many samples above an integer count as that integer, so that
#: the rounding of the chief ray's position (~1e-13 mm) cannot add a sample (issue 46: a window one sample wider moved a
#: grating's PSF by 1.1e-5)
SPAN_ROUNDING = 1e-9


def ceil_samples(span: float) -> int:
    """``ceil(span)`` of a span in samples, robust to its last bits (:data:`SPAN_ROUNDING`)."""
    return math.ceil(span - SPAN_ROUNDING)


def out_half_width(sensor: SensorWindow, p: float, center: tuple[float, float]) -> int:
    """``kk``: the output window on the simulation pitch ``p`` mm is ``2·kk + 1`` samples about the chief ray's image
    point ``center``, covering the ks × ks sensor pixels plus :data:`OUT_MARGIN` samples (the engine's
    single-source rule, :meth:`raywave.hybrid.HybridLens.propagate`)."""
    ks, ps = sensor.ks, sensor.pitch
    span = ks * ps / p
    if not (math.isfinite(span) and span < 2**31):
        raise ValueError(f"the {ks}×{ks} PSF crop of {ps:g} mm sensor pixels spans {span:g} simulation samples of "
                         f"{p:g} mm: not a usable window (check the sensor pitch and the DOE pitch)")
    m = OUT_MARGIN
    xc = center[0]
    lo_x = xc - (ks // 2) * ps - 0.5 * ps - m * p
    n_out = ceil_samples(span) + 2 + 2 * m
    return max(ceil_samples((xc - lo_x) / p), ceil_samples((lo_x + n_out * p - xc) / p))


def _own_geometry(pl: Planned, n_out: int, kk: int):
    """The window geometry (:func:`~raywave.wave.propagation.transfer._geometry`, host math) of the source ``pl``
    on its own, for an output window of ``n_out`` samples whose centre sample lies on its chief ray's image point."""
    fd = pl.fd
    p = fd.pitch
    out = (pl.center[0] - kk * p, pl.center[1] - kk * p)
    src = WindowSource(fd.grid.shape, fd.origin, out, fd.wavelength, float(fd.z), fd.n, fd.carrier)
    return _geometry(src, (n_out, n_out), p, 0.5, 2.0)


def _fft_size(pl: Planned, n_out: int, kk: int) -> tuple[int, int]:
    """The FFT size ``(My, Mx)`` that the source ``pl`` needs on its own (:func:`window_transfer`'s, host math) for
    an output window of ``n_out`` samples whose centre sample lies on its chief ray's image point."""
    return _own_geometry(pl, n_out, kk).size


def _edge_in_band(m: int, pitch: float, k: float, offset: float, zf: float, band) -> bool:
    """Whether the transfer function's band (``band`` = (lo, hi, roll-off) of the lateral shift Δ, mm) reaches the
    highest positive or negative frequency of an ``m``-point FFT grid of ``pitch`` mm (host math of
    :func:`~raywave.wave.propagation.batch._union_candidates`; ``offset`` the carrier's frequency k·α)."""
    lo, hi, taper = band
    for f in ((m + 1) // 2 - 1) / (m * pitch), -(m // 2) / (m * pitch):
        g = f + offset
        q = k * k - g * g
        if q <= 0:
            continue  # evanescent: never in the band
        s1 = zf * g / math.sqrt(q)
        if s1 > 0 and s1 <= hi + taper or s1 < 0 and s1 >= lo - taper or s1 == 0 and lo - taper <= 0 <= hi + taper:
            return True
    return False


#: sources whose beam the DOE's aperture blocks by more than this fraction keep their own FFT size on an accelerator:
#: their PSF is mostly the aperture edge's diffraction, whose spectrum fills the band's roll-off (on the bundled
#: asphere's 10×10×3 map a shared size moved those by up to 1.7e-6 relative L1, beams blocked by ≤ 50 % by ≤ 3.0e-8,
#: unblocked ones by ≤ 1.0e-10: benchmarks/results/accelerator_plan_accuracy_2026-11-30_xvi.json)
SHARED_FFT_MAX_CLIPPED = 0.5


def _resolved(pl: Planned, n_out: int, kk: int) -> bool:
    """Whether the source may share a larger FFT size: its band stays inside its own FFT grid on both axes (its
    spectrum is resolved: a larger grid moves its PSF only by the kernel's tails, ≤ 6.4e-9 relative L1; see
    :data:`COMMON_FFT`) and the DOE's aperture blocks at most :data:`SHARED_FFT_MAX_CLIPPED` of its beam. A band
    that reaches the grid's highest frequencies (a field the pitch does not resolve: its PSF moves by up to 1e-2 with
    the FFT size) or a beam mostly blocked keeps its own size."""
    if float(getattr(pl.fd.info, "clipped", 0.0)) > SHARED_FFT_MAX_CLIPPED:
        return False
    g = _own_geometry(pl, n_out, kk)
    (my, mx), (px, py) = g.size, g.pitch
    return not (_edge_in_band(mx, px, g.k, g.k * g.carrier[0], g.zf, g.bx)
                or _edge_in_band(my, py, g.k, g.k * g.carrier[1], g.zf, g.by))


#: one FFT size per group (issue 43): the sources of a wavelength, medium, distance, pitch and mode share batches
#: (cut at :data:`BATCH_BYTES`), each batch on the largest FFT size any of its members needs, instead of one group per
#: own FFT size. A larger FFT grid than a source's own changes its PSF only by the rolled-off kernel's tails, which wrap
#: around at the own size (benchmarks/fft_size_convergence.py, benchmarks/results/
#: fft_size_convergence_2026-11-29_xv_h43f.json): ≤ 6.4e-9 relative L1 on the four real lenses and the bundled asphere
#: (their errors against converged references, 6e-5 … 8e-4, move by ≤ 2.2e-9), ≤ 1.5e-7 on the hybrid_asphere 6×6×3
#: map (its corner beams clipped by the DOE's edge). Fields the grid does not resolve (a SamplingWarning) move by up to
#: 1e-2: there the band covers the whole FFT grid, and their PSFs are wrong by far more anyway. Off by default: main's
#: PSFs bit for bit; on, the 6×6×3 map runs 18 batches instead of 22 at 1.11× the CPU time per PSF (larger FFTs), and
#: the 10×10×3 map dispatches 528 ops per PSF instead of 557; the pins of tests/pin_cases.py would move (≤ 9.4e-8; the
#: Cooke triplet on its unresolved 4 µm grid 2.0e-3) and need regenerating.
COMMON_FFT = False


def _accelerator(planned: list[Planned]) -> bool:
    """Whether the sources' fields live on an accelerator (not the CPU)."""
    return bool(planned) and devices.accelerator(_device(planned[0].fd))


def _device(fd) -> torch.device:
    """The device of a DOE-plane field's envelope (a deferred one's without making it: ``DOEField.device``)."""
    dev = getattr(fd, "device", None)
    return fd.envelope.device if dev is None else dev


def accelerator_cap(device) -> int:
    """:data:`BATCH_BYTES_ACCELERATOR`, at most a 32nd of a CUDA device's memory (a batch's intermediates are
    several times its FFT-grid arrays)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return BATCH_BYTES_ACCELERATOR
    return max(BATCH_BYTES, min(BATCH_BYTES_ACCELERATOR, torch.cuda.get_device_properties(dev).total_memory // 32))


def plan_groups(planned: list[Planned], sensor: SensorWindow, element_size: int) -> list[list[Planned]]:
    """The batches of ``planned`` (lattice-path sources with light): grouped by wavelength, medium index, distance,
    pitch, whether the sensor distance is differentiated (``chief_tan``) and (unless :data:`COMMON_FFT`) the FFT size
    each source needs on its own, so that every PSF is the one-source path's to rounding; each group cut where a batch
    would pass :data:`BATCH_BYTES` (``element_size`` bytes per complex sample of the FFT grid). (A larger FFT grid
    than a source's own moves a resolved source's PSF by ≤ 6.4e-9 relative L1, ≤ 1.5e-7 for a beam clipped by the
    DOE's edge: :data:`COMMON_FFT`.) With :data:`COMMON_FFT` a group's sources are sorted by their own FFT area
    (largest first) and cut greedily: each batch runs on the largest size per axis that its members need.

    On an accelerator the resolved sources (:func:`_resolved`) always share FFT sizes this way, in batches of up to
    :data:`BATCH_BYTES_ACCELERATOR` (each batch is a few hundred kernel launches whatever its size); the others keep
    their own size. Its PSFs then differ from the CPU's by the FFT size's ≤ 3.0e-8 relative L1 (the bundled asphere's
    10×10×3 map, benchmarks/accelerator_plan_accuracy.py)."""
    accel = _accelerator(planned)
    cap = accelerator_cap(_device(planned[0].fd)) if accel else BATCH_BYTES
    by_wave: dict = {}
    for pl in planned:
        fd = pl.fd
        by_wave.setdefault((fd.wavelength, fd.n, float(fd.z), fd.pitch, fd.chief_tan is not None), []).append(pl)
    batches = []
    for key in sorted(by_wave, key=str):
        members = by_wave[key]
        kk = max(out_half_width(sensor, key[3], pl.center) for pl in members)
        if COMMON_FFT:
            batches.extend(_common_batches(members, kk, element_size, cap))
            continue
        if accel:
            resolved = [_resolved(pl, 2 * kk + 1, kk) for pl in members]
            batches.extend(_common_batches([pl for pl, r in zip(members, resolved) if r], kk, element_size, cap))
            members = [pl for pl, r in zip(members, resolved) if not r]
        groups: dict = {}
        for pl in members:
            groups.setdefault(_fft_size(pl, 2 * kk + 1, kk), []).append(pl)
        for (my, mx), group in sorted(groups.items()):
            per = max(1, cap // (my * mx * element_size))
            for i in range(0, len(group), per):
                part = group[i:i + per]
                batches.extend([part] if accel else _stack_cut(part))
    return batches


#: on a CPU a batch's zero-padded input stack (:func:`modulated_batch`, complex128) holds at most this many bytes
#: (each batch at least one source): glibc maps an array of 32 MiB or more (its largest mmap threshold) fresh from the
#: kernel on every allocation, page-faults it in and unmaps it on release, ~1.5 µs per 4 KiB page. The default stop
#: edge's windows (~1 M samples on the bundled asphere's map, 16 MB each) made 4–9-source stacks of 64–140 MB: ~8 ms
#: per PSF of faults, zero-fill and unmapping (issue 47). A CPU convolves the batch field by field anyway
#: (:func:`~raywave.wave.propagation.band.per_field`), so smaller batches give the same PSFs bit for bit.
STACK_BYTES = 2**25 - 2**20


def _stack_cut(group: list[Planned]) -> list[list[Planned]]:
    """``group`` (one FFT size, in order) cut into consecutive batches whose padded input stack (the count × each
    axis's largest window, complex128) stays within :data:`STACK_BYTES`."""
    return _cut_by_bytes([(pl.fd.grid.shape, pl) for pl in group], 16, STACK_BYTES)


def _cut_by_bytes(sized: list, element_size: int, cap: int) -> list[list[Planned]]:
    """``sized`` (``[((ny, nx), planned)]``, in order) cut into consecutive batches whose stack on each axis's
    largest size, ``count · ny · nx · element_size`` bytes, stays within ``cap`` (each batch at least one)."""
    batches, cur, (my, mx) = [], [], (0, 0)
    for (sy, sx), pl in sized:
        ny, nx = max(my, sy), max(mx, sx)
        if cur and (len(cur) + 1) * ny * nx * element_size > cap:
            batches.append(cur)
            cur, ny, nx = [], sy, sx
        cur.append(pl)
        my, mx = ny, nx
    if cur:
        batches.append(cur)
    return batches


def _common_batches(members: list[Planned], kk: int, element_size: int, cap: int) -> list[list[Planned]]:
    """:data:`COMMON_FFT`'s batches of one group (output half-width ``kk``): the members by own FFT size, largest
    first (a stable sort: ties keep the call's order), cut where a batch on the FFT size its members need (each
    axis's largest) would pass ``cap`` bytes."""
    sized = sorted(((_fft_size(pl, 2 * kk + 1, kk), pl) for pl in members), key=lambda t: -t[0][0] * t[0][1])
    return _cut_by_bytes(sized, element_size, cap)


def window_batch(batch: list[Planned], sensor: SensorWindow) -> tuple[WindowBatch, int]:
    """The :class:`~raywave.wave.propagation.batch.WindowBatch` of a batch (each source's own input window, its
    output window on the lattice through its chief ray's image point: a symmetric PSF stays symmetric) and the
    output half-width ``kk`` common to the batch."""
    p = batch[0].fd.pitch
    kk = max(out_half_width(sensor, p, pl.center) for pl in batch)
    sources = tuple(WindowSource(pl.fd.grid.shape, pl.fd.origin, (pl.center[0] - kk * p, pl.center[1] - kk * p),
                                 pl.fd.wavelength, float(pl.fd.z), pl.fd.n, pl.fd.carrier) for pl in batch)
    return WindowBatch(sources, (2 * kk + 1, 2 * kk + 1), p), kk


def modulated_batch(doe, batch: list[Planned], shape, oversample: int, dtype, frames: list | None = None):
    """The envelopes of ``batch`` zero-padded to ``shape`` ``(Ny, Nx)`` and multiplied by the DOE's ``exp(iφ)``
    (:meth:`raywave.doe.DOE.window_phasors`), cast to ``dtype``: ``(B, Ny, Nx)``; and each field's power ``(B,)``
    (∫|U|² dA, no autograd: a diagnostic). ``frames`` (:meth:`raywave.hybrid.mirror.FrameBands.frames`): a member
    with flips there is its family's frame: its deferred row read unflipped and its window's phasors flipped."""
    ny, nx = shape
    rows = [getattr(pl.fd, "row", None) for pl in batch]
    if all(r is not None for r in rows) and devices.accelerator(rows[0].base):
        # every envelope a row of a padded batch (the batched field stage's, DOEField.deferred): gathered from those
        # batches, a few ops a batch instead of one a source (and a flip a mirror image), the same values
        env = _gathered_rows(rows, shape)
    elif devices.accelerator(_device(batch[0].fd)):
        # each envelope zero-padded at its end and the batch stacked: one op a source and one for the batch (the copy
        # into slices of a zero-filled array dispatches four a source), the same values
        env = torch.stack([torch.nn.functional.pad(e, (0, nx - e.shape[-1], 0, ny - e.shape[-2]))
                           for e in (pl.fd.envelope for pl in batch)])
    else:
        # (a mirror image's deferred row copied into the stack in reverse: no flipped copy of its own)
        rows = [pl.fd.pending_row for pl in batch]
        if frames is not None:  # (a member in its family's frame: its row as stored)
            rows = [r if f is None or r is None else r.flipped(*f) for r, f in zip(rows, frames)]
        env = padded_stack([r or pl.fd.envelope for r, pl in zip(rows, batch)], shape)
    p = batch[0].fd.pitch
    with torch.no_grad():  # (env detached only where autograd records it: a detach is an op)
        power = torch.linalg.vector_norm(torch.view_as_real(env.detach() if env.requires_grad else env),
                                         dim=(-3, -2, -1)).square() * (p * p)
    if has_zero_phase(doe):  # exp(i·0) = 1: no phase maps, no product
        return env.to(dtype), power
    corners = [(pl.fd.box[0], pl.fd.box[2]) for pl in batch]
    phasors = doe.window_phasors(batch[0].fd.wavelength, corners, shape, oversample).to(env.device)
    for b, f in enumerate(frames or ()):
        dims = [d for d, on in ((-1, f[0]), (-2, f[1])) if on] if f is not None else []
        if dims:  # the member's window in its family's frame
            a, c = batch[b].fd.grid.shape
            phasors[b, :a, :c] = phasors[b, :a, :c].flip(dims)
    if env.requires_grad or phasors.requires_grad:
        return (env * phasors).to(dtype), power
    return env.mul_(phasors).to(dtype), power


def padded_stack(envs: list, shape: tuple) -> torch.Tensor:
    """The envelopes ``envs`` (each ``(ny_i, nx_i)``, or an :class:`EnvelopeRow` not yet made: copied from its batch,
    a flipped one in reverse) zero-padded at their end to ``shape`` ``(Ny, Nx)`` and stacked
    ``(B, Ny, Nx)``: one array with each envelope copied into its corner and only the padding zeroed; with autograd
    :class:`_PaddedStack` (each envelope's gradient a view of the batch's: a slice copy's backward would clone the
    whole batch's gradient per source, B² window-sized arrays). The same values either way."""
    if torch.is_grad_enabled() and any(isinstance(e, torch.Tensor) and e.requires_grad for e in envs):
        return _PaddedStack.apply(tuple(shape), *(e if isinstance(e, torch.Tensor) else e.make() for e in envs))
    return _PaddedStack.values(envs, shape)


class _PaddedStack(torch.autograd.Function):
    """:func:`padded_stack` with autograd: the backward hands each envelope its corner of the batch's gradient."""

    @staticmethod
    def values(envs, shape) -> torch.Tensor:
        """The stack: each envelope copied into its corner and only the rest of its row zeroed (a zero fill of the
        whole batch first wrote its samples twice: issue 43)."""
        e0 = envs[0] if isinstance(envs[0], torch.Tensor) else envs[0].base
        out = torch.empty((len(envs), *shape), dtype=e0.dtype, device=e0.device)
        for i, e in enumerate(envs):
            if isinstance(e, EnvelopeRow):
                a, b = e.shape
                e.copy_into(out[i, :a, :b])
            else:
                a, b = e.shape[-2:]
                out[i, :a, :b].copy_(e)
            out[i, :a, b:].zero_()
            out[i, a:].zero_()
        return out

    @staticmethod
    def forward(ctx, shape, *envs):
        ctx.shapes = [tuple(e.shape[-2:]) for e in envs]
        return _PaddedStack.values(envs, shape)

    @staticmethod
    def backward(ctx, g):
        return (None, *(g[i, :a, :b] for i, (a, b) in enumerate(ctx.shapes)))


def _row_indices(rows: list, shape: tuple) -> tuple:
    """Host index arrays that gather the envelopes ``rows`` (:class:`~raywave.hybrid.coherent.record.EnvelopeRow`
    of one base) zero-padded at their end to ``shape`` ``(Ny, Nx)``: ``(row (K, 1, 1), y (K, Ny, 1), x (K, 1, Nx),
    inside (y (K, Ny, 1), x (K, 1, Nx)) bool)`` numpy arrays (a flipped row's samples in reverse order; beyond an
    envelope index 0 and ``inside`` False)."""
    ny, nx = shape
    ky, kx = np.arange(ny), np.arange(nx)
    ri, ci, ins_y, ins_x = [], [], [], []
    for r in rows:
        a, b = r.shape
        ri.append(np.where(ky < a, (a - 1 - ky) if r.flip[1] else ky, 0))
        ci.append(np.where(kx < b, (b - 1 - kx) if r.flip[0] else kx, 0))
        ins_y.append(ky < a)
        ins_x.append(kx < b)
    return (np.array([r.row for r in rows])[:, None, None], np.stack(ri)[:, :, None], np.stack(ci)[:, None, :],
            (np.stack(ins_y)[:, :, None], np.stack(ins_x)[:, None, :]))


def _gathered_rows(rows: list, shape: tuple) -> torch.Tensor:
    """The envelopes ``rows`` (:class:`~raywave.hybrid.coherent.record.EnvelopeRow`) zero-padded at their end to
    ``shape`` and stacked ``(K, Ny, Nx)``: one gather and one masked fill per base batch (its index arrays built on
    the host; and a concatenation and a reorder for several bases), the values of each envelope's own padded copy."""
    parts = []
    groups = EnvelopeRow.by_base(rows)
    for ks in groups:
        base = rows[ks[0]].base
        dev = base.device
        t, y, x, (in_y, in_x) = _row_indices([rows[k] for k in ks], shape)
        t, y, x, out_y, out_x = (torch.from_numpy(v).to(dev) for v in (t, y, x, ~in_y, ~in_x))
        parts.append(base[t, y, x].masked_fill_(out_y | out_x, 0))  # (a fresh gather: zeroed in place)
    if len(parts) == 1:
        return parts[0]
    order = [k for ks in groups for k in ks]
    back = torch.from_numpy(np.argsort(np.array(order))).to(parts[0].device)
    return torch.cat(parts).index_select(0, back)


def edge_taper(n: int, width: int, device) -> torch.Tensor:
    """Separable raised-cosine taper (n, n): 1 inside, → 0 over the outer ``width`` samples, so that the periodic
    Fourier upsampling sees no jump at the window's edges (the taper lies outside the PSF crop)."""
    w = torch.ones(n, dtype=torch.float64, device=device)
    if width > 0 and n > 2 * width:
        t = 0.5 - 0.5 * torch.cos(math.pi * (torch.arange(width, dtype=torch.float64, device=device) + 0.5) / width)
        w[:width], w[-width:] = t, t.flip(0)
    return w[:, None] * w[None, :]


def sensor_psfs(out: torch.Tensor, kk: int, p: float, sensor: SensorWindow, power: torch.Tensor, memo=None):
    """The PSFs ``(B, ks, ks)`` (each summing to 1; all zeros where no light arrives) and the energy outside the
    crops ``(B,)`` from the sensor-plane fields ``out`` ``(B, 2kk+1, 2kk+1)`` (pitch ``p`` mm, each window's centre
    sample on its chief ray's image point, the centre of pixel ``[ks//2, ks//2]``), ``power`` ``(B,)`` the power
    reaching the DOE. ``memo`` (:class:`GeometryMemo` or None): where the pixel integration's weights and the
    window's taper are kept, built once per geometry (``kk``, ``p``, the sensor; issue 43) instead of per batch."""
    ks, ps = sensor.ks, sensor.pitch
    rel = (ks // 2) * ps - kk * p  # every window's sample (0, 0) relative to its crop's pixel (0, 0) centre
    n = out.shape[-1]

    accel = devices.accelerator(out)

    def build():
        w = upsampled_pixel_weights((out.shape[-2], n), sensor.q, p, (rel, rel), ps, (0.0, 0.0), (ks, ks),
                                    out.device, refine=True)
        taper = edge_taper(n, OUT_MARGIN - 2, out.device)
        # an accelerator: the weights, the taper and the upsampling's constants laid out for few ops (PixelPlan)
        return (pixel_plan(w, taper, out.dtype), None) if accel else (w, taper)

    key = ("pixel_weights", tuple(out.shape[-2:]), kk, float(p), sensor, str(out.device), accel, out.dtype)
    weights, taper = build() if memo is None else memo.cached(key, build)
    if accel:
        crop = integrated_intensity_planned(out, weights)
    else:
        crop = integrated_upsampled_intensity(out, sensor.q, p, (rel, rel), ps, (0.0, 0.0), (ks, ks), taper,
                                              refine=True, weights=weights)
    total3 = crop.sum((-2, -1), keepdim=True)  # (B, 1, 1): one view for the (B,) sums, not four unsqueezes
    total = total3.view(-1)
    power = power.to(torch.float64)
    lit = power > 0
    outside = torch.where(lit, 1.0 - safe_div(total, power, lit), torch.ones_like(total))
    psf = safe_div(crop, total3, total3 > 0)
    return psf, outside


class GeometryMemo:
    """Geometry-keyed constants of the batched path (the pixel integration's weights and taper: built once per
    window shape, pitch and sensor), kept while they take at most ``max_bytes`` together (least recently used
    dropped first). Plain per-engine memo, never state.

    The batch transfer functions are not memoised: a map's batches (and a replay's per-field recomputes) cycle
    through more transfer functions than any fixed budget holds, so a least-recently-used memo of them never hits
    (the replay benchmark's 5×5 map over two iterations: 0 hits in 300) and only raised the peak memory by its size
    (issue 43: 64 MB of the replay's 10×10 peak)."""

    def __init__(self, max_bytes: int = 16 * 2**20):
        from collections import OrderedDict

        self.max_bytes = int(max_bytes)
        self._items: OrderedDict = OrderedDict()

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)

    def cached(self, key, build):
        """The value of ``build()`` for the hashable ``key`` (host values that fix it: a geometry), built once while
        it stays in the memo (values that take more than ``max_bytes`` are not kept)."""
        hit = self._items.get(key)
        if hit is not None:
            self._items.move_to_end(key)
            return hit
        hit = build()
        if _nbytes(hit) <= self.max_bytes:
            self._items[key] = hit
            while sum(_nbytes(v) for v in self._items.values()) > self.max_bytes:
                self._items.popitem(last=False)
        return hit


def _nbytes(v) -> int:
    """Bytes of the tensors in ``v`` (a tensor, or tuples of them)."""
    if isinstance(v, torch.Tensor):
        return v.numel() * v.element_size()
    if isinstance(v, (tuple, list)):
        return sum(_nbytes(x) for x in v)
    if hasattr(v, "__dataclass_fields__"):  # (a PixelPlan)
        return sum(_nbytes(getattr(v, f)) for f in v.__dataclass_fields__)
    return 0


def _doe_records(doe) -> bool:
    """Whether autograd records the DOE's phase (a trainable DOE with gradients on)."""
    return torch.is_grad_enabled() and any(p.requires_grad for p in getattr(doe, "parameters", lambda: ())())


def propagate_group(engine, batch: list[Planned], centers: torch.Tensor, dz, dtype, sensor: SensorWindow,
                    shared=None):
    """Steps 2–4 for one batch (:func:`plan_groups`) of ``engine`` (a :class:`~raywave.hybrid.HybridLens`):
    ``centers`` ``(B, 2)`` mm the chief rays' image points (differentiable: the crops follow them), ``dz`` the
    zero-valued sensor-distance tensor or None, ``dtype`` the propagation's complex dtype, ``sensor`` the PSF
    window; ``shared``: the call's :class:`~raywave.hybrid.mirror.FrameBands` (mirror images propagated in their
    source's frame with its transfer function, evaluated once) or None. Returns the PSFs ``(B, ks, ks)`` and the
    energies outside the crops ``(B,)``."""
    wb, kk = window_batch(batch, sensor)
    shift = centers - centers.detach() if centers.requires_grad else None
    frames = shared.frames(batch) if shared is not None and dz is None and shift is None \
        and not _doe_records(engine.doe) else None
    u, power = modulated_batch(engine.doe, batch, wb.in_shape(), engine.oversample, dtype, frames)
    if frames is not None and u.requires_grad:  # (not expected: the framed rows are a CPU's without autograd)
        raise RuntimeError("propagate_group: a mirror frame with autograd")
    transfer = batch_transfer(wb, u.device, dz is not None or shift is not None)
    if frames is not None:
        transfer = shared.framed(transfer, wb, batch, frames)
    out = propagate_batch(wb.field(u), wb.out_grids(), wb.distances(), transfer=transfer, shift=shift, dz=dz).envelope
    for b, f in enumerate(frames or ()):
        dims = [d for d, on in ((-1, f[0]), (-2, f[1])) if on] if f is not None else []
        if dims:  # back from the family's frame
            out[b] = out[b].flip(dims)
    del u
    return sensor_psfs(out, kk, wb.pitch, sensor, power, engine._geometry_memo)
