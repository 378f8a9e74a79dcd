"""Geometric analysis of a lens: real-ray EFL, focus, spots, wavefront OPD, geometric PSF, distortion,
field curvature and third-order (Seidel) aberrations.

All results are float64 tensors (differentiable where that makes sense) or plain floats for reports.
Batch shapes follow :mod:`raywave.lens.sources`: (F, W, N) = (fields, wavelengths, pupil samples).
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens import paraxial
from raywave.lens.sources import VignettingWarning, chief_ray, point_source_rays
from raywave.rays.bundle import RayBundle
from raywave.rays.pupil import hexapolar
from raywave.utils.safe import safe_sqrt


# ---------------------------------------------------------------------------- first order, real rays
def real_ray_efl(lens, wavelength: float | None = None, height: float | None = None) -> torch.Tensor:
    """Effective focal length from a real ray parallel to the axis at ``height`` (mm; default 1e-3 of the
    entrance pupil radius): EFL = -h / tan(u') in image space. Differentiable.

    Unlike a paraxial model it sees every term of the real surfaces (and, in hybrid lenses, the DOE), so
    it is the check on the paraxial table."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    if height is None:
        height = 1e-3 * 0.5 * lens.paraxial(wl).epd
    rays = RayBundle.create([[0.0, height, -1.0]], [[0.0, 0.0, 1.0]], wl, device=lens.device)
    out = lens.image_coordinates(lens.trace(rays))  # directions in the image plane's frame (folded lenses)
    if not bool(out.valid.all()):
        raise ValueError(f"the real-ray EFL ray at height {height:g} mm is vignetted{blocking_aperture(lens, rays)}")
    return -height / (out.d[0, 1] / out.d[0, 2])


def blocking_aperture(lens, rays) -> str:
    """Where the first ray of ``rays`` is blocked, in words (": surface 3 ('secondary') blocks it: its central
    obscuration (circle of radius 2 mm); ..."), or "" when no aperture blocks it (it misses a surface, or TIR)."""
    with torch.no_grad():  # apertures off: the record keeps where the ray meets each surface (blocked rays are
        _, rec = lens.trace(rays, record=True, apertures=False)  # parked on the axis otherwise)
    for i, s in enumerate(lens.surfaces):
        if s.aperture is None or not bool(rec.valid[i + 1].reshape(-1)[0]):
            continue
        x, y = (float(c.reshape(-1)[0]) for c in rec.points[i + 1][:2])
        what = s.aperture.blocked_by(x, y)
        if what is None:
            continue
        name = f" ({s.comment!r})" if s.comment else ""
        hint = ("; a central obscuration blocks the axis: give the real-ray EFL a height outside it "
                "(real_ray_efl(lens, height=...))") if "central obscuration" in what else ""
        return f": surface {i}{name} blocks it at (x, y) = ({x:.4g}, {y:.4g}) mm: {what}{hint}"
    return ""


# ---------------------------------------------------------------------------- beam extent
def beam_field_points(lens, fields):
    """Field points (F, 2) float64 for the beam extent: ``fields`` ((2,), (F, 2) or one y value), default the
    lens's fields along y and (0, 0)."""
    if fields is None:
        pts = [(0.0, float(f)) for f in lens.fields] + [(0.0, 0.0)]
    else:
        f = torch.as_tensor(fields, dtype=torch.float64, device="cpu")
        if f.ndim == 0:
            f = torch.stack([torch.zeros_like(f), f])
        pts = [tuple(float(v) for v in row) for row in f.reshape(-1, 2)]
    return torch.tensor(pts, dtype=torch.float64, device=lens.device)


def beam_rays_at(lens, z: float, fields=None, wavelengths=None, depth=None, chief: bool = False):
    """The beam bundle on the plane ``z`` (mm from the first vertex): rays of every field point (``fields``: (2,)
    or (F, 2) in the lens's field type; default the lens's fields along y and (0, 0)) and wavelength (µm; default
    all of the lens's) through the pupil rim (72 points) and a hexapolar grid (6 rings), fully aimed, led by the
    chief ray (pupil sample 0) when ``chief``; traced without autograd and carried along straight lines to z.
    Vignetted rays are left out through the ``valid`` mask (their warnings muted: a diagnostic trace). A folded or
    mirrored lens: pass its image-space view (:func:`raywave.lens.frames.image_space`); ``z`` is then in that
    frame.

    Returns:
        (rays at z (F, W, P), the image-space index (F, W, 1), the wavelengths (list, µm)).
    """
    if not getattr(lens, "image_space_view", False):  # the image-space view's z axis is straight (lens.frames)
        lens.require_unfolded("beam_half_extent")
    t = torch.linspace(0, 2 * math.pi, 73, dtype=torch.float64, device=lens.device)[:-1]
    hx, hy = hexapolar(6, device=lens.device)
    head = [torch.zeros(1, dtype=torch.float64, device=lens.device)] if chief else []
    px = torch.cat(head + [torch.cos(t), hx])
    py = torch.cat(head + [torch.sin(t), hy])
    wls = (lens.wavelengths if wavelengths is None
           else [float(w) for w in torch.as_tensor(wavelengths, device="cpu").reshape(-1)])
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # vignetted rays are left out (valid mask)
        rays = point_source_rays(lens, beam_field_points(lens, fields), wls, pupil=(px, py), aim="full", depth=depth)
        out = lens.trace(rays)
        n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        return out.propagate_to_z(z, n), n, wls


def pupil_grid(n_grid: int, device=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cell centres of an ``n_grid`` × ``n_grid`` grid over the normalised stop square [-1, 1]², those inside the
    unit circle: ``(px (N,), py (N,), index (N,))``, ``index`` their flat positions in the grid (row-major: row y,
    column x), which :func:`fold_fraction` uses to find each ray's grid neighbours."""
    g = (torch.arange(n_grid, dtype=torch.float64, device=device) + 0.5) / n_grid * 2 - 1
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    inside = (gx**2 + gy**2 <= 1).flatten()
    return gx.flatten()[inside], gy.flatten()[inside], torch.nonzero(inside).squeeze(1)


def fold_fraction(xy: torch.Tensor, valid: torch.Tensor, index: torch.Tensor, n_grid: int) -> torch.Tensor:
    """How much of a beam's ray map from the stop to a plane is folded (rays that cross between the lens and the
    plane: a caustic lies before it).

    The rays come from the :func:`pupil_grid` cells ``index`` (N,); each grid cell with three valid rays (its own,
    the next along x, the next along y) maps to a triangle on the plane whose orientation is the sign of the map's
    Jacobian there. One orientation throughout means the map is one to one (mirrored as a whole past a focus is
    fine); both mean it folds. Returns the fraction (...,) float64 of the counted cells with the less common
    orientation (0: no fold). ``xy`` (..., N, 2) mm on the plane, ``valid`` (..., N) (vignetted rays: False)."""
    lead = xy.shape[:-2]
    nan = torch.tensor(math.nan, dtype=xy.dtype, device=xy.device)
    full = torch.full((*lead, n_grid * n_grid, 2), math.nan, dtype=xy.dtype, device=xy.device)
    full[..., index, :] = torch.where(valid[..., None], xy, nan)
    g = full.reshape(*lead, n_grid, n_grid, 2)
    a = g[..., :-1, 1:, :] - g[..., :-1, :-1, :]  # to the next column (x)
    b = g[..., 1:, :-1, :] - g[..., :-1, :-1, :]  # to the next row (y)
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    ok = torch.isfinite(det)
    det = torch.where(ok, det, torch.zeros_like(det))
    tol = 1e-9 * det.abs().amax((-1, -2), keepdim=True)  # a degenerate (focused) cell counts for neither side
    pos = (det > tol).sum((-1, -2))
    neg = (det < -tol).sum((-1, -2))
    return torch.minimum(pos, neg).to(xy.dtype) / (pos + neg).clamp_min(1).to(xy.dtype)


def beam_folds(lens, z, fields=None, wavelengths=None, depth=None, n_grid: int = 32) -> torch.Tensor:
    """:func:`fold_fraction` of every source's beam on the planes ``z`` (Z,) mm from the first vertex (in image
    space, after the last surface): ``(Z, F, W)`` float64, 0 where the rays from the stop have not crossed yet.
    Sources as :func:`beam_rays_at` (``fields`` in the lens's field type, default its fields along y and (0, 0);
    ``wavelengths`` µm, default all the lens's); an ``n_grid``² stop grid, fully aimed, traced once without autograd
    and carried along straight lines."""
    if not getattr(lens, "image_space_view", False):
        lens.require_unfolded("beam_folds")
    px, py, index = pupil_grid(n_grid, lens.device)
    wls = (lens.wavelengths if wavelengths is None
           else [float(w) for w in torch.as_tensor(wavelengths, device="cpu").reshape(-1)])
    zs = torch.as_tensor(z, dtype=torch.float64, device=lens.device).reshape(-1)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # vignetted rays are left out (valid mask)
        rays = point_source_rays(lens, beam_field_points(lens, fields), wls, pupil=(px, py), aim="full", depth=depth)
        out = lens.trace(rays)
        n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(float(zs[0]), n)
        tan = at.d[..., :2] / at.d[..., 2:]
        xy = at.o[None, ..., :2] + tan[None] * (zs - zs[0])[:, None, None, None, None]
        return fold_fraction(xy, at.valid.expand(xy.shape[:-1]), index, n_grid)


def beam_half_extent(lens, z: float, fields=None, wavelengths=None, depth=None) -> tuple[float, float] | None:
    """Largest ``|x|`` and ``|y|`` (mm) the beam (:func:`beam_rays_at`: pupil rim and hexapolar grid, every field
    and wavelength) reaches on the plane ``z`` (mm from the first vertex). None when every ray is vignetted."""
    at = beam_rays_at(lens, z, fields, wavelengths, depth)[0]
    v = at.valid & torch.isfinite(at.o).all(-1)
    if not bool(v.any()):
        return None
    xy = at.o[..., :2][v]
    return float(xy[:, 0].abs().max()), float(xy[:, 1].abs().max())


# ---------------------------------------------------------------------------- focus
def image_circle_radius(lens, depth=None, wavelength: float | None = None) -> float:
    """Radius (mm) of the lens's image circle: the real chief ray's height on the sensor plane for the largest of
    ``lens.fields`` (in the lens's field type) whose chief ray reaches the sensor, at ``wavelength`` (µm; default
    the primary), object at ``depth`` (mm; default the lens's own). A ValueError names the problem when the lens
    lists no off-axis field or no off-axis field's chief ray reaches the sensor."""
    listed = sorted({abs(float(f)) for f in lens.fields if abs(float(f)) > 0}, reverse=True)
    if not listed:
        raise ValueError("the lens lists no off-axis field (its 'fields'), so its image circle is unknown")
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    f = torch.stack([torch.zeros(len(listed), dtype=torch.float64, device=lens.device),
                     torch.tensor(listed, dtype=torch.float64, device=lens.device)], -1)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        out = lens.trace_to_image(chief_ray(lens, f, [wl], depth=depth))
    h = out.o[:, 0, 0, 1].abs()
    for i in range(len(listed)):  # the largest listed field that images
        if bool(out.valid[i, 0, 0]) and math.isfinite(float(h[i])) and float(h[i]) > 0:
            return float(h[i])
    raise ValueError(f"no chief ray of the lens's off-axis fields ({', '.join(f'{v:g}' for v in listed)} "
                     f"{_field_unit(lens)}, {wl:g} µm) reaches the sensor, so its image circle is unknown")


def default_sensor_size(lens, depth=None) -> tuple[float, float]:
    """(w, h) mm of the sensor assumed for a lens file without one: the square inscribed in the lens's image
    circle (:func:`image_circle_radius`), so its corners see the largest field the lens lists and every sensor
    point lies within the lens's field of view."""
    side = math.sqrt(2.0) * image_circle_radius(lens, depth)
    return side, side


def _field_unit(lens) -> str:
    return "deg" if lens.field_type == "angle" else "mm object height"


def refocus(lens, object_distance: float | None = None, method: str = "paraxial", wavelength=None) -> float:
    """Set the last thickness so that the sensor is at the focus of an object at ``object_distance``
    (mm; default: the lens's own). ``method``: "paraxial" (paraxial image plane) or "rms" (plane of least
    RMS on-axis spot over the full pupil, from real rays, closed form). Returns the new image z (mm)."""
    lens.require_unfolded("refocus")
    if object_distance is not None:
        lens.object_distance = float(object_distance)
    wl = lens.primary_wavelength if wavelength is None else wavelength
    z_last = lens.vertex_z()[-1].detach()
    if method == "paraxial":
        z_img = paraxial.paraxial_image_distance(lens, wl).detach()
    elif method == "rms":
        z_img = best_focus_z(lens, wl)
    else:
        raise ValueError(f"refocus method must be 'paraxial' or 'rms', got {method!r}")
    with torch.no_grad():
        lens.surfaces[-1].thickness.copy_(z_img - z_last)
    return float(z_img)


def best_focus_z(lens, wavelength=None, field=(0.0, 0.0), n: int = 41) -> torch.Tensor:
    """z (mm) of the plane minimising the RMS spot radius of a full-pupil grid (closed form: the spot
    radius² is quadratic in z)."""
    lens.require_unfolded("best_focus_z")
    wl = lens.primary_wavelength if wavelength is None else wavelength
    rays = point_source_rays(lens, field, wl, pupil=("grid", n))
    out = lens.trace(rays)
    z0 = out.o[..., 2]
    sx, sy = out.d[..., 0] / out.d[..., 2], out.d[..., 1] / out.d[..., 2]
    # Move every ray to the common plane z0max, then solve d/dΔ Σ|p + Δ s - mean|² = 0.
    zr = z0.detach().max()
    px, py = out.o[..., 0] + sx * (zr - z0), out.o[..., 1] + sy * (zr - z0)
    w = out.valid.to(px.dtype)
    m = w.sum()

    def centred(a):
        return a - (a * w).sum() / m

    cpx, cpy, csx, csy = centred(px), centred(py), centred(sx), centred(sy)
    delta = -((cpx * csx + cpy * csy) * w).sum() / ((csx * csx + csy * csy) * w).sum()
    return zr + delta


# ---------------------------------------------------------------------------- spots
def spot(lens, fields=None, wavelengths=None, pupil=("hexapolar", 6), reference: str = "centroid"):
    """Image-plane spot positions relative to the reference point.

    Returns (dx, dy, valid, ref) with dx, dy: (F, W, N) mm; ref: (F, W, 2) the reference point per
    field and wavelength ("centroid" of that wavelength's spot, or "chief" ray intercept)."""
    fields = _fields(lens, fields)
    wls = lens.wavelengths if wavelengths is None else wavelengths
    rays = point_source_rays(lens, fields, wls, pupil=pupil)
    out = lens.image_coordinates(lens.trace_to_image(rays))  # on the (possibly tilted) image plane
    x, y, v = out.o[..., 0], out.o[..., 1], out.valid
    if reference == "centroid":
        w = v.to(x.dtype)
        m = w.sum(-1).clamp_min(1)
        ref = torch.stack([(x * w).sum(-1) / m, (y * w).sum(-1) / m], -1)
    elif reference == "chief":
        c = lens.image_coordinates(lens.trace_to_image(chief_ray(lens, fields, wls)))
        ref = c.o[..., 0, :2]
    else:
        raise ValueError(f"spot reference must be 'centroid' or 'chief', got {reference!r}")
    return x - ref[..., None, 0], y - ref[..., None, 1], v, ref


def rms_spot_radius(lens, fields=None, wavelengths=None, pupil=("hexapolar", 6), reference="centroid") -> torch.Tensor:
    """RMS spot radius (mm), shape (F, W), over the valid rays of each field and wavelength; NaN for a field and
    wavelength of which every ray is vignetted (no spot: never 0, which would read as a perfect focus). Each field's
    value is the same whatever other fields share the call (the rim rule, :mod:`raywave.rays.pupil`)."""
    dx, dy, v, _ = spot(lens, fields, wavelengths, pupil, reference)
    w = v.to(dx.dtype)
    n = w.sum(-1)
    rms = _sqrt0(((dx * dx + dy * dy) * w).sum(-1) / n.clamp_min(1))
    return torch.where(n > 0, rms, torch.full_like(rms, math.nan))


def _sqrt0(x: torch.Tensor) -> torch.Tensor:
    """sqrt(max(x, 0)) with a zero (not infinite, not NaN) gradient where x <= 0: an RMS of zero (a perfect
    focus) or a tangent ray stays differentiable (double where, raywave.utils.safe)."""
    ok = x > 0
    return torch.where(ok, safe_sqrt(x, ok), torch.zeros_like(x))


def field_pairs(lens, fields=None) -> torch.Tensor:
    """Field points ``(F, 2)`` float64 on the lens's device from ``(x, y)`` pairs, y values or one value (the lens's
    field unit: degrees or mm); None: the lens's own fields along y."""
    if fields is None:
        fields = lens.fields
    f = torch.as_tensor(fields, dtype=torch.float64, device=lens.device)
    if f.ndim == 0:
        f = f[None]
    if f.ndim == 1:
        f = torch.stack([torch.zeros_like(f), f], -1)
    return f


_fields = field_pairs


# ---------------------------------------------------------------------------- wavefront
def wavefront_opd(lens, field=(0.0, 0.0), wavelength=None, pupil=("grid", 33), aim="full"):
    """Optical path difference at the exit pupil against the reference sphere, in waves.

    The reference sphere is centred on the chief ray's image-plane intercept and passes through the
    exit-pupil centre (paraxial exit-pupil z, on the chief ray). OPD = OPL(chief) − OPL(ray) measured to
    that sphere (as OpticStudio and Optiland): positive where the wavefront leads, so an undercorrected
    positive singlet has positive spherical aberration (W040 > 0, like its Seidel S_I).
    Returns (opd_waves (F, W, N), px, py (N,), valid (F, W, N)).
    """
    lens.require_unfolded("wavefront_opd")
    wl = lens.primary_wavelength if wavelength is None else wavelength
    if isinstance(pupil[0], str):
        from raywave.rays import pupil as patterns

        px, py = patterns.sample(pupil[0], pupil[1], device=lens.device)
    else:
        px, py = pupil
    px = torch.as_tensor(px, dtype=torch.float64, device=lens.device).reshape(-1)
    py = torch.as_tensor(py, dtype=torch.float64, device=lens.device).reshape(-1)
    px = torch.cat([px.new_zeros(1), px])
    py = torch.cat([py.new_zeros(1), py])
    rays = point_source_rays(lens, field, wl, pupil=(px, py), aim=aim)
    out = lens.trace_to_image(rays)
    n_img = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    xp_z = paraxial.exit_pupil(lens, lens.primary_wavelength)[0]
    chief = out[..., :1]
    centre = chief.o  # (F, W, 1, 3)
    # Exit-pupil point on the chief ray
    t_xp = (xp_z - chief.o[..., 2]) / chief.d[..., 2]
    e = chief.o + t_xp[..., None] * chief.d
    radius = torch.linalg.vector_norm(e - centre, dim=-1)  # (F, W, 1)
    # For each ray: o + t d on the sphere |p - centre| = R, the root on the exit-pupil side (t < 0 when
    # the sphere lies before the image plane).
    w = out.o - centre
    b = (w * out.d).sum(-1)
    c = (w * w).sum(-1) - radius * radius
    disc = b * b - c
    sign = torch.sign(xp_z - out.o[..., 2]) * torch.sign(out.d[..., 2])
    t = -b + sign * _sqrt0(disc)
    opl = out.opl + n_img * t
    opd = opl[..., :1] - opl
    wl_t = torch.as_tensor(wl, dtype=torch.float64, device=lens.device).reshape(-1)[None, :, None]
    opd_waves = opd / (wl_t * 1e-3)
    return opd_waves[..., 1:], px[1:], py[1:], out.valid[..., 1:]


def rms_wavefront_error(lens, field=(0.0, 0.0), wavelength=None, n: int = 33) -> torch.Tensor:
    """RMS wavefront error (waves) with piston removed, (F, W)."""
    opd, _, _, v = wavefront_opd(lens, field, wavelength, pupil=("grid", n))
    w = v.to(opd.dtype)
    m = w.sum(-1).clamp_min(1)
    mean = (opd * w).sum(-1) / m
    return _sqrt0((((opd - mean[..., None]) ** 2) * w).sum(-1) / m)


# ---------------------------------------------------------------------------- geometric PSF
def geometric_psf(lens, field=(0.0, 0.0), wavelength=None, n_rays: int = 101, size: int = 64,
                  pixel: float | None = None, center: str = "chief") -> torch.Tensor:
    """Incoherent geometric PSF by binning rays on a pixel grid (differentiable bilinear binning).

    Returns (size, size) float64 summing to 1 over the window (indexed [iy, ix], both increasing with the
    coordinate), centred on the chief-ray intercept (``center="chief"``) or the centroid.
    ``pixel``: bin size (mm); default the sensor pixel pitch, else 1 µm."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    if pixel is None:
        pixel = lens.sensor_size[0] / lens.sensor_resolution[0] if lens.sensor_resolution else 1e-3
    dx, dy, v, _ = spot(lens, [field], [wl], pupil=("grid", n_rays), reference="chief" if center == "chief" else "centroid")
    dx, dy, v = dx.reshape(-1), dy.reshape(-1), v.reshape(-1)
    fx = dx / pixel + size / 2 - 0.5
    fy = dy / pixel + size / 2 - 0.5
    img = torch.zeros(size * size, dtype=torch.float64, device=dx.device)
    x0, y0 = torch.floor(fx), torch.floor(fy)
    for ox in (0, 1):
        for oy in (0, 1):
            xi, yi = x0 + ox, y0 + oy
            wgt = (1 - (fx - xi).abs()) * (1 - (fy - yi).abs())
            ok = v & (xi >= 0) & (xi < size) & (yi >= 0) & (yi < size)
            idx = (yi.clamp(0, size - 1) * size + xi.clamp(0, size - 1)).long()
            img = img.index_add(0, idx, torch.where(ok, wgt, torch.zeros_like(wgt)))
    img = img.reshape(size, size)
    return img / img.sum().clamp_min(1e-300)


# ---------------------------------------------------------------------------- field aberrations
def distortion(lens, fields=None, wavelength=None) -> torch.Tensor:
    """Percent distortion per field: 100·(y_real − y_parax)/y_parax, with y_real the chief ray height on
    the image plane and y_parax = EFL·tan θ (distant object) or m·h (finite object). Shape (F,)."""
    lens.require_unfolded("distortion")
    wl = lens.primary_wavelength if wavelength is None else wavelength
    f = _fields(lens, fields)
    c = lens.trace_to_image(chief_ray(lens, f, [wl]))
    y_real = c.o[:, 0, 0, 1]
    p = lens.paraxial(wl)
    if math.isinf(lens.object_distance):
        y_par = p.efl * torch.tan(torch.deg2rad(f[:, 1]))
    elif lens.field_type == "object_height":
        y_par = p.magnification * f[:, 1]
    else:
        y_par = p.magnification * torch.tan(torch.deg2rad(f[:, 1])) * (-(lens.object_distance + p.ep_z))
    out = torch.zeros_like(y_real)
    nz = y_par != 0
    out[nz] = 100.0 * (y_real[nz] - y_par[nz]) / y_par[nz]
    return out


def field_curvature(lens, fields=None, wavelength=None, delta: float = 1e-3):
    """Tangential and sagittal focus positions relative to the image plane (mm), each (F,).

    Each focus is where a ray at pupil ±``delta`` (normalised, y for tangential, x for sagittal) crosses
    its partner near the chief ray (the limit of Coddington's equations), measured along z."""
    lens.require_unfolded("field_curvature", toward_plus_z=True)
    wl = lens.primary_wavelength if wavelength is None else wavelength
    f = _fields(lens, fields)
    px = torch.tensor([0.0, 0.0, delta, -delta], dtype=torch.float64, device=lens.device)
    py = torch.tensor([delta, -delta, 0.0, 0.0], dtype=torch.float64, device=lens.device)
    out = lens.trace_to_image(point_source_rays(lens, f, [wl], pupil=(px, py)))
    o, d = out.o[:, 0], out.d[:, 0]
    z_img = lens.image_z()

    def crossing(i, j, comp):
        # o_i + t s_i = o_j + t s_j in the given transverse component (s = slope d/dz)
        si = d[:, i, comp] / d[:, i, 2]
        sj = d[:, j, comp] / d[:, j, 2]
        return -(o[:, i, comp] - o[:, j, comp]) / (si - sj)

    return crossing(0, 1, 1), crossing(2, 3, 0) + 0 * z_img


# ---------------------------------------------------------------------------- third order
def seidel(lens, wavelength=None, field: float | None = None) -> dict:
    """Seidel sums S_I..S_IV (mm) from the paraxial marginal and chief rays (Welford's surface formulas).

    Wavefront coefficients: W040 = S_I/8, W131 = S_II/2, W222 = S_III/2, W220 = (S_III+S_IV)/4 (mm). Spherical surfaces and the conic/asphere r⁴ terms are included; ``field`` is the
    largest field angle (deg) the chief ray is scaled to (default: the lens's largest field)."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    phis, n = paraxial.surface_powers(lens, wl)
    p = lens.paraxial(wl)
    if not math.isinf(lens.object_distance):
        raise NotImplementedError("seidel() handles distant objects only")
    theta = max(abs(x) for x in lens.fields) if field is None else field
    u_chief0 = math.tan(math.radians(theta)) if theta else 1e-9
    # Marginal ray: height EPD/2, slope 0. Chief ray: through the EP centre.
    y, nu = torch.tensor(0.5 * p.epd, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
    yc = torch.tensor(-p.ep_z * u_chief0, dtype=torch.float64)
    nuc = n[0] * u_chief0
    S = [torch.zeros((), dtype=torch.float64) for _ in range(4)]
    lagrange = n[0] * (0.0 * yc) + (nuc * y - nu * yc)  # H = n(u_c y − u y_c)
    for i, s in enumerate(lens.surfaces):
        c = s.geometry.paraxial_curvature()
        n1, n2 = n[i], n[i + 1]
        if i > 0:
            t = lens.surfaces[i - 1].thickness
            y = y + t * nu / n1
            yc = yc + t * nuc / n1
        u1, uc1 = nu / n1, nuc / n1
        A = n1 * (y * c + u1)
        Ac = n1 * (yc * c + uc1)
        nu2 = nu - phis[i] * y
        nuc2 = nuc - phis[i] * yc
        u2 = nu2 / n2
        d_un = u2 / n2 - u1 / n1
        d_1n = 1.0 / n2 - 1.0 / n1
        # Aspheric contribution (conic and r⁴ coefficient): ΔS_I = 8 a4' (n2 − n1) y⁴ ...
        a4 = _r4_coefficient(s)
        dS = 8.0 * a4 * (n2 - n1) * y**4 if s.interaction.kind == "refraction" else 0.0
        ratio = yc / y if float(y) != 0 else 0.0
        S[0] = S[0] - A * A * y * d_un + dS
        S[1] = S[1] - A * Ac * y * d_un + dS * ratio
        S[2] = S[2] - Ac * Ac * y * d_un + dS * ratio**2
        S[3] = S[3] - lagrange**2 * c * d_1n
        nu, nuc = nu2, nuc2
    return {"S_I": S[0], "S_II": S[1], "S_III": S[2], "S_IV": S[3], "W040": S[0] / 8, "W131": S[1] / 2,
            "W222": S[2] / 2, "W220": (S[2] + S[3]) / 4}


def _r4_coefficient(surface) -> torch.Tensor | float:
    """Coefficient of r⁴ in the sag beyond the vertex sphere of curvature c_eff = c + 2·a2:
    (1+k) c³/8 + a4 − c_eff³/8 (mm⁻³)."""
    g = surface.geometry
    if not hasattr(g, "conic"):
        return 0.0
    c_eff = g.paraxial_curvature()
    total = (1.0 + g.conic) * g.curvature**3 / 8.0 - c_eff**3 / 8.0
    if hasattr(g, "coefficients") and g.coefficients.numel() > 1:
        total = total + g.coefficients[1]
    return total
