"""The record of one DOE-plane field (:class:`DOEField`: a :class:`~raywave.wave.Field` on a window of the
DOE's simulation grid, where it is, and the :class:`FieldInfo` diagnostics of its construction) and
:class:`SamplingWarning`."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from raywave.wave.grid import Field, Grid

_NEWTON_TOL = 1e-10  # mm on the DOE plane
_NEWTON_ITERS = 25


class SamplingWarning(UserWarning):
    """A grid too coarse for the phase it must carry, or a ray map that cannot be interpolated."""


class CausticWarning(SamplingWarning):
    """The rays from the stop cross between the lens and the DOE plane (a caustic lies before it): the accurate
    field is built from a one-to-one map of stop points to DOE-plane points, so there it is wrong (and so is its
    PSF). Move the DOE plane towards the lens (a lens file's default blank DOE stays before the caustic:
    :func:`raywave.assembly.build.caustic_free_distance`). Found from a regular stop grid traced to the plane
    (:func:`raywave.hybrid.coherent.doe_clippings`), which sees a fold that the field's own nodes can miss (they
    each land on one branch of it)."""


class StopEdgeWarning(UserWarning):
    """The exit-pupil stop edge is approximate or unavailable: the Fresnel edge step on an edge whose radius of
    curvature is not large against its Fresnel zone (a small obscuration), or a lens whose exit pupil lies at
    infinity (the DOE-plane edge is used instead)."""


class MergedWarning(UserWarning):
    """A warning built either from a plain message or from ``entries``, one per source of one ``scope`` ("call",
    "map"), that can be merged across calls (a map's) into one (:meth:`merged`) and pickled with its attributes
    (multi-process training). A subclass lists its constructor's arguments after the message in ``_ARGS`` (with
    "entries" and "scope" among them) and renders its text from them in ``_text``."""

    _ARGS: tuple = ("entries", "scope")

    @classmethod
    def merged(cls, warnings_: list, scope: str):
        """One warning for the sources of several built from entries (the first's other attributes kept)."""
        first = warnings_[0]
        args = {a: getattr(first, a) for a in cls._ARGS if a not in ("entries", "scope")}
        return cls("", entries=[e for w in warnings_ for e in w.entries], scope=scope, **args)

    def __reduce__(self):
        return (type(self), (str(self), *(getattr(self, a) for a in self._ARGS)))


class VignettingEdgeWarning(StopEdgeWarning, MergedWarning):
    """With the exit-pupil stop edge, an aperture other than the stop (and the DOE's) vignettes a source's beam, or
    passes near its rim: its edge is cut sharply on the DOE plane without its own edge waves (only the stop's rim
    diffracts from its images), and one just outside the rim clips the stop edge's waves, which the engine leaves out
    too; so the default's accuracy figures (docs/ray-wave.md, 1e-4 – 1e-3 against the converged references) do not
    cover that source (issue 47, class G). The estimate is a guard, not a figure: it follows the rim's clearance
    inside that aperture in Fresnel zones, not the cut edge's length
    (:func:`~raywave.hybrid.coherent.vignetting.estimate`: :data:`~raywave.hybrid.coherent.vignetting.CUT_COST`
    where rays are lost, decaying with the clearance outside the rim).

    Either a plain message, or built from ``entries``, one ``(estimate, edge length / stop rim, lost fraction of the
    stop grid's rays, surface index, where, clearance in Fresnel zones)`` per source of one ``scope`` ("call",
    "map"); :meth:`merged` joins the warnings of several calls (a map's) into one."""

    def __init__(self, message: str = "", entries=None, scope: str = "call"):
        self.entries = None if entries is None else list(entries)
        self.scope = scope
        super().__init__(message if self.entries is None else self._text())

    def _text(self) -> str:
        est, length, lost, surface, where, clear = max(self.entries, key=lambda e: e[0])
        surfaces = sorted({e[3] for e in self.entries})
        if length > 0 or lost > 0:
            how = (f"surface {surface}'s aperture (or the surface itself) vignettes the beam: {100 * lost:.3g} % of "
                   f"the stop grid's rays lost, a vignetting edge {length:.3g} × the stop's rim; that edge is cut "
                   "sharply on the DOE plane without its own edge waves (only the stop's rim diffracts from its "
                   "images)")
        else:
            how = (f"surface {surface}'s aperture passes {clear:.2g} Fresnel zones outside the beam's rim: it clips "
                   "the stop edge's waves there, which the engine leaves out")
        if len(self.entries) == 1:
            what = f"{where}: {how}"
        else:
            kind = "field × wavelength × depth" if self.scope == "map" else "field × wavelength"
            what = (f"{len(self.entries)} sources ({kind}) of this {self.scope} near or cut by the apertures of "
                    f"surface(s) {', '.join(str(j) for j in surfaces)}; most at {where}: {how}")
        return (f"{what}. This may cost the PSF up to ~{est:.1g} (relative L1; a guard, not a figure): the stop_edge "
                "default's accuracy figures do not cover these sources. Open that aperture (or use fields it does not "
                "reach) for the modelled accuracy, or accept the estimate")


@dataclass
class FieldInfo:
    """How a DOE-plane field was built (diagnostics; nothing here enters the PSF's numbers).

    Attributes:
        rays: number of rays traced to build the field.
        mode: "accurate", "faithful" or the comparison model's name (e.g. "paraxial").
        full_grid: the envelope is the whole DOE grid with no carrier removed, for the paper's full 2×-padded
            angular-spectrum propagation.
        clipped: fraction of the beam's power (leaving the lens) that falls outside the DOE aperture and is
            blocked there (from traced rays; :func:`doe_clipping`).
        beam_half: largest |x| or |y| (mm) of the beam's geometric footprint on the DOE plane.
        stop_edge: where the field's geometric-optics edge was formed: "doe" (at the DOE plane) or
            "exit_pupil" (at the exit pupil, then carried to the DOE plane).
        edge_step: with the exit-pupil edge, the step that carried it to the DOE plane: "doe" (cut on the DOE
            plane, exact there), "fresnel" (the knife-edge step, its caustic fallback included) or "asm" (the exact
            construction); None: the DOE-plane edge.
        band_clipped: with the exit-pupil edge (the knife-edge step), the fraction of the source's power on the
            plane in the edge's diffraction ripples beyond the geometric shadow that falls outside the DOE aperture
            (an estimate from the node maps; 0 where the node grid lies inside the aperture). A 0-dim tensor until
            :meth:`~raywave.hybrid.HybridLens.doe_fields` reads a call's at once (:func:`resolve_band_infos`).
        band_half: the half width (mm) of the square DOE that would hold that ripple band (0 where not computed).
        band_total: ``band_clipped`` counts the geometric beam's clipping too (the exact construction and the
            caustic fallback: the carried field's power the DOE-plane window loses); the caller subtracts
            ``clipped``.
    """

    rays: int
    mode: str
    full_grid: bool = False
    clipped: float = 0.0
    beam_half: float = 0.0
    stop_edge: str = "doe"
    edge_step: str | None = None
    band_clipped: float | torch.Tensor = 0.0  # a 0-dim tensor until resolve_band_infos reads it
    band_half: float | torch.Tensor = 0.0
    band_total: bool = False


def resolve_band_infos(fds: list) -> None:
    """Turn the :class:`FieldInfo` ``band_clipped`` / ``band_half`` tensors of the fields ``fds`` into host floats,
    from one host read for all of them (in place: each field's info replaced)."""
    pending = [fd for fd in fds if isinstance(fd.info.band_clipped, torch.Tensor)]
    if not pending:
        return
    values = torch.stack([torch.stack([torch.as_tensor(fd.info.band_clipped, dtype=torch.float64),
                                       torch.as_tensor(fd.info.band_half, dtype=torch.float64)])
                          for fd in pending]).tolist()
    for fd, (clipped, half) in zip(pending, values):
        fd.info = replace(fd.info, band_clipped=clipped, band_half=half)


@dataclass(frozen=True)
class _FieldMeta:
    """A deferred :class:`DOEField`'s :class:`~raywave.wave.Field` without its envelope (the attributes it reads)."""

    grid: Grid
    wavelength: float
    n: float
    carrier: tuple


@dataclass(frozen=True, eq=False)
class EnvelopeRow:
    """Where a DOE-plane envelope ``(ny, nx)`` = ``shape`` lies in a padded batch ``base`` (B, hy, hx): the corner of
    row ``row``, flipped along x / y where ``flip`` says (a mirror image's, :func:`raywave.hybrid.mirror.mirror_field`);
    the samples of the row beyond ``shape`` are not part of it. :meth:`make` gives the envelope itself."""

    base: torch.Tensor
    row: int
    shape: tuple
    flip: tuple = (False, False)

    def make(self) -> torch.Tensor:
        """The envelope: a strided view of the row's corner (flipped: a copy)."""
        e = self.unflipped()
        dims = [d for d, on in ((-1, self.flip[0]), (-2, self.flip[1])) if on]
        return e.flip(dims) if dims else e

    def unflipped(self) -> torch.Tensor:
        """The row's samples without its flips: a strided view (the envelope's samples in another order, for a
        read that does not depend on it: a count, a sum)."""
        s0, s1, s2 = self.base.stride()
        return torch.as_strided(self.base, tuple(self.shape), (s1, s2), self.base.storage_offset() + self.row * s0)

    def copy_into(self, dst: torch.Tensor) -> torch.Tensor:
        """``dst.copy_(self.make())`` (``dst`` ``shape``) without the flipped copy between them: on a CPU without
        autograd a flipped row is copied in reverse order (numpy's negative strides) straight into ``dst``; the
        same values. Returns ``dst``."""
        src = self.unflipped()
        if any(self.flip) and src.device.type == "cpu" and dst.device.type == "cpu" and not src.requires_grad \
                and not dst.requires_grad and src.dtype == dst.dtype and not (src.is_conj() or dst.is_conj()):
            a = src.numpy()
            np.copyto(dst.numpy(), a[::-1 if self.flip[1] else 1, ::-1 if self.flip[0] else 1])
            return dst
        return dst.copy_(self.make())

    def flipped(self, flip_x: bool, flip_y: bool) -> "EnvelopeRow":
        """The mirror image's row (no op)."""
        return EnvelopeRow(self.base, self.row, self.shape, (self.flip[0] != flip_x, self.flip[1] != flip_y))

    @staticmethod
    def by_base(rows: list) -> list:
        """The indices into ``rows`` (:class:`EnvelopeRow` s) grouped by their padded batch, each group in order and
        the groups in the order their batches first appear."""
        bases: dict = {}
        for k, r in enumerate(rows):
            bases.setdefault(id(r.base), []).append(k)
        return list(bases.values())


class DOEField:
    """The field arriving at the DOE plane for one point source and one wavelength.

    Data (the PSF is computed from these):

    * :attr:`field`: a :class:`~raywave.wave.Field`: the complex128 envelope ``(ny, nx)`` just before the DOE
      (DOE aperture applied, DOE phase not) on its :class:`~raywave.wave.Grid` (a window of the DOE's
      simulation grid, :meth:`raywave.doe.DOE.sim_grid`), divided by the carrier ``exp(i k n (α x + β y))``
      of the chief ray after the lens; wavelength (µm) and the index n between the DOE and the sensor;
    * :attr:`box`: where the grid lies on the DOE's simulation grid, half-open ``(iy0, iy1, ix0, ix1)``
      (:meth:`raywave.wave.Grid.locate`);
    * :attr:`z`: DOE → sensor distance (mm); :attr:`center`: ``(x, y)`` mm where the chief ray (through the
      refractive lens only) meets the sensor; :attr:`chief_tan`: ``(d_x/d_z, d_y/d_z)`` of that chief ray
      between the DOE and the sensor (how far ``center`` moves per mm of sensor displacement), set by
      ``HybridLens.doe_fields``; None (fields built elsewhere, or detached for a cache): the PSF is not
      differentiated with respect to the sensor distance.

    Diagnostics: :attr:`info` (:class:`FieldInfo`). The short names ``envelope``, ``origin``, ``pitch``,
    ``carrier``, ``n``, ``wavelength``, ``rays``, ``mode``, ``full_grid``, ``clipped``, ``beam_half``, ``stop_edge``
    read through to these (the legacy ``(iy0, ix0, ny, nx)`` rectangle ``window`` and ``on_window`` are gone
    (issue 43): the window is :attr:`box`, half-open, or the field's own :attr:`grid`).
    """

    __slots__ = ("_field", "_meta", "row", "box", "z", "center", "info", "chief_tan")

    def __init__(self, field: Field, box, z: float, center: tuple, info: FieldInfo,
                 chief_tan: tuple | None = None):
        if not isinstance(field, Field):
            raise TypeError(f"DOEField: field must be a raywave.wave.Field, got {type(field).__name__}")
        iy0, iy1, ix0, ix1 = (int(v) for v in box)
        if (iy1 - iy0, ix1 - ix0) != field.grid.shape:
            raise ValueError(f"DOEField: box {(iy0, iy1, ix0, ix1)} does not have the field's shape {field.grid.shape}")
        self._field, self._meta, self.row = field, field, None
        self.box, self.z, self.center = (iy0, iy1, ix0, ix1), z, center
        self.info, self.chief_tan = info, chief_tan

    @classmethod
    def deferred(cls, row: "EnvelopeRow", grid: Grid, wave: tuple, box, z: float, center: tuple, info: FieldInfo,
                 chief_tan: tuple | None = None) -> "DOEField":
        """A record whose envelope is the row ``row`` (:class:`EnvelopeRow`) of a padded batch, made (one view, and
        a flip for a mirror image) when first read (:attr:`field`, :attr:`envelope`); a batched consumer reads the
        batch itself (issue 43: the propagation's padded windows, the darkness test). ``wave`` = ``(wavelength µm,
        n, carrier (α, β))`` host floats; the rest as :class:`DOEField`'s."""
        iy0, iy1, ix0, ix1 = (int(v) for v in box)
        if (iy1 - iy0, ix1 - ix0) != tuple(grid.shape) or tuple(row.shape) != tuple(grid.shape):
            raise ValueError(f"DOEField: box {(iy0, iy1, ix0, ix1)}, grid {grid.shape} and envelope row {row.shape} "
                             "differ")
        obj = cls.__new__(cls)
        wavelength, n, carrier = wave
        obj._field, obj._meta, obj.row = None, _FieldMeta(grid, float(wavelength), float(n),
                                                          (float(carrier[0]), float(carrier[1]))), row
        obj.box, obj.z, obj.center, obj.info, obj.chief_tan = (iy0, iy1, ix0, ix1), z, center, info, chief_tan
        return obj

    @property
    def field(self) -> Field:
        """The :class:`~raywave.wave.Field` (a deferred record's envelope made now, once)."""
        if self._field is None:
            m = self._meta
            self._field = Field(self.row.make(), m.grid, m.wavelength, m.n, m.carrier)
            self._meta = self._field
        return self._field

    @field.setter
    def field(self, value: Field) -> None:
        if not isinstance(value, Field) or tuple(value.grid.shape) != tuple(self.grid.shape):
            raise ValueError("DOEField.field: a raywave.wave.Field of the record's grid shape is needed")
        self._field, self._meta, self.row = value, value, None

    @property
    def device(self) -> torch.device:
        """The envelope's device (without making a deferred one)."""
        return self.row.base.device if self._field is None else self._field.envelope.device

    @property
    def pending_row(self) -> "EnvelopeRow | None":
        """The :class:`EnvelopeRow` of a deferred record whose envelope has not been made yet (a batched consumer
        reads it there: :meth:`EnvelopeRow.copy_into`, :meth:`EnvelopeRow.unflipped`), else None."""
        return self.row if self._field is None else None

    def _with(self, info: FieldInfo, chief_tan, field: Field | None = None, center=None) -> "DOEField":
        """A copy with ``info``, ``chief_tan`` (and ``field`` / ``center`` where given); a deferred record's copy
        stays deferred (on the same row) unless given a field."""
        center = self.center if center is None else center
        if field is None and self._field is None:
            m = self._meta
            return DOEField.deferred(self.row, m.grid, (m.wavelength, m.n, m.carrier), self.box, self.z, center,
                                     info, chief_tan)
        return DOEField(self.field if field is None else field, self.box, self.z, center, info, chief_tan)

    @classmethod
    def on_box(cls, envelope: torch.Tensor, box, sim: Grid, wave: tuple, z: float, center: tuple,
               info: FieldInfo) -> "DOEField":
        """Build from an envelope on the half-open window ``box`` ``(iy0, iy1, ix0, ix1)`` of the simulation grid
        ``sim`` (:meth:`raywave.doe.DOE.sim_grid`); ``wave`` = ``(wavelength µm, n, carrier (α, β))``."""
        wavelength, n, carrier = wave
        return cls(Field(envelope, sim.window(*box), float(wavelength), n, carrier), box, z, center, info)

    def __repr__(self) -> str:
        return (f"DOEField(λ={self.wavelength:g} µm, box={self.box}, pitch={self.pitch:g} mm, z={self.z:g} mm, "
                f"carrier={self.carrier}, {self.info})")

    # ---------------------------------------------------------------- the data, by their earlier names
    envelope = property(lambda self: self.field.envelope, doc="complex ``(ny, nx)``: :attr:`field`'s envelope.")
    grid = property(lambda self: self._meta.grid, doc=":attr:`field`'s :class:`~raywave.wave.Grid`.")
    origin = property(lambda self: self._meta.grid.origin, doc="``(x, y)`` mm of the centre of sample (0, 0).")
    pitch = property(lambda self: self._meta.grid.pitch[0], doc="simulation-grid pitch (mm).")
    carrier = property(lambda self: self._meta.carrier, doc="``(α, β)`` direction cosines of the carrier.")
    n = property(lambda self: self._meta.n, doc="refractive index between the DOE and the sensor.")
    wavelength = property(lambda self: self._meta.wavelength, doc="µm.")

    rays = property(lambda self: self.info.rays)
    mode = property(lambda self: self.info.mode)
    full_grid = property(lambda self: self.info.full_grid)
    stop_edge = property(lambda self: self.info.stop_edge)

    @property
    def clipped(self) -> float:
        return self.info.clipped

    @clipped.setter
    def clipped(self, value: float) -> None:
        self.info.clipped = float(value)

    @property
    def beam_half(self) -> float:
        return self.info.beam_half

    @beam_half.setter
    def beam_half(self, value: float) -> None:
        self.info.beam_half = float(value)

    @property
    def power(self) -> torch.Tensor:
        """∫|U|² dA over the DOE plane (relative power reaching the DOE through its aperture)."""
        return (self.envelope.abs() ** 2).sum() * self.pitch**2

    # ---------------------------------------------------------------- copies
    def with_info(self, **changes) -> "DOEField":
        """A copy whose :class:`FieldInfo` has ``changes`` (e.g. ``stop_edge="exit_pupil"``)."""
        return self._with(replace(self.info, **changes), self.chief_tan)

    def with_envelope(self, envelope: torch.Tensor) -> "DOEField":
        """A copy with another envelope of the same grid (the diagnostics copied)."""
        return DOEField(self.field.with_envelope(envelope), self.box, self.z, self.center, replace(self.info),
                        self.chief_tan)

    def detach(self) -> "DOEField":
        """A copy cut from the autograd graph (for caching with a frozen refractive lens): its PSF is not
        differentiated with respect to the lens, the sensor distance included (``chief_tan`` dropped)."""
        center = tuple(c.detach() if isinstance(c, torch.Tensor) else c for c in self.center)
        return DOEField(self.field.with_envelope(self.envelope.detach()), self.box, self.z, center,
                        replace(self.info), None)

    def to(self, dtype) -> "DOEField":
        """A copy with the envelope cast to ``dtype`` (e.g. complex64 for propagation only)."""
        return self.with_envelope(self.envelope.to(dtype))
