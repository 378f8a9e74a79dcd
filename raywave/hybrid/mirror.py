"""Mirror symmetry of the DOE-plane field. A lens whose every surface, aperture and interaction is symmetric under
x → −x (every rotationally symmetric lens, toroids, centred obscurations, folds in the y–z plane), with a DOE grid
centred on the axis, sends the source (−x, y) exactly the mirror image of the field that (x, y) sends; likewise for
y → −y. :meth:`HybridLens.doe_fields` builds each set of mirror images once: the field of (±x, ±y) is the field of
(x, y) flipped, with its carrier and chief-ray point mirrored (:func:`mirror_field`). The DOE's phase is not part of
the DOE-plane field (it is applied in the propagation), so any DOE, a trained pixel map too, keeps the symmetry of
the field stage; the propagation runs for every PSF.

The mirrored field equals the one built for the mirrored source itself to the rounding of the construction (its
rays are aimed at their nodes to 1e-10 mm, by paths that are not mirror images): the PSFs of the bundled asphere's
10×10×3 map within 2.1e-13 (DOE-plane edge) and 6.5e-13 (exit-pupil edge), the Cooke triplet's and the double
Gauss's 6×6×3 maps within 1.1e-12 and 3.3e-12 (tests/test_hybrid_mirror.py)."""

from __future__ import annotations

import torch

from raywave.wave.grid import Field, Grid
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
