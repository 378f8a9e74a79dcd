"""Value types of the field constructions (issue 43): the arguments of :func:`~raywave.hybrid.coherent.faithful.
faithful_field` and :func:`~raywave.hybrid.coherent.exit_pupil.exit_pupil_field` grouped by what they describe, so
that no construction takes more than ten parameters:

* :class:`Source`: the point source (field point, wavelength, object depth, field type);
* :class:`Planes`: where the planes lie (DOE, sensor, and for the exit-pupil edge the exit-pupil plane);
* :class:`ChiefRays`: the chief ray on those planes (and its entrance-plane point, when known);
* :class:`FieldSettings`: how the field is built (nodes or rays, oversampling, checks, the edge step);
* :class:`Known`: what a caller building many fields traced already (footprint, entrance pupil, stop-rim images).

Lengths mm, wavelengths µm. (The accurate construction's own value types, if any, live with it in
:mod:`raywave.hybrid.coherent.accurate`.)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ChiefRays", "FieldSettings", "Known", "Planes", "Source"]


@dataclass(frozen=True, eq=False)
class Source:
    """One point source: ``field`` (2,) (degrees, or mm on a finite object: ``field_type``, default the lens's), the
    vacuum ``wavelength`` (µm) and the object ``depth`` (mm from the first vertex; None: the lens's, ``inf``:
    distant); ``order``: an opaque per-source value that the lens's traces carry for this source
    (:func:`raywave.hybrid.coherent.tracing.per_source`: a mid-system DOE's diffraction order, issue 46; None:
    none)."""

    field: object
    wavelength: float
    depth: object = None
    field_type: str | None = None
    order: object = None


@dataclass(frozen=True)
class Planes:
    """The planes of a construction, z in mm from the first vertex: the DOE plane ``z_doe``, the sensor ``z_sensor``
    and, for the stop's edge at the exit pupil, the paraxial exit-pupil plane ``z_xp`` (None otherwise)."""

    z_doe: float
    z_sensor: float
    z_xp: float | None = None


@dataclass(frozen=True, eq=False)
class ChiefRays:
    """The chief ray (a :class:`~raywave.rays.RayBundle` of scalar batch each) at the DOE plane (``doe``) and at the
    sensor (``sensor``); on the exit-pupil plane (``xp``: the exact exit-pupil step only, else None); its
    entrance-plane point ``uv`` (2,) mm when known (saves aiming it again)."""

    doe: object
    sensor: object
    xp: object = None
    uv: object = None


@dataclass(frozen=True)
class FieldSettings:
    """How a DOE-plane field is built.

    * ``nodes``: accurate constructions: traced nodes across the larger side of the lit footprint;
    * ``n_rays``: the faithful construction's random rays;
    * ``oversample``: simulation samples per DOE pixel;
    * ``check``: the sampling checks (Nyquist, caustics) with their warnings;
    * ``full_grid``: faithful only: the whole DOE grid, no carrier (the paper's full propagation);
    * ``generator``: faithful only: the ``torch.Generator`` of the pupil samples (replayable);
    * ``trace_dtype``: faithful only: the ray-tracing precision (float32 only to study its failure);
    * ``ripple_zones``: exit-pupil edge: Fresnel zones of the edge's ripples kept (None: ``RIPPLE_ZONES``, widened
      to the edge waves' reach at the crop's centre: :func:`~raywave.hybrid.coherent.stop_edge.ripple_band`);
    * ``method``: exit-pupil edge step, "auto", "fresnel" or "asm" (:func:`~raywave.hybrid.coherent.exit_pupil.
      exit_pupil_field`);
    * ``rim_images``: exit-pupil edge: each node's edge sharp at its stop-rim point's own image;
    * ``virtual``: accurate construction: the plane may lie inside the lens (reached by extending the rays leaving
      the last surface along straight lines in the image medium), on the DOE's simulation lattice extended without
      bound and without the DOE aperture (the window indices may be negative or beyond the DOE grid);
    * ``stop_plane``: accurate construction: z (mm) of the plane where the stop's edge is sharp (the exit pupil): the
      edge then carries its Fresnel diffraction from there (:func:`~raywave.hybrid.coherent.stop_edge_factor`);
      None: the paper's sharp edge on the construction's plane;
    * ``crop_reach``: exact edge (and the caustic fallback): how far (mm) from the chief ray's landing the PSF crop
      reaches on the sensor (its half-diagonal; 0: unknown, the geometric spot only): the construction's lattice keeps
      the directions of the edge waves that land there (:func:`~raywave.hybrid.coherent.exit_pupil.asm_coarsening`);
    * ``sphere``: accurate construction: ``(x, y, z)`` mm of a point the wave converges to (the chief ray's sensor
      point): the envelope is taken relative to the spherical wave converging on it (carrier 0) instead of the chief
      ray's plane wave, so a lattice much coarser than the wave's own Nyquist pitch holds it (the caustic fallback's
      scaled carry, :func:`~raywave.hybrid.coherent.exit_pupil.scaled_fallback`); None: the plane wave.
    """

    nodes: int = 64
    n_rays: int = 100_000
    oversample: int = 1
    check: bool = True
    full_grid: bool = False
    generator: object = None
    trace_dtype: torch.dtype = torch.float64
    ripple_zones: float | None = None
    method: str = "auto"
    rim_images: bool = True
    virtual: bool = False
    stop_plane: float | None = None
    crop_reach: float = 0.0
    sphere: tuple | None = None


@dataclass(frozen=True, eq=False)
class Known:
    """What a caller that builds many fields traced already (None: traced by the construction): ``bbox`` the lit
    footprint on the DOE plane (:func:`~raywave.hybrid.coherent.footprints`; ``False``: none), ``entrance`` ``(z,
    radius)`` mm of the paraxial entrance pupil, ``stop_rim`` the stop rim's images
    (:func:`~raywave.hybrid.coherent.stop_rim_images`), ``edge_step`` the exit-pupil edge's step of
    ``method="adaptive"`` for this source, "doe", "fresnel" or "asm" (:func:`~raywave.hybrid.coherent.exit_pupil.
    adaptive_edge_steps`, decided for all of a call's sources from one trace; "asm": the Fresnel step's error
    estimate ``edge_estimate`` (:func:`~raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates`) rejects it,
    the exact construction taken where it fits), ``go_error`` ``(z (P,), error (P,))``
    this source's geometric-optics phase error (:func:`~raywave.hybrid.coherent.exit_pupil.go_phase_errors`, for
    all of a call's sources from one trace), ``reach`` the stop edge's waves' reach (Fresnel zones, or None: unknown)
    at the crop's centre on the DOE plane from ``stop_rim`` (:func:`~raywave.hybrid.coherent.stop_edge.
    edge_reach_many`, for all of a call's sources at once; ``...``: not given, computed by the construction),
    ``medium`` the image medium's refractive index at this source's wavelength (a host float, for all of a call's
    sources of that wavelength at once; None: read by the construction), ``transfers`` the engine's memo of the exact
    exit-pupil step's window transfer functions (an ``OrderedDict``: :func:`~raywave.hybrid.coherent.exit_pupil.
    edge_transfer`; None: built every time)."""

    bbox: object = None
    entrance: object = None
    stop_rim: object = None
    edge_step: str | None = None
    go_error: tuple | None = None
    reach: object = ...
    medium: float | None = None
    transfers: object = None
    edge_estimate: tuple | None = None


def check_types(where: str, source, planes, chief, settings) -> None:
    """TypeError naming the value types when a construction is called in its pre-issue-43 loose form."""
    for name, value, kind in (("source", source, Source), ("planes", planes, Planes), ("chief", chief, ChiefRays),
                              ("settings", settings, FieldSettings)):
        if not isinstance(value, kind):
            raise TypeError(f"{where}(lens, doe, source, planes, chief, settings) takes value types since issue 43: "
                            f"{name} must be a raywave.hybrid.coherent.settings.{kind.__name__}, got "
                            f"{type(value).__name__}")
