"""First-order (paraxial) optics of a sequential lens, with y–n·u transfer matrices in float64.

State vector (y, n·u): height (mm) and reduced slope. Refraction by a surface of power φ:
[[1, 0], [-φ, 1]]; a gap of thickness t in index n: [[1, t/n], [0, 1]]. Both have determinant 1.
Surface powers include the r² term of even aspheres (vertex curvature c + 2·a2), which tools that use only
the base radius leave out, and the power of ideal (paraxial) lenses. A lens with a toroid is modelled in its
y–z section (``ParaxialData.section == "y-z"``), as OpticStudio does.

Every length is measured in mm along z from the first vertex unless its name says otherwise.

Mirrors: the index changes sign at every reflection (n' = −n) and the thicknesses after an odd number of mirrors
are negative, so t / n stays positive and a mirror's power is the refraction formula's (n' − n) c = −2 n c
(:func:`signed_indices`). z values then run along the lens's thickness axis (global z for a lens without
coordinate breaks: after a mirror the image lies at smaller z).

Coordinate breaks: the paraxial model follows the *unfolded* optical axis (the ray from the object along the
first vertex's axis, reflected by fold mirrors), with gaps measured along it (:func:`axial_gaps`); z values are
positions along that unfolded axis. It is defined only while every surface with power is centred on that axis and
perpendicular to it (plane mirrors may fold it at any angle); otherwise the quantities that depend on such a
surface raise :class:`ParaxialUndefinedError`, which names it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch


def _m(a, b, c, d):
    return torch.stack([torch.stack([a, b]), torch.stack([c, d])])


class ParaxialUndefinedError(ValueError):
    """A first-order quantity asked of a lens whose decentred or tilted surfaces leave it undefined."""


def signed_indices(lens, wl: torch.Tensor) -> list[torch.Tensor]:
    """[n_obj, n_1, ..., n_N] at ``wl`` (µm tensor), negative after an odd number of mirrors."""
    return [n if sg > 0 else -n for n, sg in zip(lens.indices(wl), lens.direction_signs())]


def _is_flat(geom) -> bool:
    from raywave.surfaces.geometry import Plane

    if isinstance(geom, Plane):
        return True
    if float(geom.paraxial_curvature().detach()) != 0.0 or float(getattr(geom, "curvature", torch.zeros(())).detach()):
        return False
    coeffs = getattr(geom, "coefficients", None)
    if coeffs is not None and bool((coeffs.detach() != 0).any()):
        return False
    rc = getattr(geom, "rotation_curvature", None)
    return rc is None or float(rc.detach()) == 0.0


def _axis_hit(p: torch.Tensor, d: torch.Tensor, rot: torch.Tensor, t: torch.Tensor):
    """Where the axis through ``p`` (3,) mm along the unit direction ``d`` (3,) meets the plane through ``t`` (3,)
    mm whose normal is ``rot[:, 2]`` (``rot`` (3, 3)): (point (3,) mm, or None when the axis runs parallel to the
    plane; normal (3,); d · normal, a 0-d tensor)."""
    normal = rot[:, 2]
    dn = d @ normal
    if abs(float(dn.detach())) < 1e-12:
        return None, normal, dn
    return p + ((t - p) @ normal / dn) * d, normal, dn


def _axis_problem(s, kind: str, where: str, n_before: float, n_after: float, d, normal, dn, h, t) -> str | None:
    """What leaves the paraxial model undefined at surface ``s`` (of interaction ``kind``, named ``where``), or
    None: the axis (unit direction ``d`` (3,)) meets it at ``h`` (3,) mm; its frame's origin is ``t`` (3,) mm and
    its normal ``normal`` (3,), ``dn`` = d · normal; ``n_before``, ``n_after``: the indices around it. Tilts are
    reported in degrees, decentres in mm."""
    # the angle between the axis and the normal from atan2(|d × n|, |d · n|): accurate near 0 (acos of a dot
    # product one rounding below 1 is already 1.2e-6 degrees, which refused a tilt undone by its inverse)
    cross = float(torch.linalg.vector_norm(torch.linalg.cross(d, normal)).detach())
    tilt = math.degrees(math.atan2(cross, abs(float(dn.detach()))))
    off = float(torch.linalg.vector_norm((h - t).detach()))
    scale = max(1.0, float(torch.linalg.vector_norm(t.detach())))
    flat = _is_flat(s.geometry) and kind in ("reflection", "refraction")
    if kind == "refraction" and flat and n_before != n_after and tilt > 1e-9:
        return (f"{where} is a plane tilted by {tilt:.6g} degrees to the optical axis between different media "
                "(a tilted plate: the system is not rotationally symmetric)")
    if not flat:
        if tilt > 1e-9:
            return f"{where} is tilted by {tilt:.6g} degrees to the optical axis"
        if off > 1e-9 * scale:
            return f"{where} is decentred by {off:.6g} mm from the optical axis"
    return None


def _axis_walk(lens, wavelength: float | None = None):
    """Follow the optical axis through a lens with coordinate breaks.

    Returns (gaps, problem): ``gaps[i]`` the signed distance (mm, a tensor) along the unfolded axis from surface
    ``i`` to the next surface (or the image plane), for every surface before the first that leaves the paraxial
    model undefined; ``problem`` None or (index of that surface, what is wrong). A surface's place on the axis is
    where the axis meets it; a coordinate break's is its origin projected onto the axis (so that, as in
    OpticStudio, the last thickness, the BFL and the paraxial image are measured from it)."""
    frames, (r_img, t_img) = lens.surface_frames()
    wl = torch.tensor(float(lens.primary_wavelength if wavelength is None else wavelength), dtype=torch.float64,
                      device=lens.device)
    n = [float(v.detach()) for v in lens.indices(wl)]
    p = torch.zeros(3, dtype=torch.float64, device=lens.device)
    d = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=lens.device)
    gaps: list = []
    surfaces = list(lens.surfaces)
    a_prev = None  # the previous surface's position along the unfolded axis (signed, mm)
    a_hit = torch.zeros((), dtype=torch.float64, device=lens.device)  # that of the last axis point p
    sign = 1  # +1 / -1: direction of travel along the unfolded coordinate after an even / odd number of mirrors

    def place(a):
        nonlocal a_prev
        if a_prev is not None:
            gaps.append(a - a_prev)
        a_prev = a

    for i, s in enumerate(surfaces + [None]):
        kind = "image" if s is None else s.interaction.kind
        if kind == "coordinate_break":
            place(a_hit + sign * ((frames[i][1] - p) @ d))
            continue
        rot, t = (r_img, t_img) if s is None else frames[i]
        h, normal, dn = _axis_hit(p, d, rot, t)
        where = "the image plane" if s is None else f"surface {i}"
        if h is None:
            return gaps, (i, f"{where} is parallel to the optical axis")
        a_hit = a_hit + sign * ((h - p) @ d)
        place(a_hit)
        if s is None:
            break
        what = _axis_problem(s, kind, where, n[i], n[i + 1], d, normal, dn, h, t)
        if what is not None:
            return gaps, (i, what)
        p = h
        if kind == "reflection":
            d = d - 2.0 * (d @ normal) * normal
            sign = -sign
    return gaps, None


def axial_gaps(lens, need: int | None = None, wavelength: float | None = None) -> list[torch.Tensor]:
    """Signed distances (mm) from each surface to the next (the last: to the image plane) along the unfolded axis:
    the thicknesses for a lens without coordinate breaks. ``need``: how many leading surfaces the caller uses
    (default all); raises :class:`ParaxialUndefinedError` if one of them leaves the paraxial model undefined."""
    if not lens.is_folded:
        return [s.thickness for s in lens.surfaces]
    gaps, problem = _axis_walk(lens, wavelength)
    need = len(lens.surfaces) if need is None else need
    if problem is not None and problem[0] <= need:
        i, what = problem
        raise ParaxialUndefinedError(
            f"paraxial quantities are undefined for this lens: {what}, so it is not rotationally symmetric about "
            "the (unfolded) optical axis; EFL, BFL, F/#, pupils and the paraxial image are not defined (trace real "
            "rays instead)")
    return gaps


def axial_vertex_positions(lens) -> torch.Tensor:
    """(n_surfaces,) vertex positions (mm) along the unfolded axis: ``lens.vertex_z()`` without coordinate breaks."""
    if not lens.is_folded:
        return lens.vertex_z()
    g = torch.stack(axial_gaps(lens))
    return torch.cat([g.new_zeros(1), torch.cumsum(g[:-1], 0)])


def surface_powers(lens, wavelength: float) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Powers φ_i (1/mm) of each surface and indices [n_obj, n_1, ..., n_N] at ``wavelength`` (µm), signed:
    negative after an odd number of mirrors."""
    wl = torch.tensor(float(wavelength), dtype=torch.float64, device=lens.device)
    n = signed_indices(lens, wl) if lens.has_mirrors else lens.indices(wl)
    phis = []
    for i, s in enumerate(lens.surfaces):
        phis.append(s.interaction.paraxial_power(s.geometry.paraxial_curvature(), n[i], n[i + 1]))
    return phis, n


def system_matrix(lens, wavelength: float, first: int = 0, last: int | None = None) -> torch.Tensor:
    """2×2 matrix from just before surface ``first`` (at its vertex) to just after surface ``last - 1``."""
    last = len(lens.surfaces) if last is None else last
    phis, n = surface_powers(lens, wavelength)
    gaps = axial_gaps(lens, last)
    one = torch.ones((), dtype=torch.float64, device=lens.device)
    zero = torch.zeros_like(one)
    m = _m(one, zero, zero, one)
    for i in range(first, last):
        if i > first:
            t = gaps[i - 1]
            m = _m(one, t / n[i], zero, one) @ m
        m = _m(one, zero, -phis[i], one) @ m
    return m


def stop_to_entrance_pupil(lens, wavelength: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(z of the entrance pupil, magnification stop/entrance pupil): the stop imaged into object space."""
    s = lens.stop_index
    phis, n = surface_powers(lens, wavelength)
    if s == 0:
        one = torch.ones((), dtype=torch.float64, device=lens.device)
        return torch.zeros_like(one), one
    m = system_matrix(lens, wavelength, 0, s)
    t = axial_gaps(lens, s)[s - 1]
    one = torch.ones_like(t)
    m = torch.stack([torch.stack([one, t / n[s]]), torch.stack([torch.zeros_like(t), one])]) @ m
    a, b = m[0, 0], m[0, 1]
    # Object-space ray (y0, n0 u0) at the first vertex hits the stop centre when a·y0 + b·n0u0 = 0.
    return b * n[0] / a, a


def marginal_slope_per_epd(lens, wavelength: float) -> float:
    """|n'·u'| of the paraxial marginal ray in image space for an entrance pupil of diameter 1 mm (it scales
    with the EPD): the ray from the axial object point (or parallel to the axis) to the pupil's rim."""
    m = system_matrix(lens, wavelength).detach()
    n = [float(x.detach()) for x in surface_powers(lens, wavelength)[1]]
    a, b, c, d = (float(v) for v in (m[0, 0], m[0, 1], m[1, 0], m[1, 1]))
    if math.isinf(lens.object_distance):
        return abs(c * 0.5)
    s = lens.object_distance
    ep_z = float(stop_to_entrance_pupil(lens, wavelength)[0].detach())
    u0 = 0.5 / (s + ep_z)
    return abs(c * s * u0 + d * n[0] * u0)


def epd_from_system_aperture(lens, kind: str, value: float, wavelength: float | None = None) -> float:
    """The paraxial entrance pupil diameter (mm) that a system aperture of type ``kind`` and ``value`` gives, as
    OpticStudio converts it (at ``wavelength``, default the primary; docs/lens-format.md "System aperture"):

    * ``epd``: the value;
    * ``f_number`` (image-space F/#): |EFL| / F, EFL at infinite conjugates;
    * ``working_f_number`` (paraxial working F/#): the EPD whose paraxial marginal ray leaves the lens with
      1 / (2 |n'u'|) = the value (for a distant object in air the same as ``f_number``);
    * ``object_na`` (n sin θ) and ``object_cone_angle`` (θ, degrees): the marginal ray from the axial object
      point at angle θ reaches the rim of the paraxial entrance pupil: EPD = 2 |s + z_EP| tan θ (finite object).
    """
    wl = lens.primary_wavelength if wavelength is None else wavelength
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"system aperture {kind}: value must be > 0, got {value!r}")
    if kind == "epd":
        return value
    if kind == "f_number":
        c = float(system_matrix(lens, wl)[1, 0].detach())
        if c == 0.0:
            raise ValueError("system aperture f_number: the lens is afocal (no focal length); give an epd")
        return abs(1.0 / c) / value
    if kind == "working_f_number":
        per = marginal_slope_per_epd(lens, wl)
        if per == 0.0:
            raise ValueError("system aperture working_f_number: the paraxial marginal ray leaves the lens parallel "
                             "to the axis (image at infinity); give an epd")
        return 1.0 / (2.0 * value * per)
    if kind in ("object_na", "object_cone_angle"):
        if math.isinf(lens.object_distance):
            raise ValueError(f"system aperture {kind} needs an object at a finite distance")
        if kind == "object_na":
            n0 = float(lens.object_material.n(torch.tensor(float(wl), dtype=torch.float64)).detach())
            if not value < n0:
                raise ValueError(f"system aperture object_na {value!r} must be < the object-space index {n0!r}")
            theta = math.asin(value / n0)
        else:
            if not value < 90.0:
                raise ValueError(f"system aperture object_cone_angle {value!r} must be < 90 degrees")
            theta = math.radians(value)
        dist = lens.object_distance + float(stop_to_entrance_pupil(lens, wl)[0].detach())
        if dist == 0.0:
            raise ValueError(f"system aperture {kind}: the entrance pupil lies on the object plane")
        return 2.0 * abs(dist) * math.tan(theta)
    raise ValueError(f"unknown system aperture type {kind!r} (known: epd, f_number, working_f_number, object_na, "
                     "object_cone_angle, float_by_stop_size)")


@dataclass
class ParaxialData:
    """First-order properties (mm, degrees). z values are measured from the first vertex (along the unfolded axis
    when coordinate breaks fold it). ``efl`` is the image-space EFL as OpticStudio and Optiland report it: negative
    after an odd number of mirrors (n' = −1: a concave mirror of radius R < 0 has efl = R/2); ``fnum`` uses |efl|.
    ``bfl`` runs from the last surface (a coordinate break: its origin) to the paraxial image, signed like the
    thicknesses (negative after an odd number of mirrors)."""

    wavelength: float
    efl: float
    bfl: float
    ffl: float
    fnum: float
    working_fnum: float
    epd: float
    ep_z: float
    xpd: float
    xp_z: float
    fov_deg: float
    image_height: float
    total_track: float
    image_z_paraxial: float
    magnification: float
    #: "rotational", or "y-z" when a surface is not rotationally symmetric (a toroid): every value above is then
    #: that of the y–z section (as OpticStudio reports it); the x–z section has other values.
    section: str = "rotational"

    def as_dict(self) -> dict:
        return asdict(self)


def exit_pupil(lens, wavelength: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(z of the exit pupil, magnification stop→exit pupil D'^-1 factor): the stop imaged into image space."""
    s = lens.stop_index
    phis, n = surface_powers(lens, wavelength)
    m = system_matrix(lens, wavelength, s, None)
    b, d = m[0, 1], m[1, 1]
    z_last = axial_vertex_positions(lens)[-1]
    n_img = n[-1]
    return z_last - b * n_img / d, 1.0 / d


def paraxial_image_distance(lens, wavelength: float) -> torch.Tensor:
    """z of the paraxial image of the lens's object plane (mm from the first vertex)."""
    m = system_matrix(lens, wavelength)
    phis, n = surface_powers(lens, wavelength)
    z_last = axial_vertex_positions(lens)[-1]
    if math.isinf(lens.object_distance):
        a, c = m[0, 0], m[1, 0]
        return z_last - a * n[-1] / c
    # A ray from the axial object point: y0 = s·u0 at the first vertex (s = object distance), n0·u0.
    s = lens.object_distance
    y0, nu0 = s, n[0]  # slope u0 = 1: height s at the first vertex
    y1 = m[0, 0] * y0 + m[0, 1] * nu0
    nu1 = m[1, 0] * y0 + m[1, 1] * nu0
    return z_last - y1 * n[-1] / nu1


def entrance_pupil_diameter(lens, wavelength: float | None = None) -> float:
    """The entrance-pupil diameter (mm) that the rays fill, at ``wavelength`` µm (default the lens's primary): the
    image of the stop's clear radius (:meth:`~raywave.lens.lens.Lens.stop_radius`). The same float as
    :func:`paraxial_data`'s ``epd``, except where the stop's own fixed clear aperture (a .zmx stop's ``CLAP``) is
    smaller than the system aperture makes the stop (``epd`` is the system aperture's there), without the rest of
    the first-order data (~0.2 ms instead of ~2 ms on the bundled asphere; the aiming of every ray bundle asks for
    it, ~10 times per PSF call)."""
    _, m_ep = stop_to_entrance_pupil(lens, lens.primary_wavelength if wavelength is None else wavelength)
    return 2.0 * lens.stop_radius() / abs(float(m_ep.detach()))


def paraxial_data(lens, wavelength: float) -> ParaxialData:
    """All first-order properties of ``lens`` at ``wavelength`` (µm)."""
    m = system_matrix(lens, wavelength).detach()
    n = [x.detach() for x in surface_powers(lens, wavelength)[1]]
    a, b, c, d = m[0, 0], m[0, 1], m[1, 0], m[1, 1]
    z_last = float(axial_vertex_positions(lens)[-1].detach())
    power = -float(c)
    # image-space EFL as OpticStudio / Optiland give it: negative after an odd number of mirrors (n' = -n there)
    efl = lens.direction_signs()[-1] / power if power != 0 else math.inf
    bfl = -float(a) * float(n[-1]) / float(c) if power != 0 else math.inf
    ffl = float(d) * float(n[0]) / float(c) if power != 0 else math.inf
    ep_z, m_ep = (v.detach() for v in stop_to_entrance_pupil(lens, wavelength))
    xp_z, m_xp = (v.detach() for v in exit_pupil(lens, wavelength))
    r_stop = lens.pupil_stop_radius()  # the system aperture's, also where the stop's own CLAP cuts the beam
    epd = 2.0 * r_stop / abs(float(m_ep))
    xpd = 2.0 * r_stop * abs(float(m_xp))
    z_img_par = float(paraxial_image_distance(lens, wavelength).detach())
    if math.isinf(lens.object_distance):
        fnum = abs(efl) / epd
        mag = 0.0
        # Working F/#: 1 / (2 n' sin u') of the paraxial marginal ray (image space)
        nu_img = (epd / 2) * float(c)  # n'·u' of the marginal ray
        working = 1.0 / (2.0 * abs(nu_img)) if nu_img else math.inf
    else:
        s = lens.object_distance
        # Marginal ray from the axial object point to the edge of the entrance pupil.
        u0 = (epd / 2) / (s + float(ep_z))
        y0 = s * u0
        y1 = float(a) * y0 + float(b) * float(n[0]) * u0
        nu1 = float(c) * y0 + float(d) * float(n[0]) * u0
        working = 1.0 / (2.0 * abs(nu1)) if nu1 else math.inf
        fnum = abs(efl) / epd
        # Chief ray from an object point at height h through the entrance pupil centre.
        h = 1.0
        uc = -h / (s + float(ep_z))
        yc0 = h + s * uc
        yc1 = float(a) * yc0 + float(b) * float(n[0]) * uc
        nuc1 = float(c) * yc0 + float(d) * float(n[0]) * uc
        mag = (yc1 + (z_img_par - z_last) * nuc1 / float(n[-1])) / h
    fov, img_h = field_of_view(lens, wavelength, efl, float(ep_z), mag)
    return ParaxialData(
        wavelength=float(wavelength), efl=efl, bfl=bfl, ffl=ffl, fnum=fnum, working_fnum=working,
        epd=epd, ep_z=float(ep_z), xpd=xpd, xp_z=float(xp_z), fov_deg=fov, image_height=img_h,
        total_track=lens.total_track(), image_z_paraxial=z_img_par, magnification=mag,
        section=paraxial_section(lens),
    )


def paraxial_section(lens) -> str:
    """"rotational" for a rotationally symmetric lens, "y-z" when a surface (a toroid) is not: the paraxial model
    then describes the y–z section only."""
    symmetric = all(getattr(s.geometry, "rotationally_symmetric", True) for s in lens.surfaces)
    return "rotational" if symmetric else "y-z"


def field_of_view(lens, wavelength: float, efl: float, ep_z: float, mag: float) -> tuple[float, float]:
    """(full field of view in degrees, paraxial image height in mm) at the largest field.

    From the lens's fields if it has any non-zero one, else from the sensor's half-diagonal.
    """
    fmax = max((abs(f) for f in lens.fields), default=0.0)
    if fmax > 0:
        if lens.field_type == "angle":
            return 2.0 * fmax, abs(efl) * math.tan(math.radians(fmax)) if math.isinf(lens.object_distance) else abs(
                mag * (lens.object_distance + ep_z) * math.tan(math.radians(fmax)))
        h_img = abs(mag) * fmax if not math.isinf(lens.object_distance) else 0.0
        ang = math.degrees(math.atan(fmax / (lens.object_distance + ep_z))) if not math.isinf(lens.object_distance) else 0.0
        return 2.0 * ang, h_img
    if lens.sensor_size is not None:
        h = 0.5 * math.hypot(*lens.sensor_size)
        return 2.0 * math.degrees(math.atan(h / abs(efl))), h
    return 0.0, 0.0
