"""Mirror symmetry of the DOE-plane field. A lens whose every surface, aperture and interaction is symmetric under
x → −x (every rotationally symmetric lens, toroids, centred obscurations, folds in the y–z plane), with a DOE grid
centred on the axis, sends the source (−x, y) exactly the mirror image of the field that (x, y) sends; likewise for
y → −y. :meth:`HybridLens.doe_fields` builds each set of mirror images once: the field of (±x, ±y) is the field of
(x, y) flipped, with its carrier and chief-ray point mirrored (:func:`mirror_field`). The DOE's phase is not part of
the DOE-plane field (it is applied in the propagation), so any DOE, a trained pixel map too, keeps the symmetry of
the field stage; the propagation runs for every PSF, a mirror image's in its source's frame with the source's
transfer function, evaluated once a family (:class:`FrameBands`, issue 47).

The mirrored field equals the one built for the mirrored source itself to the rounding of the construction (its
rays are aimed at their nodes to 1e-10 mm, by paths that are not mirror images): the PSFs of the bundled asphere's
10×10×3 map within 2.1e-13 (DOE-plane edge) and 6.5e-13 (exit-pupil edge), the Cooke triplet's and the double
Gauss's 6×6×3 maps within 1.1e-12 and 3.3e-12 (tests/test_hybrid_mirror.py)."""

from __future__ import annotations

import torch

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation.batch import BatchTransfer, OwnBand, WindowSource
from raywave.wave.propagation.kernels import BandView, SharedBand, TransferBand, transfer_params
from raywave.wave.propagation.transfer import _geometry
from raywave.hybrid.coherent.record import DOEField, EnvelopeRow, FieldInfo

#: aperture shapes (``Aperture.shape``) symmetric under x → −x and y → −y about the axis (with a centred obscuration)
_SYMMETRIC_APERTURES = ("circle", "square", "rectangle", "none")
#: two sources are mirror images when their coordinates agree (up to the sign of a mirrored one) to this times the
#: largest ``|x|`` or ``|y|`` asked for (1 at least): a map's grid names its mirror-image nodes to ~1e-14 of the
#: field (its chief-ray angles are solved per node), and the PSF moves by far less than rounding over such a distance
TWIN_TOL = 1e-12


def _aperture_symmetric(ap, axis: int) -> bool:
    """The aperture ``ap`` (None: none) is symmetric under the mirror of ``axis`` (0: x → −x, 1: y → −y)."""
    if ap is None:
        return True
    if getattr(ap, "shape", None) not in _SYMMETRIC_APERTURES:
        return False
    if getattr(ap, "decentered", False) and float(ap.decenter[axis]) != 0.0:  # a decentred aperture (OBDC)
        return False
    obs = getattr(ap, "obscuration", None)
    return obs is None or float(obs.decenter[axis]) == 0.0


def _interaction_symmetric(it, axis: int) -> bool:
    """The surface interaction ``it`` commutes with the mirror of ``axis``: refraction, reflection, an ideal lens, a
    coordinate break that keeps the mirror plane (for x → −x: decentres along y and tilts about x only, a fold in
    the y–z plane; for y → −y the converse); not a diffractive phase (any φ(x, y))."""
    kind = getattr(it, "kind", None)
    if kind in ("refraction", "reflection", "ideal_lens"):
        return True
    if kind == "coordinate_break":
        keep = (it.decenter_x, it.tilt_y, it.tilt_z) if axis == 0 else (it.decenter_y, it.tilt_x, it.tilt_z)
        return all(float(v) == 0.0 for v in keep)
    return False


def symmetric_axes(lens, doe, oversample: int) -> tuple[bool, bool]:
    """``(x, y)``: whether the DOE-plane field of the source mirrored across that axis (x → −x, resp. y → −y) is the
    mirror image of the source's: every surface of ``lens`` has an even sag
    (:attr:`~raywave.surfaces.geometry.Geometry.mirror_symmetric`), a symmetric aperture and interaction, and the
    DOE's simulation grid (``oversample``) and aperture are centred on the axis."""
    if getattr(doe, "aperture", None) not in ("square", "circle"):
        return False, False
    sim = doe.sim_grid(oversample)
    out = []
    for axis in (0, 1):
        ok = all(getattr(s.geometry, "mirror_symmetric", False) and _aperture_symmetric(s.aperture, axis)
                 and _interaction_symmetric(getattr(s, "interaction", None), axis) for s in lens.surfaces)
        last = (0, sim.shape[1] - 1) if axis == 0 else (sim.shape[0] - 1, 0)
        ok = ok and abs(sim.position(0, 0)[axis] + sim.position(*last)[axis]) <= 1e-9 * sim.pitch[axis]
        out.append(ok)
    return out[0], out[1]


def mirror_sources(fields, axes: tuple[bool, bool]) -> list:
    """For each source of ``fields`` (F, 2) (its field type's units), None if it is built itself, or ``(j, flip_x,
    flip_y)``: it is the source ``j``'s mirror image (``j`` built, listed before it), across x where ``flip_x`` and
    across y where ``flip_y`` (only across the ``axes`` of symmetry; both False: the same source, to
    :data:`TWIN_TOL`). Depends on the call's sources alone (a replay of the same call pairs them alike)."""
    f = fields.detach().cpu().double().tolist()
    scale = max([abs(v) for row in f for v in row] + [1.0])
    tol = TWIN_TOL * scale
    built, out = [], []
    for x, y in f:
        match = None
        for j in built:
            xj, yj = f[j]
            fx = _flip(x, xj, tol, axes[0])
            fy = _flip(y, yj, tol, axes[1])
            if fx is not None and fy is not None:
                match = (j, fx, fy)
                break
        if match is None:
            built.append(len(out))
        out.append(match)
    return out


def _flip(a: float, b: float, tol: float, symmetric: bool):
    """False if ``a`` equals ``b`` (to ``tol``), True if it equals ``−b`` across a ``symmetric`` axis, else None."""
    if abs(a - b) <= tol:
        return False
    if symmetric and abs(a + b) <= tol:
        return True
    return None


def mirror_fields(todo: list, sim: Grid) -> list:
    """:func:`mirror_field` of every ``(fd, flip_x, flip_y)`` of ``todo``: the same records, the negated centre
    components (0-d tensors) from one stack, one negation and one unbind for all of them (issue 43: one negation
    a component dispatched ~300 ops on a 10×10×3 map) where every one is a 0-d tensor on one device."""
    comps = [(k, a) for k, (fd, fx, fy) in enumerate(todo) for a, on in ((0, fx), (1, fy)) if on]
    vals = [todo[k][0].center[a] for k, a in comps]
    if len(vals) < 2 or not all(isinstance(v, torch.Tensor) and v.ndim == 0 and v.device == vals[0].device
                                and v.dtype == vals[0].dtype for v in vals):
        return [mirror_field(fd, sim, fx, fy) for fd, fx, fy in todo]
    neg = dict(zip(comps, torch.stack(vals).neg().unbind(0)))
    return [mirror_field(fd, sim, fx, fy, centre=tuple(neg.get((k, a), fd.center[a]) for a in (0, 1)))
            for k, (fd, fx, fy) in enumerate(todo)]


def mirror_field(fd: DOEField, sim: Grid, flip_x: bool, flip_y: bool, centre: tuple | None = None) -> DOEField:
    """The DOE-plane field of the mirrored source: ``fd`` (on a window of the simulation grid ``sim``, centred on the
    axis) flipped along x (``flip_x``) and y (``flip_y``), its window mirrored, its carrier's and its chief ray's
    image point's mirrored components negated (differentiable: the flips and the negations carry ``fd``'s graph).
    The diagnostics are copied; ``chief_tan`` is left to the caller (:meth:`HybridLens.doe_fields` sets every
    field's from its own chief ray). Neither flip: a copy of the record on the same envelope. A made envelope on a
    CPU without autograd is flipped where it is read (a deferred record on an :class:`EnvelopeRow` of it: the
    propagation copies it into its stack in reverse). ``centre``: the mirrored centre when the caller has it
    (:func:`mirror_fields`)."""
    iy0, iy1, ix0, ix1 = fd.box
    ny, nx = sim.shape
    if flip_x:
        ix0, ix1 = nx - ix1, nx - ix0
    if flip_y:
        iy0, iy1 = ny - iy1, ny - iy0
    grid = Grid(sim.position(iy0, ix0), sim.pitch, (iy1 - iy0, ix1 - ix0))
    a, b = fd.carrier
    carrier = (-a if flip_x else a, -b if flip_y else b)
    if centre is None:
        cx, cy = fd.center
        centre = (-cx if flip_x else cx, -cy if flip_y else cy)
    info = FieldInfo(**{k: getattr(fd.info, k) for k in FieldInfo.__dataclass_fields__})
    box = (iy0, iy1, ix0, ix1)
    if fd.row is not None:  # a row of a batch (DOEField.deferred): the flip made only where the envelope is read
        return DOEField.deferred(fd.row.flipped(flip_x, flip_y), grid, (fd.wavelength, fd.n, carrier), box, fd.z,
                                 centre, info)
    env = fd.envelope
    if (flip_x or flip_y) and env.device.type == "cpu" and not env.requires_grad:
        # on a CPU without autograd the flip is made where the envelope is read: the propagation copies the row in
        # reverse into its padded input stack (:meth:`EnvelopeRow.copy_into`), the darkness test reads it unflipped;
        # a flipped copy of each mirror image's window was a fresh window-sized array (issue 47: ~2 ms a PSF of the
        # default edge's 6×6×3 map). The same values
        row = EnvelopeRow(env[None], 0, tuple(env.shape), (flip_x, flip_y))
        return DOEField.deferred(row, grid, (fd.wavelength, fd.n, carrier), box, fd.z, centre, info)
    dims = [d for d, on in ((-1, flip_x), (-2, flip_y)) if on]
    env = env.flip(dims) if dims else env
    return DOEField(Field(env, grid, fd.wavelength, fd.n, carrier), box, fd.z, centre, info)


#: a mirror image shares its family's transfer function (:class:`FrameBands`) where its geometry, mirrored into the
#: family's frame, gives the family's parameters to this (relative, 1 at least: mm, cycles/mm): the windows' origins
#: differ there by the rounding of their positions (~1e-16 mm), a phase of ~1e-13 cycles at the band's edge
FRAME_TOL = 1e-12
#: a family's transfer function is evaluated once as one array (:class:`FrameBands`) up to this many bytes (complex128
#: band samples); a larger band is evaluated lazily per member in the frame, as before (no band-sized array)
SHARED_BAND_BYTES = 64 * 2**20


def _row_key(row: EnvelopeRow) -> tuple:
    """The stored envelope a deferred row reads (the family of a source and its mirror images)."""
    return (row.base.data_ptr(), row.row, tuple(row.shape))


def _mirrored_lines(idx: torch.Tensor, m: int, flip: bool) -> list:
    """The FFT-grid lines ``idx`` (int64, sorted) of one axis of length ``m`` in the mirrored frame (``f → −f``:
    the line ``(m − c) mod m``), sorted, as a host list; as they are without ``flip``."""
    if not flip:
        return idx.tolist()
    # (m − c) mod m of ascending lines: line 0 stays, the others reverse (m − c descends as c ascends); one host
    # read and list operations in C, not a Python expression a line (issue 47: ~1 000 lines a band, 4 axes a member)
    v = idx.tolist()
    head = [0] if v and v[0] == 0 else []
    return head + [m - c for c in reversed(v[len(head):])]


def _positions(lines: list, shared: list, m: int, flip: bool):
    """The positions of ``lines`` (a source's band lines in its family's frame) among a family's ``shared`` lines
    (:class:`FrameBands`: its regular lines, then the +Nyquist line of an even ``m``): a mirrored source's Nyquist
    line (``m/2``, −Nyquist on the ``fftfreq`` grid) reads the family's +Nyquist line, its mirror image. None where a
    line is not there."""
    regular = shared[:-1] if m % 2 == 0 else shared
    # the usual case: the lines a run of the family's (the same list, or consecutive lines of it): their positions
    # a range, checked by one list comparison (C speed) instead of a dictionary look-up a line (issue 47)
    k0 = regular.index(lines[0]) if lines and lines[0] in regular else None
    if k0 is not None:
        if regular[k0:k0 + len(lines)] == lines:
            out = list(range(k0, k0 + len(lines)))
            if flip and m % 2 == 0 and m // 2 in lines:  # (ascending: at most one such line)
                out[lines.index(m // 2)] = len(shared) - 1
            return out
    at = dict(zip(regular, range(len(regular))))
    nyq = m // 2 if flip and m % 2 == 0 else None
    out = [len(shared) - 1 if c == nyq else at.get(c) for c in lines]
    return None if None in out else out


class FrameBands:
    """The transfer functions of a source and its mirror images shared within one call (issue 47): a mirror image
    (a deferred :class:`EnvelopeRow` flipped along x / y) is propagated in its source's frame, i.e. its envelope
    read unflipped (its DOE phasors flipped), the kernel the source's, its output window flipped back. The
    convolution commutes with the mirror, so the PSF is the one of its own frame to the rounding of the windows'
    positions (the transfer function ``G_i(f) = G_j(−f)·exp(2πi f (N_in − N_out) p)`` of window corners, the same
    FFT grid: a frequency line ``c`` of the image is the line ``−c`` of the source, the Nyquist line's mirror the
    +Nyquist frequency, kept as an extra line). The family's transfer function is then evaluated once on its first
    member's band (:class:`~raywave.wave.propagation.kernels.SharedBand`) and each member's band read from it
    (:class:`~raywave.wave.propagation.kernels.BandView`), instead of once per member: 4 evaluations of the
    compiled transfer loop become 1 on a symmetric map's quadrants. Only families of two or more members in the
    call (a single PSF's source is propagated as before, bit for bit), on a CPU without autograd and without the
    window-shift / distance perturbations. ``keep``: the families held at once (a map's batches run a family's
    members one after another)."""

    def __init__(self, planned: list, keep: int = 2):
        counts: dict = {}
        for pl in planned:
            row = _eligible_row(pl.fd)
            if row is not None:
                counts[_row_key(row)] = counts.get(_row_key(row), 0) + 1
        self._shared = {k for k, n in counts.items() if n > 1}
        self._families: dict = {}
        self.keep = keep

    def frames(self, batch: list) -> list | None:
        """Per member of ``batch`` (:class:`~raywave.hybrid.batched.Planned`): its flips ``(flip_x, flip_y)`` into
        its family's frame (``(False, False)``: the family's own orientation), or None (propagated as it is); None
        where no member shares."""
        out = []
        for pl in batch:
            row = _eligible_row(pl.fd)
            out.append(tuple(row.flip) if row is not None and _row_key(row) in self._shared else None)
        return out if any(f is not None for f in out) else None

    def framed(self, transfer, wb, batch: list, frames: list):
        """``transfer`` (:func:`~raywave.wave.propagation.batch.batch_transfer` of ``wb``, each source on its own band)
        with each framed member's band in its family's frame, read from the family's shared evaluation (or, where
        its lines or geometry differ from the family's, evaluated on its own in that frame)."""
        my, mx = transfer.size
        dev = transfer.rows.device
        (px, py), parts = transfer.pitch, list(transfer.parts)
        fx_all = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=dev)
        fy_all = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=dev)
        for i, (pl, fr) in enumerate(zip(batch, frames)):
            part = parts[i]
            if fr is None or part.values is None:
                continue
            cols = _mirrored_lines(part.cols, mx, fr[0])
            rows = _mirrored_lines(part.rows, my, fr[1])
            p = transfer_params(_geometry(_framed_source(wb.sources[i], fr, wb), wb.out_shape, wb.pitch, wb.margin,
                                          wb.guard))
            row = _eligible_row(pl.fd)
            key = (*_row_key(row), transfer.size, wb.out_shape)
            fam = self._families.get(key)
            cpos = rpos = None
            if (len(cols) + 1) * (len(rows) + 1) * 16 <= SHARED_BAND_BYTES:
                if fam is None or not _close(fam[0], p):
                    fam = self._family(key, row, p, (cols, rows), (fx_all, fy_all))
                cpos = _positions(cols, fam[2], mx, fr[0])
                rpos = _positions(rows, fam[3], my, fr[1])
            if cpos is not None and rpos is not None:
                values = BandView(fam[1], cpos, rpos)
            else:  # lines the family's evaluation lacks (or a band too large to hold): this member's own, in the frame
                fxv, fyv = _frame_freqs(fx_all, cols, fr[0]), _frame_freqs(fy_all, rows, fr[1])
                values = TransferBand(fxv, fyv, torch.tensor(p, dtype=torch.float64, device=dev))
            parts[i] = OwnBand(torch.tensor(rows, dtype=torch.long, device=dev),
                               torch.tensor(cols, dtype=torch.long, device=dev), values)
        return BatchTransfer(transfer.size, transfer.rows, transfer.cols, None, None, transfer.wave, transfer.pitch,
                             transfer.batch, tuple(parts))

    def _family(self, key, row: EnvelopeRow, p: list, lines: tuple, freqs: tuple) -> tuple:
        """A new family: its parameters ``p``, the shared evaluation on the first member's ``lines`` = ``(cols,
        rows)`` (frame lines) and the +Nyquist line of each even axis, those lines, and its row's base (held: the
        key's address stays its own while the family lives)."""
        (cols, rows), (fx_all, fy_all) = lines, freqs
        mx, my = fx_all.numel(), fy_all.numel()
        cl = list(cols) + ([None] if mx % 2 == 0 else [])
        rl = list(rows) + ([None] if my % 2 == 0 else [])
        fx = _frame_freqs(fx_all, cols, False, extra=mx % 2 == 0)
        fy = _frame_freqs(fy_all, rows, False, extra=my % 2 == 0)
        shared = SharedBand(fx, fy, torch.tensor(p, dtype=torch.float64, device=fx.device))
        fam = (p, shared, cl, rl, row.base)
        self._families[key] = fam
        while len(self._families) > self.keep:
            self._families.pop(next(iter(self._families)))
        return fam


def _eligible_row(fd) -> EnvelopeRow | None:
    """The deferred row of ``fd`` (a made envelope: itself as a row, the base its mirror images read,
    :func:`mirror_field`) where its propagation may run in its family's frame: a CPU without autograd."""
    row = getattr(fd, "pending_row", None)
    if row is None:
        env = fd.envelope
        if env.ndim != 2:
            return None
        row = EnvelopeRow(env[None], 0, tuple(env.shape))
    if row.base.device.type != "cpu" or row.base.requires_grad:
        return None
    return row


def _framed_source(src, flips: tuple, wb):
    """The :class:`~raywave.wave.propagation.batch.WindowSource` ``src`` mirrored along ``flips`` = ``(x, y)``: its
    input and output windows' corners (pixel (0, 0) centres) mirrored, its carrier's components negated."""
    pitch = wb.pitch if isinstance(wb.pitch, tuple) else (wb.pitch, wb.pitch)
    (ny, nx), (oy, ox) = src.in_shape, wb.out_shape
    io, oo, car = list(src.in_origin), list(src.out_origin), list(src.carrier)
    for a, (flip, n_in, n_out) in enumerate(zip(flips, (nx, ny), (ox, oy))):
        if flip:
            io[a] = -(io[a] + (n_in - 1) * pitch[a])
            oo[a] = -(oo[a] + (n_out - 1) * pitch[a])
            car[a] = -car[a]
    return WindowSource(src.in_shape, tuple(io), tuple(oo), src.wavelength, src.z, src.n, tuple(car))


def _frame_freqs(f_all: torch.Tensor, lines: list, flip: bool, extra: bool = False) -> torch.Tensor:
    """The frequencies (cycles/mm) of the frame lines ``lines`` of one axis (``f_all`` its ``fftfreq`` grid): a
    mirrored source's Nyquist line at +Nyquist (``flip``); ``extra``: the +Nyquist line appended."""
    m = f_all.numel()
    f = f_all[torch.tensor(lines, dtype=torch.long, device=f_all.device)]
    if flip and m % 2 == 0 and m // 2 in lines:
        f = f.clone()
        f[lines.index(m // 2)] = -f_all[m // 2]
    if extra:
        f = torch.cat([f, -f_all[m // 2:m // 2 + 1]])
    return f


def _close(a: list, b: list) -> bool:
    """Parameter vectors equal to :data:`FRAME_TOL` (relative, 1 at least)."""
    return all(abs(x - y) <= FRAME_TOL * max(1.0, abs(x), abs(y)) for x, y in zip(a, b))
