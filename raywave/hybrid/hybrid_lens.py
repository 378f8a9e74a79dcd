"""The hybrid refractive-diffractive lens and its ray-wave PSF.

``HybridLens`` = a refractive :class:`~raywave.lens.Lens` + a :class:`~raywave.doe.DOE` in the plane
``doe_distance`` mm after the lens's last vertex + the lens's sensor (its image plane). The PSF of a point
source is computed by

1. coherent float64 ray tracing to the DOE plane and the field there (:mod:`raywave.hybrid.coherent`; by default
   (``stop_edge="exit_pupil"``) the stop's edge is sharp at the exit pupil and diffracts on the way to the DOE plane:
   the knife-edge Fresnel step, or with ``edge_step="asm"`` the field built on the exit-pupil plane and propagated
   by the angular spectrum; ``stop_edge="doe"``, the paper's model, cuts it on the DOE plane);
2. multiplication by the DOE's ``exp(i φ(x, y; λ))``;
3. band-limited angular-spectrum propagation to the sensor (:func:`raywave.wave.propagate_window`: only the
   lit DOE window to the ks×ks PSF window, with the chief-ray carrier removed; or the paper's full-grid
   2×-padded propagation for the faithful mode);
4. ``|U|²`` integrated over every sensor pixel (energy-conserving resampling from the simulation pitch),
   cropped so that the chief ray's image point (traced through the refractive lens only, so the DOE never
   moves the centre) is the centre of pixel ``[ks//2, ks//2]``, normalised to sum 1.

Conventions: fields as the lens defines them (angles in degrees, OpticStudio signs: +y field images at +y);
PSF arrays ``[iy, ix]`` with both indices increasing with the coordinate (``imshow(origin="lower")``).
"""

from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn

from raywave.doe import DOE
from raywave.hybrid.coherent import (CausticWarning, DOEField, StopEdgeWarning, VignettingEdgeWarning,
                                     accurate_field_steps, chief_rays, entrance_pupil, exit_pupil_field_steps,
                                     faithful_field, run_batched)
from raywave.hybrid.coherent.exit_pupil import (adaptive_edge_steps, fresnel_step_estimates, fresnel_step_holds,
                                                go_phase_errors, obscuration_fraction)
from raywave.hybrid.coherent.geometry import _medium_index, footprints_and_clippings
from raywave.hybrid.coherent.stop_edge import EXIT_PUPIL_FAR, edge_reach_many, stop_rim_images_all
from raywave.hybrid.coherent.record import EnvelopeRow, MergedWarning, resolve_band_infos
from raywave.hybrid.coherent.vignetting import VIGNETTING_WARN
from raywave.hybrid.coherent.settings import ChiefRays, FieldSettings, Known, Planes, Source
from raywave.hybrid.batched import (OUT_MARGIN, GeometryMemo, Planned, SensorWindow, accelerator_cap, ceil_samples,
                                    plan_groups, propagate_group)
from raywave.hybrid.mirror import FrameBands, mirror_fields, mirror_sources, symmetric_axes
from raywave.lens.frames import image_space
from raywave.lens.paraxial import exit_pupil
from raywave.lens.sources import VignettingWarning, _as_fields, chief_aim
from raywave.rays.bundle import RayBundle
from raywave.utils import devices
from raywave.utils.checks import MAX_FIELD_ANGLE, wavelengths_um
from raywave.utils.memo import recent
from raywave.utils.safe import safe_div
from raywave.wave.grid import Grid
from raywave.wave.propagation import (angular_spectrum, integrated_upsampled_intensity, propagate_window,
                                      window_transfer)

__all__ = ["DEFAULT_EDGE_STEP", "DEFAULT_STOP_EDGE", "DOEApertureWarning", "HybridLens", "PSFResult",
           "SensorCropWarning", "StopEdgeWarning"]

#: blocked power fraction above which :class:`DOEApertureWarning` is raised
CLIP_WARN = 0.01
#: the same for the stop edge's ripple band beyond the geometric beam (the beam itself within CLIP_WARN): the PSF
#: moves by 0.5 – 4× this fraction when the DOE grows to hold the band (the bundled asphere with the Fresnel step,
#: DOEs of 0.76 – 1.05 mm on axis and 3 mm at 11°; tests/test_band_clipping.py), so a cut that moves it by ~1e-3 (the
#: accuracy bars' scale) is named
BAND_CLIP_WARN = 5e-4
#: Default DOE size: this factor times the beam's extent on the DOE plane (raywave.assembly.build.default_doe_size;
#: quoted by :class:`DOEApertureWarning`).
BEAM_MARGIN = 1.2
#: the accepted values of ``HybridLens(stop_edge=...)``
STOP_EDGES = ("doe", "exit_pupil")
#: the accepted values of ``HybridLens(edge_step=...)``: how the exit-pupil edge reaches the DOE plane
EDGE_STEPS = ("adaptive", "auto", "fresnel", "asm")
#: where the stop's sharp edge is formed unless a caller says otherwise: at the exit pupil, where it is physically
#: sharp ("doe" is the paper's model; issue 19, docs/ray-wave.md)
DEFAULT_STOP_EDGE = "exit_pupil"
#: how the default exit-pupil edge reaches the DOE plane: "adaptive" (issue 47), per source the Fresnel step
#: (1.3–1.8× the DOE-plane edge's cost, any beam size), or with a blank DOE and a spherical wave at the stop's edge the
#: edge cut on the DOE plane, there exact (raywave.hybrid.coherent.exit_pupil.adaptive_edge_step), and the exact
#: construction where the Fresnel step's error estimate rejects it and the beam fits (exit_pupil.
#: fresnel_step_estimates); "asm" is the exact construction at ~4×, "auto" takes it where the beam fits
DEFAULT_EDGE_STEP = "adaptive"


#: the DOE-plane fields of one call are built and propagated in groups whose envelopes take at most about this many
#: bytes (:meth:`HybridLens._field_groups`; issue 43): the call's traces (chief rays, footprints, the stop rim's
#: images, the DOE-aperture diagnostics) are shared by all its groups, and a group's Newton rounds are one trace
FIELD_GROUP_BYTES = 2**29
#: :data:`FIELD_GROUP_BYTES` on an accelerator (at most a 32nd of a CUDA device's memory, as a propagation batch:
#: :func:`~raywave.hybrid.batched.accelerator_cap`): fewer, larger groups, each a fixed number of kernel launches
#: (the bundled asphere's 10×10×3 map: 8 groups of 512 MB; one of 4 GB)
FIELD_GROUP_BYTES_ACCELERATOR = 2**32
#: the ray stages (aiming, Newton inversion, node traces) of a call's groups are run together for up to about this
#: many nodes (:meth:`HybridLens._stage_chunks`; the default 64 nodes a side: ~128 constructions): the paused
#: constructions keep their node maps (~10 float64 channels a node) until their group's fields are built
RAY_STAGE_NODES = 2**21


@dataclass
class _CallGeometry:
    """What the field constructions of one call share (:meth:`HybridLens._accurate_geometry`): the sources ``f``
    (F, 2) at ``wls`` (µm) and ``depth``; ``chief`` = (at the DOE, at the sensor, entrance-plane points) (F, W); per
    source, None or its mirror source ``(j, flip_x, flip_y)`` (``src``); ``todo`` the built sources (indices into
    ``f``) and, per built source (its row in ``todo``): ``boxes`` ``[R][W]`` the lit footprints (False: none),
    ``clips`` ``[R][W]`` the DOE-aperture diagnostics; ``entrance`` the entrance pupil; with the exit-pupil edge
    ``edge`` = ``(z_xps, rims, cx, steps)``: its planes per wavelength, ``[W][R]`` the stop rim's images and the
    chief rays on the exit pupil, ``[R][W]`` the adaptive edge step's choice (None: another edge step) (``edge``
    None: the DOE-plane edge); ``orders`` None, or per source of ``f`` its per-source value (:class:`~raywave.hybrid.
    coherent.settings.Source` ``order``: a mid-system DOE's orders, issue 46); ``reach`` None, or ``[R][W]`` the stop
    edge's waves' reach on the DOE plane for the Fresnel step's ripple band (:func:`_edge_reaches`); ``aim`` the
    built sources' chief-ray aim (:func:`~raywave.lens.sources.chief_aim`), shared by their diagnostic ray sets;
    ``crop_reach`` (mm) the PSF crop's half-diagonal where the call knows it (:meth:`HybridLens.psf_result`; 0:
    :meth:`HybridLens.doe_fields`), for the exact edge's lattice (:class:`~raywave.hybrid.coherent.settings.
    FieldSettings` ``crop_reach``) and the adaptive step's error estimates; ``estimates`` None, or ``[R][W]`` those
    estimates (:func:`~raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates`; None where none was made);
    ``vignetting`` (the exit-pupil edge) ``{(R, W): VignettingEdge}`` of the built sources that an aperture other
    than the stop cuts or nears (:func:`~raywave.hybrid.coherent.vignetting.vignetting_edges`)."""

    f: torch.Tensor
    wls: list
    depth: object
    chief: tuple
    src: list
    todo: list | None = None
    boxes: list | None = None
    entrance: tuple | None = None
    clips: list | None = None
    edge: tuple | None = None
    orders: list | None = None
    reach: list | None = None
    aim: tuple | None = None
    crop_reach: float = 0.0
    estimates: list | None = None
    vignetting: dict | None = None

    def host_fields(self) -> list:
        """The fields ``f`` as host values ``[F][2]`` (one read for the call, on first use: the warnings' text)."""
        if self._host is None:
            self._host = self.f.detach().cpu().tolist()
        return self._host

    def __post_init__(self):
        self._host = None
        if self.todo is None:
            self.todo = [i for i, s_ in enumerate(self.src) if s_ is None]
        self.row = {i: r for r, i in enumerate(self.todo)}


class _PupilUndefined(ValueError):
    """The exit pupil is undefined (NaN: no chief ray crosses the axis and no paraxial pupil): no exit-pupil plane to
    form the stop's edge on. (A pupil at infinity is placed at :data:`EXIT_PUPIL_FAR`.)"""


_OUT_MARGIN = OUT_MARGIN  # samples around the PSF window (keeps the periodic upsampling's edge effects out of it)


def _edge_taper(shape, width: int, device) -> torch.Tensor:
    """Separable raised-cosine taper (ny, nx): 1 inside, → 0 over the outer ``width`` samples, so that the
    periodic Fourier upsampling sees no jump at the window's edges (the taper lies outside the PSF crop)."""
    def ramp(n):
        w = torch.ones(n, dtype=torch.float64, device=device)
        if width > 0 and n > 2 * width:
            t = 0.5 - 0.5 * torch.cos(math.pi * (torch.arange(width, dtype=torch.float64, device=device) + 0.5) / width)
            w[:width], w[-width:] = t, t.flip(0)
        return w
    return ramp(shape[0])[:, None] * ramp(shape[1])[None, :]


def _full_grid_window(u, fd: DOEField, dz, lo, n_out: int):
    """The paper's path: the whole DOE grid ``u`` propagated by the 2×-padded angular spectrum, then the
    ``n_out + 1`` samples from ``lo = (x, y)`` mm cut out (clamped to the grid); returns ``(field, origin)``."""
    p = fd.pitch
    full = angular_spectrum(u, p, fd.wavelength, fd.z if dz is None else fd.z + dz, fd.n, pad=2)
    jx0 = int(math.floor((lo[0] - fd.origin[0]) / p))
    jy0 = int(math.floor((lo[1] - fd.origin[1]) / p))
    a0, b0 = max(jy0, 0), max(jx0, 0)
    a1, b1 = min(jy0 + n_out + 1, full.shape[-2]), min(jx0 + n_out + 1, full.shape[-1])
    if a1 <= a0 or b1 <= b0:
        return torch.zeros((1, 1), dtype=full.dtype, device=full.device), lo
    return full[a0:a1, b0:b1], (fd.origin[0] + b0 * p, fd.origin[1] + a0 * p)


def _quiet_chief_rays(optics, f: torch.Tensor, wls: list[float], depth, z_doe: float, z_sen: float):
    """:func:`chief_rays` of the fields ``f`` (F, 2) at the wavelengths ``wls`` (µm) on the DOE plane ``z_doe`` and
    the sensor ``z_sen`` (mm): ``(at the DOE, at the sensor, entrance-plane points)``, each (F, W). Its warnings
    are dropped: chief-ray vignetting is reported per PSF (:meth:`HybridLens._finish_fields`)."""
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always", VignettingWarning)
        return chief_rays(optics, f, torch.tensor(wls, dtype=torch.float64, device=optics.device), depth, z_doe, z_sen)


def _edge_reaches(optics, rims: list, chief_sensor, todo: list, wls: list, planes: tuple) -> list:
    """``[R][W]``: the stop edge's waves' reach (Fresnel zones, or None) on the DOE plane at each built source's crop
    centre (its chief ray on the sensor, ``chief_sensor`` (F, W)), from its rim images ``rims`` ``[W][R]``, for the
    Fresnel step's ripple band (:func:`~raywave.hybrid.coherent.stop_edge.edge_reach_many`: one host read for the
    call, issue 43; each value that of the construction's own :func:`~raywave.hybrid.coherent.stop_edge.ripple_band`).
    ``planes`` = ``(z_doe, z_sensor, crop_reach)`` mm (``crop_reach``: the PSF crop's half-diagonal, 0: unknown;
    a crop inside the rim rays' ring widens its band)."""
    nr, nw = len(todo), len(wls)
    if nr == 0:
        return []
    pts = chief_sensor.o.detach()[torch.tensor(todo, dtype=torch.long, device=chief_sensor.o.device)][..., :2]
    lam = [wl * 1e-3 / _medium_index(optics, wl) for wl in wls]  # the image medium's wavelength (mm), as _Build's
    z_doe, z_sen, crop_reach = planes
    flat = edge_reach_many([rims[j][r] for j in range(nw) for r in range(nr)], z_doe, z_sen,
                           pts.transpose(0, 1).reshape(-1, 2), [lam[j] for j in range(nw) for _ in range(nr)],
                           crop_reach=crop_reach)
    return [[flat[j * nr + r] for j in range(nw)] for r in range(nr)]


def _source_elements(t, sources: list[int], nw: int) -> dict:
    """``{i: [W] elements}`` of the (F, W) chief-ray bundle or (F, W, 2) tensor ``t`` at the sources ``sources``
    (indices into its first axis): each element what ``t[i][j]`` gives, from one gather and one unbind per field
    (issue 43: not a few ops per source)."""
    if not sources:
        return {}
    idx = torch.tensor(sources, dtype=torch.long, device=t.o.device if isinstance(t, RayBundle) else t.device)

    def rows(x):
        return x.index_select(0, idx).flatten(0, 1).unbind(0)

    if isinstance(t, RayBundle):
        wl = torch.broadcast_to(t.wavelength, t.shape)
        flat = [RayBundle(*f) for f in zip(rows(t.o), rows(t.d), rows(wl), rows(t.valid), rows(t.opl))]
    else:
        flat = rows(t)
    return {i: flat[k * nw:(k + 1) * nw] for k, i in enumerate(sources)}


def _center_of(fd: DOEField):
    """``fd.center`` as one float64 (2,) tensor (its two 0-d tensors stacked) or a host pair."""
    c = fd.center
    if all(isinstance(v, torch.Tensor) for v in c):
        return torch.stack(list(c)).to(torch.float64)
    return tuple(float(v) for v in c)


def _chief_tans(chief_doe, members: list[int]) -> list:
    """The chief rays' slopes ``(dx/dz, dy/dz)`` (host floats) on the DOE plane of the sources ``members`` (indices
    into the (F, W) bundle ``chief_doe``), ``[len(members)][W]`` pairs: one division and one host read for all of
    them (issue 43; the same values as each source's own)."""
    d = chief_doe.d.detach()[torch.tensor(members, dtype=torch.long, device=chief_doe.d.device)]  # (M, W, 3)
    return [[tuple(t) for t in row] for row in (d[..., :2] / d[..., 2:]).tolist()]


def _dark_many(fds: list) -> list[bool]:
    """:func:`_dark` of every field of ``fds`` from one host read."""
    if not fds:
        return []
    rows = [getattr(fd, "row", None) for fd in fds]
    if len(fds) > 1 and all(r is not None and not r.base.requires_grad for r in rows):
        # every envelope a row of a padded batch (DOEField.deferred): each batch's rows tested at once, its samples
        # beyond each envelope masked (issue 43: three ops a field before)
        lit = []
        groups = EnvelopeRow.by_base(rows)
        for ks in groups:
            base = rows[ks[0]].base
            _, hy, hx = base.shape
            sub = [rows[k] for k in ks]
            picked = [r.row for r in sub]
            part = base if picked == list(range(base.shape[0])) else \
                base.index_select(0, torch.tensor(picked, device=base.device))
            own_y = np.arange(hy) < np.array([r.shape[0] for r in sub])[:, None]  # (the masks built on the host)
            own_x = np.arange(hx) < np.array([r.shape[1] for r in sub])[:, None]
            own = (torch.from_numpy(own_y[:, :, None]).to(base.device)
                   & torch.from_numpy(own_x[:, None, :]).to(base.device))
            nz = (torch.view_as_real(part) != 0).any(-1) & own
            lit.append(nz.flatten(1).any(1))
        order = [k for ks in groups for k in ks]
        flags = torch.cat(lit).tolist() if len(lit) > 1 else lit[0].tolist()
        out = [False] * len(fds)
        for k, f in zip(order, flags):
            out[k] = not f
        return out
    # (a deferred envelope counted on its row unflipped: a count does not depend on the order)
    counts = torch.stack([torch.count_nonzero(torch.view_as_real(
        fd.pending_row.unflipped().detach() if getattr(fd, "pending_row", None) is not None else fd.envelope.detach()))
        for fd in fds])
    return [c == 0 for c in counts.tolist()]


def _dark(fd: DOEField) -> bool:
    """No light in the field (its power is 0): every envelope sample is 0 (a cheap test, no |U|² sum; counting
    the real view's non-zeros is ~2.5× faster than a complex ``!= 0``)."""
    return int(torch.count_nonzero(torch.view_as_real(fd.envelope.detach()))) == 0


class SensorCropWarning(UserWarning):
    """The PSF crop is centred outside the sensor."""


class DOEApertureWarning(MergedWarning):
    """The DOE aperture blocks part of the beam (more than 1 % of its power), or (``kind`` "band") of the stop
    edge's diffraction ripples beyond the beam's geometric shadow (more than :data:`BAND_CLIP_WARN` of the beam's
    power, the beam itself fitting); ``energy_outside`` does not show it, since it is measured against the power
    that reaches the DOE.

    Either a plain message (``DOEApertureWarning("text")``, as ``warnings`` builds it), or built from ``entries``,
    one ``(blocked fraction, beam half-width mm, where)`` per clipped source of one ``scope`` ("call", "map"),
    and the DOE's ``size`` (w, h) mm; these are kept as attributes, so that the warnings of several calls can be
    merged into one (:meth:`merged`, one per ``kind`` and DOE size). For the "band" kind the half-width is the ripple
    band's."""

    _ARGS = ("entries", "size", "scope", "kind")

    def __init__(self, message: str = "", entries=None, size=None, scope: str = "call", kind: str = "beam"):
        self.entries = None if entries is None else list(entries)
        self.size, self.scope, self.kind = (None if size is None else tuple(size)), scope, kind
        super().__init__(message if self.entries is None else self._text())

    def _text(self) -> str:
        w, h = self.size
        blocked, half, where = max(self.entries, key=lambda e: e[0])
        need = 2.0 * max(e[1] for e in self.entries)
        band = self.kind == "band"
        what_blocked = "the stop edge's diffraction ripples beyond the beam's geometric edge, " if band else ""
        pct = (lambda v: f"{100 * v:.2g}") if band else (lambda v: f"{100 * v:.1f}")  # the ripples: small fractions
        if len(self.entries) == 1:
            what = (f"{where}: the {w:g}×{h:g} mm DOE aperture blocks {what_blocked}{pct(blocked)} % of the "
                    "beam's power")
            beams = "a DOE of {:.3g} mm square holds the ripple band" if band else "the beam needs"
        else:
            low = min(e[0] for e in self.entries)
            kind = "field × wavelength × depth" if self.scope == "map" else "field × wavelength"
            what = (f"{len(self.entries)} sources ({kind}) of this {self.scope}: the {w:g}×{h:g} mm DOE "
                    f"aperture blocks {what_blocked}{pct(low)}–{pct(blocked)} % of their beams' power (most at "
                    f"{where})")
            beams = "a DOE of {:.3g} mm square holds every ripple band" if band else "the widest beam needs"
        if band:  # the beam fits: the PSF carries the DOE edge's own diffraction of the ripples
            return (f"{what} (not counted in energy_outside; the PSF carries the DOE edge's diffraction of them); "
                    + beams.format(need))
        return (f"{what} (not counted in energy_outside); {beams} a DOE of at least {need:.3g} mm square "
                f"({BEAM_MARGIN * need:.3g} mm with the usual {BEAM_MARGIN:g}× margin, see "
                "raywave.assembly.build.default_doe_size)")


@dataclass
class PSFResult:
    """PSFs of a batch of point sources.

    Attributes:
        psf: float64 ``(F, W, ks, ks)``, each summing to 1 (all zeros for a fully vignetted source).
        center: ``(F, W, 2)`` mm, sensor position of pixel ``[ks//2, ks//2]``'s centre (the chief ray).
        energy_outside: ``(F, W)`` fraction of the power reaching the DOE that falls outside the crop.
        pitch: sensor pixel pitch (mm).
        rays: ``(F, W)`` number of rays traced per PSF.
        doe_clipped: ``(F, W)`` fraction of the beam's power leaving the lens that the DOE aperture blocks
            (from traced rays; not in ``energy_outside``, whose reference is the power through the DOE).
            None where not computed.
    """

    psf: torch.Tensor
    center: torch.Tensor
    energy_outside: torch.Tensor
    pitch: float
    rays: torch.Tensor
    doe_clipped: torch.Tensor | None = None


class HybridLens(nn.Module):
    """A refractive lens followed by a DOE and the sensor.

    Args:
        lens: the refractive part (its last thickness reaches the sensor plane).
        doe: the DOE (its grid and pitch define the simulation grid).
        doe_distance: mm from the last surface's vertex to the DOE plane (0 < d < last thickness).
        sensor_pitch: PSF pixel pitch (mm); default: the lens's sensor pixel pitch, else the DOE pitch.
        oversample: simulation samples per DOE pixel per axis (resolves the DOE's pixel steps).
        intensity_upsample: the sensor-plane field is Fourier-interpolated to pitch p/q before |U|² is
            integrated over the sensor pixels (q ≥ 2 samples the intensity exactly; 4 makes the pixel
            quadrature accurate to ~1e-4 for PSFs as sharp as the simulation grid allows).
        stop_edge: where the accurate mode forms the geometric field's sharp edge. "exit_pupil" (the default,
            :data:`DEFAULT_STOP_EDGE`): at the exit pupil (:meth:`exit_pupil_z`, the stop's image, where its edge
            is physically sharp); the edge's Fresnel diffraction between there and the DOE plane is added by
            ``edge_step``, so off-axis PSFs do not depend on the DOE distance and agree with the Huygens exit-pupil
            model (docs/ray-wave.md, Accuracy). "doe" (the paper's model): cut sharply on the DOE plane. None: the
            default; a lens whose exit pupil is undefined (no chief ray crosses the axis) then falls back to "doe"
            with a :class:`StopEdgeWarning` (an explicit "exit_pupil" raises instead); one at or near infinity
            (image-space telecentric) takes the exit pupil's edge too (:data:`EXIT_PUPIL_FAR`). The faithful mode
            ignores it.
        edge_step: with ``stop_edge="exit_pupil"``, how the edge's diffraction reaches the DOE plane. "asm": the
            exact construction, the field built on the exit-pupil plane and propagated to the DOE plane by the
            angular spectrum (~10× the DOE-plane edge's cost; only for beams that span at most
            :data:`raywave.hybrid.coherent.AUTO_ASM_SAMPLES` simulation samples on the exit-pupil plane).
            "fresnel": the analytic knife-edge step on the DOE plane's own grid (a few times the DOE-plane edge's
            cost, any beam size; :func:`raywave.hybrid.coherent.stop_edge_factor`; 1e-3 … 5e-3 L1 from the exact
            construction on the bundled asphere, docs/ray-wave.md).
            "auto": "asm" where the beam fits, else "fresnel". "adaptive" (the default since issue 47): "fresnel", or
            where the DOE is blank and the wave at the stop's edge a sphere, the edge cut on the DOE plane (exact
            there: :func:`raywave.hybrid.coherent.exit_pupil.adaptive_edge_step`), or "asm" where the Fresnel step's
            error estimate for the PSF's crop rejects it and the beam fits as for "auto" (:func:`raywave.hybrid.
            coherent.exit_pupil.fresnel_step_estimates`; else "fresnel" with a :class:`StopEdgeWarning`). Each
            field's ``info.edge_step`` says which step it took.
        mirror: build the DOE-plane field of a source that is the mirror image of another in the same call (across
            x or y, on a lens and DOE grid symmetric across that axis: :func:`raywave.hybrid.mirror.symmetric_axes`)
            by mirroring the other's (default True: a map's symmetric grid builds a quarter of its fields; the PSFs
            agree with building each one to the construction's rounding, max |Δ| 2e-13 … 3e-12 on the bundled
            lenses' maps). False builds every field.
    """

    #: sources a PSF map without autograd hands to one :meth:`psf_result` call (:func:`raywave.imaging.psfmap.
    #: map_call_size`): the call's shared traces hold ~3,000 rays per source (~1 GB at most), its fields are built
    #: in groups of :data:`FIELD_GROUP_BYTES`
    map_sources_per_call = 512

    def __init__(self, lens, doe: DOE, doe_distance: float, sensor_pitch: float | None = None, oversample: int = 1,
                 intensity_upsample: int = 4, stop_edge: str | None = None, edge_step: str = DEFAULT_EDGE_STEP,
                 mirror: bool = True):
        super().__init__()
        problem = lens.wave_support_problem()
        if problem is not None:
            raise ValueError(problem)
        self.lens = lens
        self.doe = doe
        last = float(lens.surfaces[-1].thickness.detach()) * lens.direction_signs()[-1]
        if not (0 <= doe_distance < last):
            raise ValueError(f"doe_distance must lie between the last surface and the sensor (0 ≤ d < {last:g} mm), "
                             f"got {doe_distance!r}")
        self.doe_distance = float(doe_distance)
        pitch = sensor_pitch if sensor_pitch is not None else lens.pixel_pitch
        self.sensor_pitch = float(pitch if pitch is not None else doe.pitch)
        if not (self.sensor_pitch > 0 and math.isfinite(self.sensor_pitch)):
            raise ValueError(f"sensor pitch must be a finite number > 0 mm, got {self.sensor_pitch!r}")
        if int(oversample) < 1:
            raise ValueError(f"oversample must be a positive integer, got {oversample!r}")
        self.oversample = int(oversample)
        if int(intensity_upsample) < 2:
            raise ValueError(f"intensity_upsample must be >= 2 (|U|² has twice the field's bandwidth), got "
                             f"{intensity_upsample!r}")
        self.intensity_upsample = int(intensity_upsample)
        if stop_edge is not None and stop_edge not in STOP_EDGES:
            raise ValueError(f"stop_edge must be one of {STOP_EDGES}, got {stop_edge!r}")
        self._edge_requested = stop_edge  # None: the default, which may fall back (see _exit_pupil_planes)
        self.stop_edge = DEFAULT_STOP_EDGE if stop_edge is None else stop_edge
        if edge_step not in EDGE_STEPS:
            raise ValueError(f"edge_step must be one of {EDGE_STEPS}, got {edge_step!r}")
        self.edge_step = edge_step
        self.mirror = bool(mirror)
        # transfer functions of recent window pairs (a training loop with a frozen lens reuses them); plain
        # per-instance memo, never part of the state_dict
        self._transfer_cache: OrderedDict = OrderedDict()
        # and of the exact exit-pupil step (raywave.hybrid.coherent.exit_pupil.edge_transfer: its few most recent)
        self._edge_transfers: OrderedDict = OrderedDict()
        self._geometry_memo = GeometryMemo()  # the batched path's pixel weights (raywave.hybrid.batched)
        self._xp_memo: dict = {}  # exit-pupil planes per (lens state, wavelength): plain memo, not state
        self._rim_images = None  # use_rim_images: the exact edge's stop-rim images, replaced by a caller's

    def use_rim_images(self, fn) -> "HybridLens":
        """Let ``fn(optics, fields (F, 2), wavelengths [W], depth, rims)`` replace the stop rim's images that the
        exit-pupil edge uses (``rims``: :func:`~raywave.hybrid.coherent.stop_rim_images_all`'s ``[W][F]`` results; it
        returns the same structure), e.g. a :class:`~raywave.hybrid.MidSystemLens`'s weak diffraction orders, whose
        edge wave reaches the PSF crop far from the rim ray (issue 46); None: the rim images as traced. Returns
        ``self``."""
        if fn is not None and not callable(fn):
            raise TypeError(f"use_rim_images: a callable or None, got {type(fn).__name__}")
        self._rim_images = fn
        return self

    def use_transfer_cache(self, cache: OrderedDict, edge: OrderedDict | None = None) -> "HybridLens":
        """Share ``cache``, a memo of window transfer functions (see :meth:`_transfer`), with other engines on the
        same geometry (e.g. a :class:`~raywave.hybrid.MidSystemLens`'s engines for its diffraction orders), and
        ``edge`` (when given) the memo of the exact exit-pupil step's (:func:`~raywave.hybrid.coherent.exit_pupil.
        edge_transfer`); returns ``self``."""
        if not isinstance(cache, OrderedDict):
            raise TypeError(f"use_transfer_cache: an OrderedDict, got {type(cache).__name__}")
        if edge is not None and not isinstance(edge, OrderedDict):
            raise TypeError(f"use_transfer_cache: edge must be an OrderedDict, got {type(edge).__name__}")
        self._transfer_cache = cache
        if edge is not None:
            self._edge_transfers = edge
        return self

    def with_doe(self, doe: DOE, **overrides) -> "HybridLens":
        """A new :class:`HybridLens` on the same refractive lens (shared, not copied) with ``doe`` in place of
        this one's and every setting kept (DOE distance, sensor pitch, oversample, intensity upsampling, stop edge,
        edge step and mirroring); ``overrides``: constructor arguments to change."""
        kw = dict(doe_distance=self.doe_distance, sensor_pitch=self.sensor_pitch, oversample=self.oversample,
                  intensity_upsample=self.intensity_upsample, stop_edge=self._edge_requested,
                  edge_step=self.edge_step, mirror=self.mirror)
        kw.update(overrides)
        return HybridLens(self.lens, doe, **kw)

    def field_signature(self) -> tuple:
        """What this hybrid's DOE-plane fields depend on besides their sources: the refractive lens (the exact
        bytes of its parameters and buffers, and its structure), the DOE's grid and aperture (not its phase: the
        fields arrive before it) and the settings :meth:`with_doe` keeps that shape them (not the intensity
        upsampling, a propagation setting). Equal signatures build equal fields
        (:class:`raywave.imaging.DOEFieldCache`)."""
        import hashlib

        h = hashlib.blake2b(digest_size=16)
        for name, t in sorted(self.lens.state_dict().items()):
            h.update(name.encode())
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        doe = self.doe
        return (type(self).__name__, repr(self.lens), h.hexdigest(), type(doe).__name__, tuple(doe.shape),
                float(doe.pitch), doe.aperture, self.doe_distance, self.sensor_pitch, self.oversample, self.stop_edge,
                self.edge_step, self._edge_requested, self.mirror)

    # ------------------------------------------------------------------ geometry
    @property
    def optics(self):
        """The refractive lens as the engine traces it: the lens itself, or for a folded, decentred, tilted or
        mirrored lens its :class:`~raywave.lens.frames.ImageSpaceLens`, whose traces end in the image-space frame
        (the local frame after the last coordinate break, z along the light): the DOE plane and the sensor lie
        perpendicular to that axis, and every z and PSF centre of this class is in that frame."""
        return image_space(self.lens)

    def doe_z(self) -> float:
        """z (mm) of the DOE plane."""
        return float(self.lens.vertex_z()[-1].detach()) + self.doe_distance

    def sensor_z(self) -> float:
        """z (mm) of the sensor plane (the lens's image plane)."""
        return float(self.optics.image_z().detach())

    def sensor_distance(self) -> torch.Tensor:
        """DOE → sensor distance (mm), a 0-d float64 tensor differentiable with respect to the lens's
        thicknesses: the DOE sits ``doe_distance`` after the last vertex, so only the last thickness (the
        focus) changes it."""
        return self.optics.image_z() - (self.lens.vertex_z()[-1] + self.doe_distance)

    def _sensor_dz(self) -> torch.Tensor | None:
        """Zero-valued 0-d tensor carrying d(DOE → sensor distance)/dθ, or None for a frozen lens."""
        d = self.sensor_distance()
        return d - d.detach() if d.requires_grad else None

    def exit_pupil_z(self, wavelength: float | None = None) -> float:
        """z (mm) of the refractive lens's exit pupil at ``wavelength`` µm (default primary), the image of the
        stop's centre: where a real chief ray of a small field (1e-3 of the largest field), extended as a
        straight line in the image medium, crosses the axis (the paraxial exit pupil, but also right for
        surfaces the paraxial trace does not model, e.g. phase surfaces); usually a virtual plane inside the
        lens. Falls back to :func:`raywave.lens.paraxial.exit_pupil` when that ray cannot be traced. A pupil farther
        than :data:`EXIT_PUPIL_FAR` from the DOE plane (image-space telecentric) is placed that far before the plane:
        where the exit-pupil edge's construction starts."""
        from raywave.lens.sources import chief_ray

        wl = self.lens.primary_wavelength if wavelength is None else float(wavelength)
        return self._checked_pupil(self._exit_pupil_zs([wl])[0])

    def _checked_pupil(self, z: float) -> float:
        """``z`` (an exit pupil's z, mm); one farther than :data:`EXIT_PUPIL_FAR` from the DOE plane on either side,
        or at infinity, placed that far before the plane (the telecentric limit is the same from both sides; the
        rim images are placed alike); :class:`_PupilUndefined` where ``z`` is undefined (NaN: no chief ray and no
        paraxial pupil)."""
        zd = self.doe_z()
        if math.isnan(z):
            raise _PupilUndefined(f"stop_edge='exit_pupil': the lens's exit pupil is undefined (z = {z:g}), where no "
                                   "field can be built; use stop_edge='doe'")
        if abs(z - zd) <= EXIT_PUPIL_FAR:
            return z
        return zd - EXIT_PUPIL_FAR

    def _exit_pupil_zs(self, wls: list) -> list:
        """:meth:`exit_pupil_z`'s z (mm) at each wavelength of ``wls`` (µm), unchecked (inf or NaN where it fails):
        on a lens in its own frame, the wavelengths' chief rays aimed and traced together (issue 43: one aiming, one
        trace and one host read, not one each per wavelength; every ray is traced on its own)."""
        from raywave.lens.sources import chief_ray

        # the exit pupil is the stop's image by the lens behind it: it does not depend on the object, so the
        # ray comes from a distant object at a small angle whatever the lens's field type and object distance
        # (object-height fields cannot describe a distant object)
        if self.lens.field_type == "angle":
            angle = 1e-3 * (max([abs(float(f)) for f in getattr(self.lens, "fields", [])] + [0.0]) or 1.0)
        else:
            angle = 1e-2
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", VignettingWarning)  # a locating ray (apertures off); the PSF reports
            optics = self.optics
            if optics is self.lens:
                ray = chief_ray(self.lens, (0.0, angle), list(wls), field_type="angle", depth=math.inf)  # (1, W, 1)
                out = self.lens.trace(ray, apertures=False)
                o, d = out.o.reshape(-1, 3), out.d.reshape(-1, 3)
                ok = out.valid.reshape(len(wls), -1).all(-1)
                rows = torch.cat([o[:, 1:], d[:, 1:], ok[:, None].to(o.dtype)], 1).tolist()  # one host read
                # z = o_z − o_y·d_z/d_y in the same float64 operations as on 0-d tensors
                return [oz - oy * dz / dy if good == 1.0 and abs(dy) > 1e-15 else float(exit_pupil(self.lens, wl)[0])
                        for (oy, oz, dy, dz, good), wl in zip(rows, wls)]
            zs = []
            for wl in wls:  # image-space frame: where the small field's chief ray meets the axial chief ray
                rays = chief_ray(self.lens, [(0.0, 0.0), (0.0, angle)], wl, field_type="angle", depth=math.inf)
                out = optics.trace(rays, apertures=False)
                o, d = out.o.reshape(2, 3), out.d.reshape(2, 3)
                w = o[1] - o[0]
                w_perp = w - (w @ d[0]) * d[0]  # components across the axial chief ray: no cancellation
                u = d[1] - (d[1] @ d[0]) * d[0]
                uu = float(u @ u)
                ok = bool(out.valid.all()) and uu > 1e-30
                zs.append(float(o[1, 2] - d[1, 2] * (w_perp @ u) / uu) if ok else math.nan)
            return zs

    def _lens_state_key(self) -> tuple:
        """What identifies the refractive lens's current numbers without reading them: each state tensor's storage,
        version counter (every in-place change, an optimiser's step or ``load_state_dict``, bumps it) and shape,
        and the lens's field settings (host-side: no device round trip)."""
        state = tuple((k, t.data_ptr(), t._version, tuple(t.shape), str(t.device))
                      for k, t in self.lens.state_dict(keep_vars=True).items())
        lens = self.lens
        return (id(lens), state, lens.field_type, tuple(getattr(lens, "fields", []) or ()), lens.primary_wavelength,
                getattr(lens, "stop_index", None), tuple(id(m) for m in lens.modules()))

    def _exit_pupil_memo(self, wls: list) -> list:
        """:meth:`exit_pupil_z` at each wavelength of ``wls`` (µm), memoised per wavelength while the lens's state is
        unchanged (a map's calls, a training loop with a frozen lens: one chief-ray trace per wavelength instead of one
        per call; the missing wavelengths' together, :meth:`_exit_pupil_zs`)."""
        state = self._lens_state_key()
        keys = [(state, float(wl)) for wl in wls]
        todo = list(dict.fromkeys(float(wl) for wl, k in zip(wls, keys) if k not in self._xp_memo))
        # the wavelengths together unless exit_pupil_z is replaced (a subclass's or an instance's own): then its calls
        own = getattr(self.exit_pupil_z, "__func__", None) is HybridLens.exit_pupil_z
        zs = self._exit_pupil_zs(todo) if todo and own else [None] * len(todo)
        if todo:
            for wl, z in zip(todo, zs):
                z = self._checked_pupil(z) if own else self.exit_pupil_z(wl)
                if len(self._xp_memo) > 32:
                    self._xp_memo.clear()
                self._xp_memo[(state, wl)] = z
        return [self._xp_memo[k] for k in keys]

    def _exit_pupil_planes(self, wls: list[float]) -> list[float] | None:
        """z (mm) of every wavelength's exit-pupil plane when the accurate field forms the stop's edge there, else
        None: ``stop_edge="doe"``, or the default edge on a lens whose exit pupil is undefined (warns
        :class:`StopEdgeWarning` and uses the DOE-plane edge; an explicit ``stop_edge="exit_pupil"`` raises). A pupil
        at or near infinity (image-space telecentric) is placed at :data:`EXIT_PUPIL_FAR` (:meth:`_checked_pupil`)."""
        if self.stop_edge != "exit_pupil":
            return None
        stop_ap = self.lens.surfaces[self.lens.stop_index].aperture
        refusal = stop_ap.stop_edge_refusal() if stop_ap is not None else None
        if refusal is not None:  # a rectangular or decentred stop (issue 44): its rim is no circle about the axis
            if self._edge_requested is not None:
                raise ValueError(f"stop_edge='exit_pupil': {refusal}; use stop_edge='doe' (the edge cut on the DOE "
                                 "plane honours any aperture)")
            warnings.warn(f"{refusal}: the stop's edge is formed on the DOE plane (stop_edge='doe') instead of the "
                          "default exit pupil", StopEdgeWarning, stacklevel=4)
            return None
        try:
            return self._exit_pupil_memo(wls)
        except _PupilUndefined:
            if self._edge_requested is not None:
                raise
            warnings.warn("the lens's exit pupil is undefined (no chief ray crosses the axis): the stop's edge is "
                          "formed on the DOE plane (the paper's model) instead of the default exit pupil",
                          StopEdgeWarning, stacklevel=4)
            return None

    def wavelength_list(self, wavelengths=None) -> list[float]:
        """``wavelengths`` (µm: None → the lens's primary, a scalar or any (W,)) as a list of floats: how every PSF
        model (this engine and :mod:`raywave.models`) reads its ``wavelengths`` argument."""
        if wavelengths is None:
            return [self.lens.primary_wavelength]
        return wavelengths_um(torch.as_tensor(wavelengths, dtype=torch.float64, device="cpu"), "wavelengths")

    _wavelengths = wavelength_list  # the pre-issue-17 private name

    # ------------------------------------------------------------------ step 1-2: the DOE-plane field
    def doe_fields(self, fields=(0.0, 0.0), wavelengths=None, depth=None, mode: str = "accurate",
                   rays: int | None = None, full_grid: bool = False, generator=None, check: bool = True,
                   trace_dtype=torch.float64, crop_reach: float = 0.0):
        """The fields arriving at the DOE plane, a nested list ``[F][W]`` of :class:`DOEField`.

        Depends on the refractive lens only (not on the DOE phase): call ``.detach()`` on each to cache
        them when only the DOE is trained (see :meth:`psf` ``cache=``).

        Accurate mode: the F×W fields are built together, their ray traces batched across fields
        (:func:`raywave.hybrid.coherent.run_batched`; each field equals the one a call for that source alone
        builds). Holds all F×W fields (and, with autograd, their traces' graph) at once: a map limits F per call.

        Args:
            fields: (2,) or (F, 2) field points in the lens's field type (degrees for angles).
            wavelengths: µm, scalar or (W,) (default: the lens's primary wavelength).
            depth: object distance (mm from the first vertex; default the lens's, ``inf`` = distant).
            mode: "accurate" (default) or "faithful" (the paper's ray splatting).
            rays: accurate: traced nodes across the footprint (default 64); faithful: number of rays
                (default 100 000).
            full_grid: faithful only: keep the whole DOE grid for the paper's full 2×-padded propagation.
            generator: torch.Generator for the faithful mode's random pupil samples.
            trace_dtype: faithful only: the ray-tracing precision (float64; float32 only to study its failure,
                see examples/precision_study.py). The accurate mode always traces in float64.
            crop_reach: accurate, exact edge: how far (mm) from the chief ray's landing the PSF crop these fields are
                for reaches (its half-diagonal, :meth:`crop_reach`; :meth:`psf_result` passes its own; 0: the
                geometric spot only): the exact construction's lattice keeps the edge waves that land there (issue
                46, the far tails).
        """
        if mode not in ("accurate", "faithful"):
            raise ValueError(f"mode must be 'accurate' or 'faithful', got {mode!r}")
        if mode == "accurate" and trace_dtype != torch.float64:
            raise ValueError("the accurate mode traces in float64 only (its rays land on their nodes to 1e-10 mm)")
        if not (math.isfinite(float(crop_reach)) and float(crop_reach) >= 0.0):
            raise ValueError(f"crop_reach must be a finite distance >= 0 mm, got {crop_reach!r}")
        f = self._engine_fields(fields)
        wls = self.wavelength_list(wavelengths)
        if mode == "accurate":
            geo = self._accurate_geometry(f, wls, depth, float(crop_reach))
            out = self._finish_fields(self._accurate_group(geo, list(range(f.shape[0])), rays or 64, check), geo)
            self._warn_vignetting(geo, stacklevel=2)
            return out
        optics = self.optics
        z_doe, z_sen = self.doe_z(), self.sensor_z()
        cd, cs, _ = _quiet_chief_rays(optics, f, wls, depth, z_doe, z_sen)
        settings = FieldSettings(n_rays=rays or 100_000, oversample=self.oversample, full_grid=full_grid,
                                 generator=generator, check=check, trace_dtype=trace_dtype)
        built = [faithful_field(optics, self.doe, Source(f[i], wl, depth), Planes(z_doe, z_sen),
                                ChiefRays(cd[i, j], cs[i, j]), settings)
                 for i in range(f.shape[0]) for j, wl in enumerate(wls)]
        geo = _CallGeometry(f, wls, depth, (cd, None, None), [None] * f.shape[0])
        return self._finish_fields((list(range(f.shape[0])), built), geo)

    def _engine_fields(self, fields) -> torch.Tensor:
        """The call's field points as an (F, 2) float64 tensor; ValueError naming the first angle field at or beyond
        :data:`~raywave.utils.checks.MAX_FIELD_ANGLE` (the engine samples the entrance-pupil plane: a fisheye's wider
        field is for the geometric analyses)."""
        f = _as_fields(fields, torch.float64, self.lens.device)
        if self.lens.field_type == "angle" and bool((f.abs() >= MAX_FIELD_ANGLE).any()):
            raise ValueError(f"field {f[(f.abs() >= MAX_FIELD_ANGLE).any(-1)][0].tolist()}: the ray-wave engine "
                             f"samples the entrance-pupil plane and traces field angles below {MAX_FIELD_ANGLE:g}°; a "
                             "fisheye's wider field is traced by the geometric analyses (trace, spot, info)")
        return f

    def _accurate_geometry(self, f: torch.Tensor, wls: list[float], depth, crop_reach: float = 0.0) -> "_CallGeometry":
        """What the accurate construction of the call's sources ``f`` (F, 2) × ``wls`` (µm) shares, each traced once
        for the call (whatever the number of its sources, issue 43): the chief rays, the mirror pairing, and for the
        sources that are built (not mirror images) their lit footprints, the DOE-aperture diagnostics, the entrance
        pupil, the exit-pupil planes, the stop rim's images, (adaptive edge step) each source's step and its
        Fresnel step's error estimate for the PSF crop reaching ``crop_reach`` mm (0: unknown), and (exact edge
        step, or an adaptive source that takes it) the chief rays on the exit pupil."""
        optics = self.optics  # the lens, or its image-space view (one object for the whole call: run_batched groups by it)
        z_doe, z_sen = self.doe_z(), self.sensor_z()
        cd, cs, cuv = _quiet_chief_rays(optics, f, wls, depth, z_doe, z_sen)
        axes = symmetric_axes(self.lens, self.doe, self.oversample) if self.mirror else (False, False)
        src = mirror_sources(f, axes) if any(axes) else [None] * f.shape[0]
        todo = [i for i, s_ in enumerate(src) if s_ is None]
        geo = _CallGeometry(f, wls, depth, (cd, cs, cuv), src, todo=todo, crop_reach=crop_reach)
        ft = f[torch.tensor(todo, dtype=torch.long, device=f.device)]
        wls_t = torch.tensor(wls, dtype=torch.float64, device=self.lens.device)
        # the lit footprints and the DOE-aperture diagnostic (a mirror image's are its source's) of every built
        # field, from one aimed trace of both ray sets
        # the built sources' chief-ray aim, shared by their footprints, edge rays and stop grids (one aiming)
        with warnings.catch_warnings():  # vignetting is reported once, by the PSF (as footprints_and_clippings does)
            warnings.simplefilter("ignore", VignettingWarning)
            geo.aim = chief_aim(optics, ft, wls_t, depth=depth)
        z_xps = self._exit_pupil_planes(wls)
        boxes, geo.clips, *vig = footprints_and_clippings(optics, self.doe, ft, wls_t, depth, z_doe, folds=True,
                                                          chief=geo.aim, vignetting=z_xps is not None)
        geo.boxes = [[False if b is None else b for b in row] for row in boxes]
        geo.entrance = entrance_pupil(optics)  # one lens: once for every field
        if z_xps is not None:
            geo.vignetting = vig[0]  # warned by the caller (doe_fields, psf_result), at its own caller
            rims = self.edge_rim_images(ft, wls, depth)  # one trace for every source and wavelength
            if self._rim_images is not None:
                rims = self._rim_images(optics, ft, wls, depth, rims)
            steps, ests = None, None
            if self.edge_step == "adaptive":  # every built source's step from one trace of their edge rays
                steps = adaptive_edge_steps(optics, self.doe, ft, wls, depth, (z_doe, z_sen), chief=geo.aim)
                steps, ests = self._fresnel_estimates(steps, rims, wls, crop_reach)
            # the Fresnel step needs no chief ray on the exit-pupil plane
            cx = [[None] * ft.shape[0] for _ in wls]
            if self.edge_step not in ("fresnel", "adaptive") or any("asm" in row for row in steps or []):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", VignettingWarning)
                    cx = [chief_rays(optics, ft, torch.tensor([wl], dtype=torch.float64, device=optics.device),
                                     depth, zx, z_sen)[0][:, 0] for wl, zx in zip(wls, z_xps)]
            geo.edge = (z_xps, rims, cx, steps)
            geo.estimates = ests
            if self.edge_step in ("fresnel", "adaptive"):  # the Fresnel step's ripple band, for every source at once
                geo.reach = _edge_reaches(optics, rims, cs, todo, wls, (z_doe, z_sen, crop_reach))
        return geo

    def _accurate_group(self, geo: "_CallGeometry", members: list[int], nodes: int, check: bool,
                        staged: dict | None = None) -> tuple:
        """The accurate fields of the call's sources ``members`` (indices into ``geo.f``; every mirror image's source
        among them), built together (:func:`raywave.hybrid.coherent.run_batched`): ``(members, flat field-major
        list of their F·W :class:`DOEField`)``. A mirror image (:func:`~raywave.hybrid.mirror.mirror_sources`, with
        :attr:`mirror` on a mirror-symmetric lens) is not built: its fields are its source's mirrored
        (:func:`~raywave.hybrid.mirror.mirror_field`; the same to the construction's rounding, at a quarter of the
        field stage's cost for a map's symmetric grid). ``staged``: the constructions of the built sources' rows
        with their ray stage done (:meth:`_ray_stage`; taken out of it here), else built from the start."""
        rows = [geo.row[i] for i in members if geo.src[i] is None]  # rows of the built sources (geo.todo)
        if staged is None:
            done = run_batched(self._accurate_constructions(geo, rows, nodes, check))
        else:
            done = run_batched([c for r in rows for c in staged.pop(r)])
        nw = len(geo.wls)
        at = {geo.todo[r]: k for k, r in enumerate(rows)}
        sim = self.doe.sim_grid(self.oversample)
        src = geo.src
        # the mirror images' fields together (their centres negated by one op for all)
        images = iter(mirror_fields([(done[at[src[i][0]] * nw + j], src[i][1], src[i][2])
                                     for i in members if src[i] is not None for j in range(nw)], sim))
        return members, [done[at[i] * nw + j] if src[i] is None else next(images)
                         for i in members for j in range(nw)]

    def _accurate_constructions(self, geo: "_CallGeometry", rows: list[int], nodes: int, check: bool) -> list:
        """The accurate field constructions (generators, :func:`raywave.hybrid.coherent.run_batched` runs them
        together: their ray traces batched per round) of the built sources ``rows`` (indices into ``geo.todo``) ×
        wavelength, field-major: the stop edge on the DOE plane or at the exit pupil."""
        optics, z_doe, z_sen = self.optics, self.doe_z(), self.sensor_z()
        # the built sources' (source, wavelength) elements from one gather and one unbind per field (indexing each
        # dispatches ~25 ops; unbinding every source's row ~5 per source)
        built = [geo.todo[r] for r in rows]
        cd, cs, cuv = (_source_elements(t, built, len(geo.wls)) for t in geo.chief)
        settings = FieldSettings(nodes=nodes, oversample=self.oversample, check=check, method=self.edge_step,
                                 crop_reach=geo.crop_reach)
        go = self._go_errors(geo, rows) if check else None
        nw = len(geo.wls)
        media = [_medium_index(optics, wl) for wl in geo.wls]  # (one host read per wavelength, not per source)
        # the sources' field rows and the GO errors' per-construction rows from one unbind each (issue 43: indexing
        # each construction's dispatched four ops)
        f_rows = geo.f.unbind(0) if rows else ()
        if go is not None:
            go = (go[0].unbind(0), go[1].flatten(0, 1).unbind(0))
        out = []
        for k, r in enumerate(rows):
            i = geo.todo[r]
            for j, wl in enumerate(geo.wls):
                source = Source(f_rows[i], wl, geo.depth, order=None if geo.orders is None else geo.orders[i])
                if geo.edge is None:
                    out.append(accurate_field_steps(optics, self.doe, source, Planes(z_doe, z_sen),
                                                    ChiefRays(cd[i][j], cs[i][j], uv=cuv[i][j]), settings,
                                                    Known(geo.boxes[r][j], geo.entrance, medium=media[j])))
                else:
                    z_xps, rims, cx, steps = geo.edge
                    out.append(exit_pupil_field_steps(optics, self.doe, source, Planes(z_doe, z_sen, z_xps[j]),
                                                      ChiefRays(cd[i][j], cs[i][j], cx[j][r], cuv[i][j]), settings,
                                                      Known(geo.boxes[r][j], geo.entrance, rims[j][r],
                                                            None if steps is None else steps[r][j],
                                                            None if go is None else (go[0][j], go[1][k * nw + j]),
                                                            ... if geo.reach is None else geo.reach[r][j],
                                                            media[j], self._edge_transfers,
                                                            None if geo.estimates is None else geo.estimates[r][j])))
        return out

    def edge_rim_images(self, fields, wavelengths: list, depth) -> list:
        """The stop rim's images ``[W][F]`` of the sources ``fields`` (F, 2) × ``wavelengths`` (µm) as the exit-pupil
        edge uses them (:func:`~raywave.hybrid.coherent.stop_edge.stop_rim_images_all` on :attr:`optics`, one trace):
        images farther than :data:`EXIT_PUPIL_FAR` from the DOE plane, or at infinity, placed that far before it."""
        return stop_rim_images_all(self.optics, fields, wavelengths, depth, bound=(self.doe_z(), EXIT_PUPIL_FAR))

    def edge_step_estimates(self, rims: list, wavelength: float, crop_reach: float) -> list:
        """The Fresnel edge step's error estimate (:func:`~raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates`:
        ``(zones, zones_max, curvature)`` or None) of each source's rim images ``rims`` (F,) at ``wavelength`` µm,
        for a PSF crop reaching ``crop_reach`` mm on the sensor, on this lens's DOE and sensor planes and simulation
        pitch."""
        optics = self.optics
        return fresnel_step_estimates(rims, (wavelength, _medium_index(optics, wavelength)),
                                      (self.doe_z(), self.sensor_z()), crop_reach, self.doe.pitch / self.oversample,
                                      obscuration_fraction(optics))

    def _fresnel_estimates(self, steps: list, rims: list, wls: list, crop_reach: float) -> tuple:
        """The adaptive edge step's ``steps`` ``[R][W]`` with "fresnel" turned to "asm" where the Fresnel step's
        error estimate rejects it (:func:`~raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates` from the rim
        images ``rims`` ``[W][R]``, for a crop reaching ``crop_reach`` mm; the construction then takes the exact
        step where it fits, else keeps the Fresnel step with a warning), and the estimates ``[R][W]``."""
        per_wl = [self.edge_step_estimates(rims[j], wl, crop_reach) if any(row[j] == "fresnel" for row in steps)
                  else [None] * len(steps) for j, wl in enumerate(wls)]
        ests = [[per_wl[j][r] for j in range(len(wls))] for r in range(len(steps))]
        steps = [["asm" if st == "fresnel" and not fresnel_step_holds(e) else st for st, e in zip(row, erow)]
                 for row, erow in zip(steps, ests)]
        return steps, ests

    def _go_errors(self, geo: "_CallGeometry", rows: list[int]):
        """The geometric-optics phase errors of the exit-pupil edge's Fresnel step for the built sources ``rows``
        (indices into ``geo.todo``) × the call's wavelengths, from one trace of all their stop grids
        (:func:`~raywave.hybrid.coherent.exit_pupil.go_phase_errors`: ``(zs (W, P), error (R, W, P))``); None
        where no source can take that step (the DOE-plane edge, the exact step, a DOE plane before the exit pupil, or
        no source with the Fresnel step)."""
        if geo.edge is None or self.edge_step not in ("fresnel", "adaptive") or not rows or geo.orders is not None:
            return None  # (a mid-system DOE's orders: each source computes its own)
        z_xps, _, _, steps = geo.edge
        z_doe = self.doe_z()
        if not any(zx < z_doe for zx in z_xps):
            return None
        if steps is not None and not any(steps[r][j] == "fresnel" for r in rows for j in range(len(geo.wls))):
            return None
        idx = torch.tensor([geo.todo[r] for r in rows], dtype=torch.long, device=geo.f.device)
        # the shared chief-ray aim where these are all the built sources (an aim's Newton runs over its whole batch:
        # a part of them aims on its own)
        aim = geo.aim if list(rows) == list(range(len(geo.todo))) else None
        return go_phase_errors(self.optics, geo.f[idx], geo.wls, geo.depth, None, (z_xps, z_doe), aim,
                               band_fold=True)

    def _ray_stage(self, geo: "_CallGeometry", groups: list[list[int]], nodes: int, check: bool) -> dict:
        """The ray stage of the accurate constructions of every built source in ``groups`` (their aiming, Newton
        inversion and node traces: :func:`~raywave.hybrid.coherent.run_batched` with ``pause=True``), in one pass
        for all the groups (issue 43: one batched trace per round for the call instead of one per group): ``{row in
        geo.todo: [W] constructions paused before their field stage}`` (or their fields where they finished)."""
        rows = [geo.row[i] for members in groups for i in members if geo.src[i] is None]
        nw = len(geo.wls)
        done = run_batched(self._accurate_constructions(geo, rows, nodes, check), pause=True)
        return {r: done[k * nw:(k + 1) * nw] for k, r in enumerate(rows)}

    def _stage_chunks(self, geo: "_CallGeometry", groups: list[list[int]], nodes: int) -> list[list[list[int]]]:
        """``groups`` (:meth:`_field_groups`) in consecutive runs whose ray stages are done together
        (:meth:`_ray_stage`): each run's constructions hold at most about :data:`RAY_STAGE_NODES` nodes (estimated
        ``(2·nodes)²`` each: the footprint's grid and its margin), which bounds the paused constructions' node
        maps and the batched Newton rounds' rays."""
        per = (2 * nodes) ** 2 * len(geo.wls)
        chunks, cur, size = [], [], 0
        for members in groups:
            est = per * sum(1 for i in members if geo.src[i] is None)
            if cur and size + est > RAY_STAGE_NODES:
                chunks.append(cur)
                cur, size = [], 0
            cur.append(members)
            size += est
        if cur:
            chunks.append(cur)
        return chunks

    def _field_groups(self, geo: "_CallGeometry") -> list[list[int]]:
        """The call's sources in groups whose DOE-plane fields are built and propagated together (issue 43): every
        built source with its mirror images, the groups cut where their envelopes' estimated size (the lit
        footprints with a margin, complex128) would pass :data:`FIELD_GROUP_BYTES` (on an accelerator
        :data:`FIELD_GROUP_BYTES_ACCELERATOR`) (the fields of one group are
        held at once; the call's traces are shared by all groups)."""
        p = self.doe.pitch / self.oversample
        cap = FIELD_GROUP_BYTES
        if devices.accelerator(geo.f):
            cap = max(FIELD_GROUP_BYTES, min(FIELD_GROUP_BYTES_ACCELERATOR, accelerator_cap(geo.f.device)))
        deps: dict = {i: [i] for i in geo.todo}
        for i, s_ in enumerate(geo.src):
            if s_ is not None:
                deps[s_[0]].append(i)
        groups, cur, size = [], [], 0.0
        for r, i in enumerate(geo.todo):
            est = 0.0
            for b in geo.boxes[r]:
                if b is not False:
                    w, h = b[1] - b[0], b[3] - b[2]
                    m = 0.1 * max(w, h) + 16 * p  # the edge's ripple band and the window's margin, roughly
                    est += 16.0 * ((w + 2 * m) / p + 1) * ((h + 2 * m) / p + 1)
            est *= len(deps[i])
            if cur and size + est > cap:
                groups.append(cur)
                cur, size = [], 0.0
            cur.extend(deps[i])
            size += est
        if cur:
            groups.append(cur)
        return groups

    def _finish_fields(self, group: tuple, geo: "_CallGeometry", pending: tuple | None = None) -> list:
        """The fields of ``group`` = ``(members, built)`` (``built``: the flat field-major list of the members' F·W
        :class:`DOEField`) as a nested ``[F][W]`` list, each completed: the DOE-aperture diagnostic (``geo.clips``:
        ``[F][W]`` of (blocked fraction, beam half-width mm, folded fraction) of the built sources, a mirror image
        takes its source's; None: the field's own) and the chief ray's slopes ``chief_tan``; warns (pointing at the
        caller of :meth:`doe_fields`) where no light reaches the DOE, and (at once, or with ``pending`` = ``(clipped,
        folded)`` lists collected for one warning per call) where the DOE aperture clips the beam or the rays cross
        before the DOE plane."""
        members, built = group
        nw, out, clipped, folded = len(geo.wls), [], [], []
        tans = _chief_tans(geo.chief[0], members)
        # a mirror image is dark where its source is (its envelope is the source's, mirrored); the built fields'
        # flags from one host read (issue 43: not one per field)
        own_fields = [(i, j, built[k * nw + j]) for k, i in enumerate(members) if geo.src[i] is None for j in range(nw)]
        dark = dict(zip([(i, j) for i, j, _ in own_fields], _dark_many([fd for _, _, fd in own_fields])))
        resolve_band_infos(built)  # the ripple bands' blocked power (FieldInfo.band_clipped): one host read
        for k, i in enumerate(members):
            row = []
            own = i if geo.src[i] is None else geo.src[i][0]
            for j, wl in enumerate(geo.wls):
                fd = built[k * nw + j]
                if dark[own, j] if (own, j) in dark else _dark(fd):
                    warnings.warn(f"field {geo.f[i].tolist()} at {wl:g} µm: no light reaches the DOE (every ray is "
                                  "vignetted or misses the DOE aperture); its PSF is all zeros",
                                  VignettingWarning, stacklevel=3)
                if geo.clips is not None:
                    fd.clipped, fd.beam_half, fold = geo.clips[geo.row[own]][j]
                    if fold > 0:
                        folded.append((fold, geo.f[i].tolist(), wl))
                if fd.clipped > CLIP_WARN:  # the field as host values, read once for the call (not per warning)
                    clipped.append((fd, geo.host_fields()[i]))
                elif fd.info.band_clipped > BAND_CLIP_WARN:
                    if fd.info.band_total:  # the window's whole loss: the ripples' share beyond the beam's
                        fd.info = replace(fd.info, band_clipped=max(fd.info.band_clipped - fd.clipped, 0.0),
                                          band_total=False)
                    if fd.info.band_clipped > BAND_CLIP_WARN:  # the beam fits, the edge's ripple band does not
                        clipped.append((fd, geo.host_fields()[i], "band"))
                fd.chief_tan = tans[k][j]
                row.append(fd)
            out.append(row)
        if pending is None:
            self._warn_clipped(clipped)
            self._warn_caustic(folded)
        else:
            pending[0].extend(clipped)
            pending[1].extend(folded)
        return out

    def _warn_vignetting(self, geo: "_CallGeometry", stacklevel: int) -> None:
        """One :class:`~raywave.hybrid.coherent.VignettingEdgeWarning` (``stacklevel`` 1: pointing at the method that
        calls this; 2: at its caller, as :meth:`doe_fields` passes; 3: one further, :meth:`_accurate_psfs`) for the call's
        sources (a mirror image's its source's) whose vignetting by a surface other than the stop, or whose rim's
        nearness to one (:func:`~raywave.hybrid.coherent.vignetting.vignetting_edges`: ``geo.vignetting`` ``{(row in
        geo.todo, w): VignettingEdge}``), may cost more than :data:`~raywave.hybrid.coherent.vignetting.
        VIGNETTING_WARN`."""
        loud = {k: e for k, e in (geo.vignetting or {}).items() if e.estimate >= VIGNETTING_WARN}
        if not loud:
            return
        entries = []
        for i, s_ in enumerate(geo.src):
            own = geo.row[i if s_ is None else s_[0]]
            for j, wl in enumerate(geo.wls):
                e = loud.get((own, j))
                if e is not None:
                    entries.append((e.estimate, e.length, e.lost, e.surface,
                                    f"field {[float(v) for v in geo.host_fields()[i]]} at {wl:g} µm", e.clearance))
        warnings.warn(VignettingEdgeWarning("", entries, "call"), stacklevel=stacklevel + 1)

    def _warn_caustic(self, folded: list) -> None:
        """One :class:`~raywave.hybrid.coherent.CausticWarning` (pointing at the caller of :meth:`doe_fields`) for
        the sources whose rays cross before the DOE plane: ``folded`` a list of ``(fraction of the stop grid's cells
        folded, field, wavelength µm)``."""
        if not folded:
            return
        frac, field, wl = max(folded)
        warnings.warn(f"{len(folded)} source(s): the rays cross between the lens and the DOE plane "
                      f"{self.doe_distance:g} mm after the last vertex (a caustic before it; worst {frac:.1%} of the "
                      f"stop grid folded, field {field} at {wl:g} µm): the accurate field, built from a one-to-one "
                      "ray map, is wrong there. Move the DOE plane towards the lens", CausticWarning, stacklevel=4)

    def _warn_clipped(self, clipped: list) -> None:
        """One :class:`DOEApertureWarning` (pointing at the caller of :meth:`doe_fields`, through
        :meth:`_finish_fields`) for the ``clipped`` sources, a list of ``(DOEField, field (2,))`` whose power the DOE
        aperture blocks by more than :data:`CLIP_WARN`, and one of ``kind`` "band" for those given as ``(DOEField,
        field (2,), "band")``, whose stop-edge ripple band it blocks by more than :data:`BAND_CLIP_WARN`: a call's many
        sources give one line a kind, not one each (and :func:`raywave.imaging.psf_map` merges its calls' into one
        for the map)."""
        beam = [e for e in clipped if len(e) == 2]
        if beam:
            entries = [(float(fd.clipped), float(fd.beam_half),
                        f"field {[float(v) for v in field]} at {fd.wavelength:g} µm") for fd, field in beam]
            warnings.warn(DOEApertureWarning("", entries, self.doe.size, "call"), stacklevel=4)
        band = [e for e in clipped if len(e) == 3]
        if band:
            entries = [(float(fd.info.band_clipped), float(fd.info.band_half),
                        f"field {[float(v) for v in field]} at {fd.wavelength:g} µm"
                        + (f" (and {100 * float(fd.clipped):.2g} % within the beam's edge)" if fd.clipped > 0 else ""))
                       for fd, field, _ in band]
            warnings.warn(DOEApertureWarning("", entries, self.doe.size, "call", "band"), stacklevel=4)

    # ------------------------------------------------------------------ steps 3-4: DOE, propagation, sensor
    def propagate(self, fd: DOEField, ks: int, propagation_dtype=torch.complex128):
        """PSF ``(ks, ks)``, centre (2,) and energy outside the crop for one :class:`DOEField`.

        ``propagation_dtype=torch.complex64`` propagates in single precision after the phase was formed in
        float64 (safe: the measured PSF error is ~1e-6, see tests/test_hybrid_precision.py).

        Differentiable with respect to the DOE → sensor distance (:meth:`sensor_distance`, i.e. the lens's
        last thickness: focus) for fields built by :meth:`doe_fields` (not detached ones: a cache stands for a
        frozen lens): a zero-valued ``dz`` enters the propagation (``propagate_window(dz=)``, or ``z + dz`` on
        the full grid) and moves the crop centre along the chief ray by ``chief_tan·dz``; exact to first order
        (the discrete choices — windows, FFT sizes, band rows — are those of the current distance)."""
        ps, p = self.sensor_pitch, fd.pitch
        center_t, dz = self._chief_image(fd)
        xc, yc = (float(c) for c in center_t.detach())
        half = ks // 2
        psf_origin = (xc - half * ps, yc - half * ps)
        crop_origin = center_t - half * ps  # differentiable: the crop follows the chief ray
        full_grid = fd.full_grid
        # full-grid path: the crop's derivative goes through the pixel overlaps (piecewise-constant model)
        integrate_origin = crop_origin if full_grid else psf_origin
        u = self.doe.modulate(fd.field, self.oversample).envelope  # exp(iφ) of the DOE on the field's grid
        with torch.no_grad():  # a diagnostic (energy outside the crop); the DOE's phase does not change it
            power = torch.linalg.vector_norm(torch.view_as_real(fd.envelope)).square() * p * p  # one pass
        if float(power.detach()) == 0.0:
            z = torch.zeros((ks, ks), dtype=torch.float64, device=u.device)
            return z, center_t, torch.ones((), dtype=torch.float64, device=u.device)
        u = u.to(propagation_dtype)
        # output window on the simulation pitch covering the ks×ks sensor pixels, plus a margin for the
        # 2× Fourier upsampling of the field (its intensity needs the p/2 grid)
        m = _OUT_MARGIN
        lo_x, lo_y = psf_origin[0] - 0.5 * ps - m * p, psf_origin[1] - 0.5 * ps - m * p
        span = ks * ps / p
        if not (math.isfinite(span) and span < 2**31):
            raise ValueError(f"the {ks}×{ks} PSF crop of {ps:g} mm sensor pixels spans {span:g} simulation samples of "
                             f"{p:g} mm: not a usable window (check the sensor pitch and the DOE pitch)")
        n_out = ceil_samples(span) + 2 + 2 * m
        if full_grid:
            out, out_origin = _full_grid_window(u, fd, dz, (lo_x, lo_y), n_out)
        else:
            out, out_origin = self._lattice_window(u, fd, dz, crop_origin, (xc, yc), lo_x, n_out)
        del u  # the DOE-plane window is no longer needed (autograd keeps what its backward needs)
        # intensity on a q-times finer grid (q ≥ 2: |U|² has twice the field's bandwidth), integrated over the
        # sensor pixels through its cubic interpolant; computed on the 2× grid (the q grid's weights folded onto it)
        q = self.intensity_upsample
        crop = integrated_upsampled_intensity(out, q, p, out_origin, ps, integrate_origin, (ks, ks),
                                              _edge_taper(out.shape[-2:], _OUT_MARGIN - 2, out.device), refine=True)
        total = crop.sum()
        outside = 1.0 - total / power.to(torch.float64)
        psf = safe_div(crop, total, total > 0)  # a crop with no light stays 0, with finite gradients
        return psf, center_t, outside

    def _chief_image(self, fd: DOEField):
        """The chief ray's image point on the sensor, float64 (2,) mm, and the zero-valued 0-d ``dz`` (or None)
        that carries d(DOE → sensor distance)/dθ into :meth:`propagate`."""
        center_t = torch.stack([torch.as_tensor(c, dtype=torch.float64) for c in fd.center])
        # the sensor distance: fd.z (a float, used for every discrete choice) plus a zero-valued dz that carries
        # d(distance)/dθ (the last thickness) into the propagation and into the chief ray's image point, which
        # slides along the chief ray by tan·dz. Only for live fields from doe_fields (they record chief_tan);
        # detached (cached) fields and other models' fields (raywave.models) keep a fixed sensor.
        dz = self._sensor_dz() if fd.chief_tan is not None else None
        if dz is not None:
            dz = dz.to(center_t.device)
            center_t = center_t + torch.tensor(fd.chief_tan, dtype=torch.float64, device=center_t.device) * dz
        return center_t, dz

    def _lattice_window(self, u, fd: DOEField, dz, crop_origin, center, lo_x: float, n_out: int):
        """The field ``u`` (the DOE's phase applied) propagated to the sensor window of ≥ ``n_out`` samples from
        ``lo_x`` on the simulation pitch, on the lattice through the chief ray's image point ``center`` (mm; a
        symmetric PSF stays symmetric), band-limited windowed angular spectrum; returns ``(field, origin)``. The
        window moves with the chief ray: a zero-valued shift carries d(center)/dθ (``crop_origin``) into it."""
        p, (xc, yc) = fd.pitch, center
        kk = max(ceil_samples((xc - lo_x) / p), ceil_samples((lo_x + n_out * p - xc) / p))
        out_origin = (xc - kk * p, yc - kk * p)
        n_out = 2 * kk + 1
        shift = crop_origin - crop_origin.detach() if crop_origin.requires_grad else None
        transfer = self._transfer(u, p, fd, out_origin, n_out, dz is not None or shift is not None)
        out = propagate_window(fd.field.with_envelope(u), Grid(out_origin, p, (n_out, n_out)), fd.z, shift=shift, dz=dz,
                               transfer=transfer).envelope
        return out, out_origin

    def _transfer(self, u, p, fd: DOEField, out_origin, n_out: int, weight_derivative: bool = False):
        """The window transfer function for this geometry, memoised (the 8 most recent window pairs, each a
        band-only :class:`~raywave.wave.propagation.WindowTransfer` of ≤ ~6 MB; ~2.5× that with
        ``weight_derivative``, for a PSF differentiated with respect to the sensor distance)."""
        key = (tuple(u.shape[-2:]), n_out, p, fd.wavelength, float(fd.z), fd.n, fd.carrier,
               round((out_origin[0] - fd.origin[0]) / p, 9), round((out_origin[1] - fd.origin[1]) / p, 9), u.device,
               weight_derivative)
        return recent(self._transfer_cache, key,
                      lambda: window_transfer(fd.field.with_envelope(u), Grid(out_origin, p, (n_out, n_out)), fd.z,
                                              weight_derivative=weight_derivative), 8)

    def crop_reach(self, ks: int) -> float:
        """How far (mm) a ``ks``-pixel PSF crop reaches from its centre pixel's centre: its half-diagonal,
        ``(ks/2 + 1/2)·√2`` sensor pixels (:meth:`doe_fields` ``crop_reach``)."""
        return math.sqrt(0.5) * (int(ks) + 1) * self.sensor_pitch

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None, mode: str = "accurate",
                   rays: int | None = None, cache=None, propagation_dtype=torch.complex128, **field_kw) -> PSFResult:
        """PSFs with their centres and the energy outside the crop (see :class:`PSFResult`).

        Args: as :meth:`doe_fields` (``field_kw``: ``full_grid``, ``generator``, ``trace_dtype``, ``check``,
        ``crop_reach``: default :meth:`crop_reach` of ``ks``),
        plus ``ks`` (PSF size in sensor pixels), ``cache`` (the output of :meth:`doe_fields`, e.g. detached
        for a frozen refractive lens; then the field arguments are taken from it) and ``propagation_dtype``
        (see :meth:`propagate`)."""
        if int(ks) < 1:
            raise ValueError(f"ks must be >= 1, got {ks}")
        if cache is None and mode == "accurate" and not (set(field_kw) - {"check", "trace_dtype"}):
            if field_kw.get("trace_dtype", torch.float64) != torch.float64:
                raise ValueError("the accurate mode traces in float64 only (its rays land on their nodes to 1e-10 mm)")
            psf, center, outside, nr, clip = self._accurate_psfs(fields, wavelengths, depth, rays,
                                                                 field_kw.get("check", True), ks, propagation_dtype)
            wls = self.wavelength_list(wavelengths)
            self._check_sensor(center)
            psf = self._checked(psf, [wls] * psf.shape[0])
            return PSFResult(psf, center, outside, self.sensor_pitch, nr,
                             torch.tensor(clip, dtype=torch.float64, device=center.device))
        # the crop's own reach unless the caller gives one (a wider reach for fields reused by a larger crop)
        field_kw = {"crop_reach": self.crop_reach(ks), **field_kw}
        fds = cache if cache is not None else self.doe_fields(fields, wavelengths, depth, mode, rays, **field_kw)
        psf, center, outside, nr = self.propagate_fields(fds, ks, propagation_dtype)
        clip = [[fd.clipped for fd in row] for row in fds]
        self._check_sensor(center)
        psf = self._checked(psf, [[fd.wavelength for fd in row] for row in fds], connect=cache is None)
        return PSFResult(psf, center, outside, self.sensor_pitch, nr,
                         torch.tensor(clip, dtype=torch.float64, device=center.device))

    def _accurate_psfs(self, fields, wavelengths, depth, rays, check: bool, ks: int, propagation_dtype):
        """:meth:`psf_result`'s accurate path without a cache (issue 43): the call's shared traces once
        (:meth:`_accurate_geometry`), the ray stage of many groups in one pass (:meth:`_ray_stage`), then per group
        of sources (:meth:`_field_groups`, bounded by the fields' memory) the fields built together and propagated
        in batches (:meth:`propagate_fields`), each group's fields dropped before the next is built. Returns ``(psf (F, W, ks, ks), centres (F, W, 2), energy outside (F, W),
        rays (F, W), clipped fractions [F][W])``; the aperture and caustic warnings once for the call."""
        f = self._engine_fields(fields)
        wls = self.wavelength_list(wavelengths)
        geo = self._accurate_geometry(f, wls, depth, self.crop_reach(ks))
        pending: tuple = ([], [])
        order, parts, clip = [], [], {}
        nodes = rays or 64
        for chunk in self._stage_chunks(geo, self._field_groups(geo), nodes):
            staged = self._ray_stage(geo, chunk, nodes, check)  # the traces of all the chunk's groups at once
            for members in chunk:
                fds = self._finish_fields(self._accurate_group(geo, members, nodes, check, staged), geo, pending)
                parts.append(self.propagate_fields(fds, ks, propagation_dtype))
                clip.update({i: [fd.clipped for fd in row] for i, row in zip(members, fds)})
                order.extend(members)
                del fds
        self._warn_clipped(pending[0])
        self._warn_caustic(pending[1])
        self._warn_vignetting(geo, stacklevel=3)
        if len(parts) == 1 and order == list(range(f.shape[0])):
            psf, center, outside, nr = parts[0]
        else:
            back = torch.argsort(torch.tensor(order, dtype=torch.long, device="cpu"))
            psf, center, outside, nr = (torch.cat(ts)[back.to(ts[0].device)] for ts in zip(*parts))
        return psf, center, outside, nr, [clip[i] for i in range(f.shape[0])]

    def propagate_fields(self, fds, ks: int, propagation_dtype=torch.complex128):
        """Steps 2–4 for a nested list ``[F][W]`` of :class:`DOEField` (this engine's, or a comparison model's):
        PSFs ``(F, W, ks, ks)``, centres ``(F, W, 2)``, energy outside ``(F, W)`` and rays ``(F, W)``; what
        :meth:`psf_result` and :func:`raywave.models.base.propagate_fields` share.

        The sources are propagated in batches (:mod:`raywave.hybrid.batched`: one padded window, one FFT size, one
        transfer tensor and one pixel integration per batch of a wavelength); the paper's full-grid fields and fields
        without light go through :meth:`propagate` one at a time. Each PSF equals :meth:`propagate`'s to the
        sampling of its kernel's spectrum on the batch's (larger) FFT grid (≤ 1e-7 relative L1,
        tests/test_hybrid_batched_propagation.py); differentiable like it."""
        flat = [fd for row in fds for fd in row]
        nf, nw = len(fds), (len(fds[0]) if fds else 0)
        sensor = SensorWindow(int(ks), self.sensor_pitch, self.intensity_upsample)
        centers, dz = self._chief_images(flat)
        host = centers.detach().cpu().tolist()
        lattice = [Planned(i, fd, tuple(host[i])) for i, fd in enumerate(flat)
                   if not fd.full_grid and tuple(fd.grid.shape) != (1, 1)]
        done = {pl.index for pl in lattice}
        order, psfs, outs = [], [], []
        for i, fd in enumerate(flat):  # the full grid and the fields without light: one at a time
            if i not in done:
                psf, _, o = self.propagate(fd, ks, propagation_dtype)
                order.append(i), psfs.append(psf[None]), outs.append(o.reshape(1))
        elem = torch.empty((), dtype=propagation_dtype, device="meta").element_size()
        shared = FrameBands(lattice)  # (a mirror image's transfer function its source's: issue 47)
        for batch in plan_groups(lattice, sensor, elem):
            idx = [pl.index for pl in batch]
            cb = centers[torch.tensor(idx, dtype=torch.long, device=centers.device)]
            psf, o = propagate_group(self, batch, cb, dz if batch[0].fd.chief_tan is not None else None,
                                     propagation_dtype, sensor, shared)
            order.extend(idx), psfs.append(psf), outs.append(o)
        back = torch.argsort(torch.tensor(order, dtype=torch.long, device="cpu")).to(centers.device)
        psf = torch.cat(psfs)[back].reshape(nf, nw, ks, ks)
        outside = torch.cat(outs)[back].reshape(nf, nw)
        nr = torch.tensor([[fd.rays for fd in row] for row in fds], device="cpu")
        return psf, centers.reshape(nf, nw, 2), outside, nr

    def _chief_images(self, flat: list):
        """The chief rays' image points ``(N, 2)`` mm (float64) of the fields ``flat``, moved along their chief rays
        by the zero-valued sensor-distance ``dz`` for live fields (``chief_tan`` set: :meth:`_chief_image`), and that
        ``dz`` (None for a frozen lens)."""
        dev = self.lens.device
        if flat and all(isinstance(v, torch.Tensor) and v.ndim == 0 and v.device == flat[0].center[0].device
                        for fd in flat for v in fd.center):
            # every centre a pair of 0-d tensors (the accurate path): one stack for the call, not one per field
            centers = torch.stack([v for fd in flat for v in fd.center]).reshape(-1, 2).to(torch.float64).to(dev)
        else:
            centers = torch.stack([c if isinstance(c, torch.Tensor) else torch.tensor(c, dtype=torch.float64)
                                   for c in (_center_of(fd) for fd in flat)]).to(dev)
        live = [fd.chief_tan for fd in flat]
        dz = self._sensor_dz() if any(t is not None for t in live) else None
        if dz is not None:
            tans = torch.tensor([t if t is not None else (0.0, 0.0) for t in live], dtype=torch.float64, device=dev)
            centers = centers + tans * dz.to(dev)
        return centers, dz

    def psf(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None, mode: str = "accurate",
            rays: int | None = None, cache=None, **kw) -> torch.Tensor:
        """PSFs ``(F, W, ks, ks)`` (float64, each summing to 1); see :meth:`psf_result` for the arguments."""
        return self.psf_result(fields, wavelengths, ks, depth, mode, rays, cache, **kw).psf

    def _checked(self, psf: torch.Tensor, wls, connect: bool = True) -> torch.Tensor:
        """``psf`` (F, W, ks, ks) (``wls`` ``[F][W]`` their wavelengths, µm) refused when not finite (:class:`~raywave.utils.errors.NonFiniteError` naming the
        source), and (``connect``: fields traced now, not a cache, which stands for a frozen lens) kept connected
        to the autograd graph when no light reached the sensor in any source (all zeros): a zero-valued term in
        every trainable parameter, so ``backward()`` works and gives zero gradients instead of failing inside
        torch."""
        from raywave.utils.errors import NonFiniteError

        bad = ~torch.isfinite(psf).all(-1).all(-1)
        if bool(bad.any()):
            i, j = (int(v) for v in bad.nonzero()[0])
            raise NonFiniteError(
                f"the PSF of source {i} at {wls[i][j]:g} µm is not finite (NaN or inf): the DOE's phase is not "
                f"finite on its grid (check its phase model: coefficients, order, normalisation radius) or the lens "
                f"gives non-finite optical paths; DOE: {self.doe.extra_repr()}")
        if connect and torch.is_grad_enabled() and not psf.requires_grad:
            live = [q for q in self.parameters() if q.requires_grad]
            if live:
                psf = psf + sum(q.sum() for q in live).to(psf.dtype) * 0.0
        return psf

    def _check_sensor(self, center: torch.Tensor) -> None:
        size = self.lens.sensor_size
        if size is None:
            return
        hw, hh = 0.5 * size[0], 0.5 * size[1]
        bad = (center[..., 0].abs() > hw) | (center[..., 1].abs() > hh)
        if bool(bad.any()):
            i = tuple(int(v) for v in bad.nonzero()[0])
            x, y = (float(v) for v in center[i].detach())
            warnings.warn(f"PSF {i} is centred at ({x:.4g}, {y:.4g}) mm, outside the {size[0]:g}×{size[1]:g} mm "
                          "sensor: the crop lies (partly) off the sensor", SensorCropWarning, stacklevel=3)

    def extra_repr(self) -> str:
        return (f"doe_distance={self.doe_distance:g} mm, sensor_pitch={self.sensor_pitch * 1e3:g} µm, "
                f"oversample={self.oversample}, stop_edge={self.stop_edge!r}"
                + (f", edge_step={self.edge_step!r}" if self.stop_edge == "exit_pupil" else ""))
