"""Coherent ray tracing to the DOE plane and the complex field it carries there.

For one point source and one wavelength the refractive lens delivers, just before the DOE plane
``z = z_doe``, a wave whose optical path (OPL, mm), irradiance and edges follow from rays traced in float64.
Two constructions of the sampled field on the DOE simulation grid are provided:

``accurate`` (default)
    Trace *exactly aimed* rays to a coarse regular grid of nodes on the DOE plane (Newton on the entrance-pupil
    coordinates, every ray landing on its node to 1e-10 mm), and read off at every node the smooth real
    quantities of the wave there: the optical path Φ (corrected to the node by Malus–Dupin,
    ``Φ(x) = OPL + n d⊥·(x − X)``, which also gives the exact first-order derivative with respect to the lens
    parameters), the amplitude ``sqrt(irradiance / d_z)`` from the ray density (the Jacobian of the
    pupil → DOE map, by differences over the node grid), and the signed distance to every vignetting edge
    (each aperture's ``slack``, converted to DOE-plane mm by its gradient). These are interpolated to the
    fine grid with third-order cubic convolution, and only then is the phase formed, ``exp(i k Φ)``; edges
    are anti-aliased from the distance. Nothing is averaged as phasors, so the result does not alias when
    there are far fewer rays than pixels. Assumes the pupil → DOE map does not fold (no caustic between the
    lens and the DOE), which holds when the DOE is well away from focus; a fold is reported.

``faithful``
    The paper's method: rays sampled over the pupil, each ray's complex amplitude ``d_z · exp(i k OPL)``
    spread bilinearly into its four neighbouring pixels (:func:`raywave.wave.field.splat_bilinear`).

With the stop's edge at the exit pupil (``HybridLens(stop_edge="exit_pupil")``, :func:`exit_pupil_field`) the
accurate field either is built on the exit-pupil plane and propagated to the DOE plane by the angular spectrum
(``method="asm"``, exact), or carries on the DOE plane the knife-edge Fresnel factor of the edge diffracting
from the exit pupil (``method="fresnel"``, :func:`stop_edge_factor`: any beam size, the DOE grid only).

Both return :class:`DOEField` objects: the field's *envelope* on a window of the simulation grid (the
carrier ``exp(i k n (α x + β y))`` of the chief ray removed, so off-axis light stays far below Nyquist), with
the DOE aperture applied and the DOE phase not yet applied. Phases are formed from float64 optical paths.

Modules (each name is importable from ``raywave.hybrid.coherent`` as before the split): :mod:`.record`
(:class:`DOEField`, :class:`SamplingWarning`), :mod:`.geometry` (chief rays, footprints, DOE clipping, windows),
:mod:`.tracing` (trace requests, batching, Newton aiming), :mod:`.stop_edge` (the Fresnel step, the stop rim's
images), :mod:`.accurate`, :mod:`.exit_pupil`, :mod:`.faithful` (the three constructions), :mod:`.settings` (their value
types: :class:`Source`, :class:`Planes`, :class:`ChiefRays`, :class:`FieldSettings`, :class:`Known`). Module-level limits
are read where they are used (e.g. ``coherent.exit_pupil.AUTO_ASM_SAMPLES``).
"""

from __future__ import annotations

from raywave.hybrid.coherent.record import (CausticWarning, DOEField, FieldInfo, SamplingWarning,  # noqa: F401
                                            StopEdgeWarning, VignettingEdgeWarning, _NEWTON_ITERS, _NEWTON_TOL)
from raywave.hybrid.coherent.geometry import (WINDOW_BYTES, _check_beyond_last_surface, _common_setup,
                                              _crop_to_lit, _empty_field, _footprint, _medium_index, _sim_grid,
                                              _warn_nyquist, check_window_memory, chief_rays, lit_box,
                                              window_bytes_per_sample, doe_clipping, doe_clippings, footprints,
                                              inside_doe)  # noqa: F401
from raywave.hybrid.coherent.tracing import (_Aim, _TraceRequest, _invert_to_nodes, _landing_and_jacobian, _nearest_fill,
                                             _solve2, _split_bundle, _trace_group, _trace_uv, run_batched,
                                             run_serial)  # noqa: F401
from raywave.hybrid.coherent.stop_edge import (INNER_TAIL, RIM_POINTS, RIPPLE_ZONES, _fresnel_scale,
                                               _nu_inner, _rim_z, _smoothstep, _zone_estimate, stop_edge_factor,
                                               stop_rim_images, stop_rim_images_all,
                                               stop_rim_images_many)  # noqa: F401
from raywave.hybrid.coherent.accurate import (accurate_field, accurate_field_steps, entrance_pupil)  # noqa: F401
from raywave.hybrid.coherent.exit_pupil import (AUTO_ASM_SAMPLES, MAX_XP_SAMPLES, exit_pupil_field,
                                                exit_pupil_field_steps)  # noqa: F401
from raywave.hybrid.coherent.faithful import (faithful_field)  # noqa: F401
from raywave.hybrid.coherent.settings import ChiefRays, FieldSettings, Known, Planes, Source  # noqa: F401

__all__ = ["CausticWarning", "DOEField", "FieldInfo", "SamplingWarning", "StopEdgeWarning", "VignettingEdgeWarning",
           "accurate_field",
           "chief_rays", "doe_clipping", "doe_clippings",
           "exit_pupil_field", "footprints", "faithful_field", "ChiefRays", "FieldSettings", "Known", "Planes", "Source"]
