"""2D lens layout (y–z section) with ray fans for several fields."""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.lens.sources import point_source_rays
from raywave.plotting._mpl import new_figure, save

FIELD_COLOURS = ["tab:blue", "tab:green", "tab:red", "tab:orange", "tab:purple", "tab:brown"]


def _trace_fans(lens, fields, n_rays: int, wavelength: float):
    """Meridional fans: per field a list of (z, y) polylines of the valid rays."""
    py = torch.linspace(-1, 1, n_rays, dtype=torch.float64)
    px = torch.zeros_like(py)
    f = torch.tensor([[0.0, float(v)] for v in fields], dtype=torch.float64)
    with torch.no_grad():
        rays = point_source_rays(lens, f, wavelength, pupil=(px, py))
        # Start rays a little in front of the first surface so the object side is drawn.
        _, rec = lens.trace_to_image(rays, record=True)
    ys = torch.stack([p[1] for p in rec.points], -1)[:, 0]  # (F, N, S)
    zs = torch.stack([torch.broadcast_to(p[2], p[1].shape) for p in rec.points], -1)[:, 0]
    ok = rec.valid[-1][:, 0]
    return zs.numpy(), ys.numpy(), ok.numpy()


def _surface_heights(lens, zs, ys, ok) -> list[float]:
    """Half-height to draw each surface: its clear radius, else the largest ray height on it."""
    out = []
    for i, s in enumerate(lens.surfaces):
        r = s.clear_radius()
        if r is None:
            h = np.abs(ys[..., i + 1][ok]) if ok.any() else np.array([1.0])
            r = float(h.max()) * 1.05 if h.size else 1.0
        out.append(float(r))
    return out


def _profile(surface, z0: float, h: float, n: int = 101):
    y = torch.linspace(-h, h, n, dtype=torch.float64)
    with torch.no_grad():
        ok = surface.geometry.in_domain(torch.zeros_like(y), y)
        z = surface.geometry.sag(torch.zeros_like(y), torch.where(ok, y, 0.0))
    return (z0 + z.numpy())[ok.numpy()], y.numpy()[ok.numpy()]


def _draw_rays(ax, lens, zs, ys, ok, n_fields: int, n_rays: int) -> None:
    """Draw the valid rays of the ``n_fields`` fans of ``n_rays`` rays ((F, N, S) z / y polylines, mm), one colour
    per field: from the object point when it is close, else from a short stub in front of the lens."""
    stub = 0.15 * lens.total_track()
    from_object = not math.isinf(lens.object_distance) and lens.object_distance <= lens.total_track()
    for fi in range(n_fields):
        colour = FIELD_COLOURS[fi % len(FIELD_COLOURS)]
        for k in range(n_rays):
            if not ok[fi, k]:
                continue
            z, y = zs[fi, k], ys[fi, k]
            if not from_object:
                dz, dy = z[1] - z[0], y[1] - y[0]
                slope = dy / dz if dz != 0 else 0.0
                z = np.concatenate([[z[1] - stub], z[1:]])
                y = np.concatenate([[y[1] - stub * slope], y[1:]])
            ax.plot(z, y, color=colour, lw=0.6)


def _draw_surfaces(ax, lens, zv, heights) -> None:
    """Draw the surfaces (at vertex z ``zv``, mm, to half-heights ``heights``, mm: an ideal lens as an arrow, a flat
    stop in air as two bars, else its profile) and the element edges joining the rims of glass elements."""
    prev = None
    for i, s in enumerate(lens.surfaces):
        if is_doe_plane(s):  # drawn by _draw_doe_planes; the element edges join the surfaces around it
            continue
        zp, yp = _profile(s, float(zv[i]), heights[i])
        style = dict(color="k", lw=1.0 if not s.is_stop else 2.0)
        if s.kind == "paraxial":
            ax.annotate("", xy=(zv[i], heights[i]), xytext=(zv[i], -heights[i]),
                        arrowprops=dict(arrowstyle="<->", color="k"))
        elif s.is_stop and s.geometry.paraxial_curvature().item() == 0 and s.material.is_air:
            ax.plot([zv[i], zv[i]], [heights[i], heights[i] * 1.3], **style)
            ax.plot([zv[i], zv[i]], [-heights[i], -heights[i] * 1.3], **style)
        elif zp.size:
            ax.plot(zp, yp, **style)
        if prev is not None and not prev[2].material.is_air and zp.size and prev[0].size:
            for end in (0, -1):  # element edges: join the rims of its two faces
                ax.plot([prev[0][end], zp[end]], [prev[1][end], yp[end]], color="k", lw=1.0)
        prev = (zp, yp, s)


def is_doe_plane(surface) -> bool:
    """Whether ``surface`` is a thin DOE plane placed inside a lens (:func:`raywave.hybrid.midsystem.insert_doe`:
    a plane with a diffractive interaction)."""
    return surface.interaction.kind == "diffraction" and surface.geometry.paraxial_curvature().item() == 0


def _draw_doe_planes(ax, lens, zv, heights) -> None:
    """Draw every DOE plane inside ``lens`` (:func:`is_doe_plane`) as :func:`draw_doe_plane`, labelled with the
    surface it follows."""
    for i, s in enumerate(lens.surfaces):
        if is_doe_plane(s):
            draw_doe_plane(ax, float(zv[i]), heights[i], label=f"DOE (after surface {max(i - 1, 0)})")


def draw_doe_plane(ax, z: float, half_height: float, label: str = "DOE") -> None:
    """Draw a DOE plane at ``z`` (mm) across ``±half_height`` (mm): a dashed magenta bar with a label."""
    ax.plot([z, z], [-half_height, half_height], color="tab:pink", lw=2.0, ls="--", label=label)
    ax.annotate(label, xy=(z, -half_height), xytext=(0, -11), textcoords="offset points", ha="center", fontsize=8,
                color="tab:pink")


def doe_plane_of(doe: dict, lens) -> tuple[float, float]:
    """(z mm, half-height mm) of a DOE given as a lens file's ``"doe"`` section (``distance`` mm after the last
    vertex, ``size`` [w, h] mm; without a size, sized to the beam as the ray-wave engine does)."""
    z = float(lens.vertex_z()[-1].detach()) + float(doe.get("distance", 0.0))
    size = doe.get("size")
    if size is None:
        from raywave.assembly.build import default_doe_size

        size = default_doe_size(lens, float(doe.get("distance", 0.0)))
    return z, 0.5 * float(size[1])


def plot_hybrid_layout(hl, path=None, fields=None, n_rays: int = 7, wavelength: float | None = None):
    """:func:`plot_layout` of a :class:`~raywave.hybrid.HybridLens`'s lens with its DOE plane drawn."""
    return plot_layout(hl.lens, path, fields, n_rays, wavelength,
                       doe={"distance": hl.doe_distance, "size": list(hl.doe.size)})


def plot_midsystem_layout(ml, path=None, fields=None, n_rays: int = 7, wavelength: float | None = None):
    """:func:`plot_layout` of a :class:`~raywave.hybrid.midsystem.MidSystemLens`: its lens with the DOE plane in
    place, the rays bent by the DOE's strongest order at ``wavelength`` (default the primary)."""
    from raywave.hybrid.midsystem import DOEPhaseSurface, insert_doe

    wl = ml.lens.primary_wavelength if wavelength is None else wavelength
    scale = ml.orders(wl)[0][0]
    lens = insert_doe(ml.lens, ml.after, ml.distance, DOEPhaseSurface(ml.doe, float(scale)), 1.0, ml.doe)
    return plot_layout(lens, path, fields, n_rays, wl)


def plot_layout(lens, path=None, fields=None, n_rays: int = 7, wavelength: float | None = None, ax=None,
                doe: dict | None = None):
    """Draw the lens section and meridional ray fans; write a PNG if ``path`` is given.

    Args:
        fields: field values along y (degrees or mm, as the lens's fields; default: the lens's).
        n_rays: rays per fan.
        doe: a DOE to draw, as a lens file's ``"doe"`` section (``distance`` mm after the last vertex, ``size``);
            :func:`plot_hybrid_layout` passes a hybrid lens's. A DOE plane inside ``lens`` (issue 46,
            :func:`plot_midsystem_layout`) is drawn the same way where it sits, its rays bent by it.
    Returns the matplotlib figure.
    """
    lens.require_unfolded("plot_layout")
    fields = list(lens.fields) if fields is None else list(fields)
    wl = lens.primary_wavelength if wavelength is None else wavelength
    zs, ys, ok = _trace_fans(lens, fields, n_rays, wl)
    fig = None
    if ax is None:
        fig, ax = new_figure(9, 4)
    zv = lens.vertex_z().detach().numpy()
    heights = _surface_heights(lens, zs, ys, ok)
    _draw_rays(ax, lens, zs, ys, ok, len(fields), n_rays)
    _draw_surfaces(ax, lens, zv, heights)
    _draw_doe_planes(ax, lens, zv, heights)
    zi = float(lens.image_z().detach())
    # The sensor is drawn to its half-diagonal: field points are radial, so they land within it.
    hi = max(heights) if lens.sensor_size is None else 0.5 * math.hypot(*lens.sensor_size)
    ax.plot([zi, zi], [-hi, hi], color="0.3", lw=2)
    if doe is not None:
        draw_doe_plane(ax, *doe_plane_of(doe, lens))
    ax.set_aspect("equal")
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    unit = "°" if lens.field_type == "angle" else " mm"
    ax.set_title(f"{lens.name or 'lens'}: fields " + ", ".join(f"{f:g}{unit}" for f in fields))
    if fig is not None and path is not None:
        save(fig, path)
    return fig if fig is not None else ax.figure
