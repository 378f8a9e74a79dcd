"""Clear apertures: which points (x, y) of a surface transmit light (local frame, mm).

Clear regions: a circle, a square, a rectangle of unequal half widths (OpticStudio's ``SQAP hx hy``, CODE V's
``REX`` / ``REY``). Any aperture may be decentred (``decenter``: OpticStudio's ``OBDC``, CODE V's ``ADX`` /
``ADY``): its clear region and its obscuration move together. An aperture may carry an :class:`Obscuration` (a
circle, a rectangle or an annulus, optionally decentred about the aperture's centre): points inside it are blocked,
so a circular aperture with a circular obscuration is an annulus (a spider-free central obscuration), and an
annular obscuration blocks a ring. :class:`OpenAperture` is an obscuration alone (no clear limit: OpticStudio's
``OBSC`` / ``OBSQ`` aperture types)."""

from __future__ import annotations

import torch
from torch import nn

#: Obscuration shapes and their size keys (lens-file form). An annulus blocks inner_radius <= r <= radius.
OBSCURATION_SHAPES = {"circle": ("radius",), "rectangle": ("half_width_x", "half_width_y"),
                      "annulus": ("inner_radius", "radius")}


def _decenter_buffer(decenter, what: str) -> torch.Tensor:
    dx, dy = (float(v) for v in decenter)
    if not all(abs(v) < float("inf") for v in (dx, dy)):
        raise ValueError(f"{what} decenter must be finite, got {decenter!r}")
    return torch.tensor([dx, dy], dtype=torch.float64, device="cpu")  # built on the CPU; Module.to moves it


def _positive(v, what: str) -> float:
    v = float(v)
    if not v > 0:
        raise ValueError(f"{what} must be > 0 mm, got {v!r}")
    return v


class Obscuration(nn.Module):
    """A central obscuration blocking the points inside it (local frame, mm).

    Args:
        shape: ``"circle"`` (``radius``), ``"rectangle"`` (``half_width_x``, ``half_width_y``) or ``"annulus"``
            (a ring ``inner_radius`` <= r <= ``radius``: light passes inside and outside it).
        decenter: ``(dx, dy)`` mm, the obscuration's centre (relative to its aperture's centre).
    """

    def __init__(self, shape: str = "circle", radius: float | None = None, half_width_x: float | None = None,
                 half_width_y: float | None = None, decenter=(0.0, 0.0), inner_radius: float | None = None):
        super().__init__()
        if shape not in OBSCURATION_SHAPES:
            raise ValueError(f"unknown obscuration shape {shape!r} (expected 'circle', 'rectangle' or 'annulus')")
        self.shape = shape
        if shape in ("circle", "annulus"):
            self.register_buffer("radius", torch.tensor(_positive(radius if radius is not None else 0.0,
                                                                  "obscuration radius"), dtype=torch.float64))
        if shape == "annulus":
            rin = _positive(inner_radius if inner_radius is not None else 0.0, "annular obscuration inner_radius")
            if not rin < float(radius):
                raise ValueError(f"annular obscuration: inner_radius {rin!r} must be < radius {float(radius)!r}")
            self.register_buffer("inner_radius", torch.tensor(rin, dtype=torch.float64))
        if shape == "rectangle":
            hx = _positive(half_width_x if half_width_x is not None else 0.0, "obscuration half_width_x")
            hy = _positive(half_width_y if half_width_y is not None else hx, "obscuration half_width_y")
            self.register_buffer("half_widths", torch.tensor([hx, hy], dtype=torch.float64))
        self.register_buffer("decenter", _decenter_buffer(decenter, "obscuration"))

    def slack(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Signed distance (mm) to the obscuration's edge: > 0 outside (clear), < 0 inside (blocked)."""
        u = x - self.decenter[0].to(x.dtype)
        v = y - self.decenter[1].to(x.dtype)
        if self.shape == "circle":
            return torch.sqrt((u * u + v * v).clamp_min(1e-300)) - self.radius.to(x.dtype)
        if self.shape == "annulus":
            r = torch.sqrt((u * u + v * v).clamp_min(1e-300))
            return torch.maximum(self.inner_radius.to(x.dtype) - r, r - self.radius.to(x.dtype))
        h = self.half_widths.to(x.dtype)
        return torch.maximum(u.abs() - h[0], v.abs() - h[1])

    def blocks(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Bool tensor: True where (x, y) lies strictly inside the obscuration."""
        return self.slack(x, y) < 0

    def to_spec(self) -> dict:
        if self.shape == "circle":
            out = {"shape": "circle", "radius": float(self.radius)}
        elif self.shape == "annulus":
            out = {"shape": "annulus", "inner_radius": float(self.inner_radius), "radius": float(self.radius)}
        else:
            out = {"shape": "rectangle", "half_width_x": float(self.half_widths[0]),
                   "half_width_y": float(self.half_widths[1])}
        d = [float(v) for v in self.decenter]
        if any(d):
            out["decenter"] = d
        return out

    def extra_repr(self):
        return ", ".join(f"{k}={v}" for k, v in self.to_spec().items())


def obscuration_from_spec(spec: dict | None) -> Obscuration | None:
    """Build an obscuration from ``{"shape": "circle", "radius": r, "decenter": [dx, dy]}`` (or rectangle)."""
    if spec is None:
        return None
    shape = spec.get("shape", "circle")
    kw = {k: spec[k] for k in OBSCURATION_SHAPES.get(shape, ()) if k in spec}
    if shape == "annulus" and "outer_radius" in spec and "radius" not in spec:
        kw["radius"] = spec["outer_radius"]
    return Obscuration(shape, decenter=spec.get("decenter", (0.0, 0.0)), **kw)


class Aperture(nn.Module):
    """Base class. ``contains(x, y)`` -> bool tensor; ``extent`` = largest |x| or |y| reached (mm).

    Subclasses define the clear region (``_contains``, ``_slack``); an optional ``obscuration`` blocks the
    points inside it, in ``contains`` and ``slack`` alike."""

    shape = "none"

    def _set_decenter(self, decenter) -> None:
        """The aperture's centre ``(dx, dy)`` mm in the surface's local frame (OpticStudio's OBDC)."""
        self.register_buffer("decenter", _decenter_buffer(decenter, "aperture"))
        self._decentered = any(float(v) != 0.0 for v in decenter)  # fixed at construction: no device sync

    def _local(self, x, y):
        """(x, y) relative to the aperture's centre."""
        if not self.decentered:
            return x, y
        d = self.decenter.to(device=x.device, dtype=x.dtype)
        return x - d[0], y - d[1]

    @property
    def decentered(self) -> bool:
        """Whether the aperture is decentred (OBDC / ADX, ADY)."""
        return getattr(self, "_decentered", False)

    def _set_obscuration(self, obscuration) -> None:
        if isinstance(obscuration, dict):
            obscuration = obscuration_from_spec(obscuration)
        if obscuration is not None and not isinstance(obscuration, Obscuration):
            raise TypeError(f"obscuration must be an Obscuration, a dict or None, got {type(obscuration).__name__}")
        self.obscuration = obscuration

    def _contains(self, x, y):
        raise NotImplementedError

    def _slack(self, x, y):
        raise NotImplementedError

    def clear_contains(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Bool tensor: inside the clear region, the obscuration not applied."""
        return self._contains(*self._local(x, y))

    def contains(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        x, y = self._local(x, y)
        ok = self._contains(x, y)
        if self.obscuration is not None:
            ok = ok & ~self.obscuration.blocks(x, y)
        return ok

    def slack(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Signed distance (mm) from (x, y) to the aperture edge: > 0 inside, < 0 outside. Smooth across
        the edge, so the ray-wave model can place a vignetting edge with sub-pixel accuracy. With an
        obscuration: the smaller of the clear slack and the distance outside the obscuration."""
        x, y = self._local(x, y)
        s = self._slack(x, y)
        if self.obscuration is not None:
            s = torch.minimum(s, self.obscuration.slack(x, y))
        return s

    @property
    def extent(self) -> float | None:
        raise NotImplementedError

    def _obscuration_spec(self, out: dict) -> dict:
        if self.decentered:
            out["decenter"] = [float(v) for v in self.decenter]
        if self.obscuration is not None:
            out["obscuration"] = self.obscuration.to_spec()
        return out

    def _decenter_extent(self) -> float:
        """How far the decentre moves the aperture from the axis (mm)."""
        return float(torch.linalg.vector_norm(self.decenter)) if self.decentered else 0.0  # no sync when centred

    def blocked_by(self, x: float, y: float) -> str | None:
        """What of this aperture blocks the point (x, y) mm (local frame), in words, or None when it passes: its
        obscuration (e.g. "its central obscuration (circle of radius 2 mm)") or its clear region."""
        dev = next(self.buffers()).device  # the aperture's (the lens's) device
        xt = torch.tensor([float(x)], dtype=torch.float64, device=dev)
        yt = torch.tensor([float(y)], dtype=torch.float64, device=dev)
        u, v = self._local(xt, yt)
        if self.obscuration is not None and bool(self.obscuration.blocks(u, v)[0]):
            o = self.obscuration.to_spec()
            central = not any(o.get("decenter", [0.0, 0.0])) and not self.decentered and o["shape"] != "annulus"
            size = {"circle": f"circle of radius {o.get('radius', 0):g} mm",
                    "annulus": f"ring {o.get('inner_radius', 0):g}–{o.get('radius', 0):g} mm",
                    "rectangle": f"rectangle {2 * o.get('half_width_x', 0):g} × {2 * o.get('half_width_y', 0):g} mm"}
            return (f"its {'central ' if central else ''}obscuration ({size[o['shape']]}"
                    f"{', decentred ' + str(o['decenter']) + ' mm' if 'decenter' in o else ''})")
        if not bool(self._contains(u, v)[0]):
            return f"its clear aperture ({self.to_spec()})"
        return None

    def stop_edge_refusal(self) -> str | None:
        """Why the ray-wave engine's stop-edge construction cannot use this aperture as the stop (it samples the
        stop's rim as a circle about the axis), or None for a centred circle."""
        if self.shape != "circle":
            return (f"the stop's aperture is a {self.shape} ({self.to_spec()}); the exit-pupil stop-edge "
                    "construction samples the stop's rim as a circle about the axis")
        if self.decentered:
            return (f"the stop's aperture is decentred by {[float(v) for v in self.decenter]} mm; the exit-pupil "
                    "stop-edge construction samples the stop's rim as a circle about the axis")
        return None

    def to_spec(self) -> dict:
        raise NotImplementedError

    def _obs_repr(self) -> str:
        return "" if self.obscuration is None else ", obscured"


class CircularAperture(Aperture):
    """A circle of ``radius`` (mm) about the axis, optionally with a central ``obscuration``.

    ``fixed``: on the stop, a clear aperture of the stop's own (a .zmx stop's ``CLAP``) that the system aperture does
    not resize beyond: :meth:`raywave.lens.lens.Lens.set_system_aperture` keeps ``fixed_radius`` (mm) as the stop's
    hard edge where it is smaller than the radius the system aperture gives the stop (OpticStudio: a surface aperture
    vignettes whatever the system aperture says), while the paraxial pupil still comes from the system aperture."""

    shape = "circle"

    def __init__(self, radius: float, obscuration: Obscuration | dict | None = None, decenter=(0.0, 0.0),
                 fixed: bool = False):
        super().__init__()
        if not radius > 0:
            raise ValueError(f"circular aperture radius must be > 0 mm, got {radius!r}")
        self.register_buffer("radius", torch.tensor(float(radius), dtype=torch.float64))
        self._set_decenter(decenter)
        self._set_obscuration(obscuration)
        #: the stop's own clear radius (mm) that a system aperture does not enlarge, or None (:attr:`fixed`)
        self.fixed_radius = float(radius) if fixed else None

    @property
    def fixed(self) -> bool:
        """Whether the system aperture keeps this (stop) aperture's own radius where it is the smaller."""
        return self.fixed_radius is not None

    def _contains(self, x, y):
        r = self.radius.to(x.dtype)
        return x * x + y * y <= r * r

    def _slack(self, x, y):
        return self.radius.to(x.dtype) - torch.sqrt((x * x + y * y).clamp_min(1e-300))  # finite gradient at 0

    @property
    def extent(self) -> float:
        return float(self.radius) + self._decenter_extent()

    def set_radius(self, radius: float) -> None:
        self.radius.fill_(float(radius))

    def to_spec(self) -> dict:
        out = self._obscuration_spec({"shape": "circle", "radius": float(self.radius)})
        if self.fixed:
            out["fixed"] = True
        return out

    def extra_repr(self):
        return f"radius={float(self.radius)}"


class SquareAperture(Aperture):
    """A square |x|, |y| <= ``half_width`` (mm) (e.g. a square DOE or sensor), optionally with an obscuration."""

    shape = "square"

    def __init__(self, half_width: float, obscuration: Obscuration | dict | None = None, decenter=(0.0, 0.0)):
        super().__init__()
        if not half_width > 0:
            raise ValueError(f"square aperture half_width must be > 0 mm, got {half_width!r}")
        self.register_buffer("half_width", torch.tensor(float(half_width), dtype=torch.float64))
        self._set_decenter(decenter)
        self._set_obscuration(obscuration)

    def _contains(self, x, y):
        h = self.half_width.to(x.dtype)
        return (x.abs() <= h) & (y.abs() <= h)

    def _slack(self, x, y):
        return self.half_width.to(x.dtype) - torch.maximum(x.abs(), y.abs())

    @property
    def extent(self) -> float:
        return float(self.half_width) * 2**0.5 + self._decenter_extent()

    def set_radius(self, radius: float) -> None:
        self.half_width.fill_(float(radius))

    def to_spec(self) -> dict:
        return self._obscuration_spec({"shape": "square", "half_width": float(self.half_width)})

    def extra_repr(self):
        return f"half_width={float(self.half_width)}"


class RectangularAperture(Aperture):
    """A rectangle |x| <= ``half_width_x``, |y| <= ``half_width_y`` (mm) about its centre, optionally decentred and
    with an obscuration (OpticStudio's ``SQAP hx hy``; CODE V's ``REX`` / ``REY``).

    On the stop, :meth:`set_radius` does not resize the rectangle (a fixed hard aperture, as OpticStudio keeps
    it): it records ``pupil_radius``, the circular stop radius that the system aperture gives the paraxial pupil."""

    shape = "rectangle"

    def __init__(self, half_width_x: float, half_width_y: float, obscuration: Obscuration | dict | None = None,
                 decenter=(0.0, 0.0)):
        super().__init__()
        hx = _positive(half_width_x, "rectangular aperture half_width_x")
        hy = _positive(half_width_y, "rectangular aperture half_width_y")
        self.register_buffer("half_widths", torch.tensor([hx, hy], dtype=torch.float64))
        self._set_decenter(decenter)
        self._set_obscuration(obscuration)
        self.pupil_radius: float | None = None

    def _contains(self, x, y):
        h = self.half_widths.to(x.dtype)
        return (x.abs() <= h[0]) & (y.abs() <= h[1])

    def _slack(self, x, y):
        h = self.half_widths.to(x.dtype)
        return torch.minimum(h[0] - x.abs(), h[1] - y.abs())

    @property
    def extent(self) -> float:
        return float(torch.linalg.vector_norm(self.half_widths)) + self._decenter_extent()

    def set_radius(self, radius: float) -> None:
        self.pupil_radius = float(radius)

    def to_spec(self) -> dict:
        return self._obscuration_spec({"shape": "rectangle", "half_width_x": float(self.half_widths[0]),
                                       "half_width_y": float(self.half_widths[1])})

    def extra_repr(self):
        return f"half_width_x={float(self.half_widths[0])}, half_width_y={float(self.half_widths[1])}"


class OpenAperture(Aperture):
    """No clear limit, only an ``obscuration`` (OpticStudio's obscuration aperture types): everything outside
    the obscuration transmits. ``extent`` is None (the surface's semi-diameter is its size)."""

    shape = "none"

    def __init__(self, obscuration: Obscuration | dict):
        super().__init__()
        self._set_obscuration(obscuration)
        if self.obscuration is None:
            raise ValueError("an open aperture ('shape': 'none') needs an obscuration")

    def _contains(self, x, y):
        return torch.ones_like(x, dtype=torch.bool)

    def _slack(self, x, y):
        return torch.full_like(x, float("inf"))

    @property
    def extent(self) -> None:
        return None

    def set_radius(self, radius: float) -> None:
        raise ValueError("the stop has only an obscuration (aperture shape 'none'): give it a clear aperture "
                         "('circle' or 'square') to size it from the entrance pupil")

    def to_spec(self) -> dict:
        return self._obscuration_spec({"shape": "none"})


def aperture_from_spec(spec: dict | None) -> Aperture | None:
    """Build an aperture from the lens-file form ``{"shape": "circle", "radius": r}`` (or ``"square"``
    ``half_width``, ``"rectangle"`` ``half_width_x`` / ``half_width_y``, or ``"none"``), with an optional
    ``"decenter": [dx, dy]`` (mm; not on ``"none"``: decentre its obscuration) and ``"obscuration"`` entry (see
    :func:`obscuration_from_spec`); None -> None."""
    if spec is None:
        return None
    obs = obscuration_from_spec(spec.get("obscuration"))
    dec = spec.get("decenter", (0.0, 0.0))
    if spec["shape"] == "circle":
        return CircularAperture(spec["radius"], obs, dec, fixed=bool(spec.get("fixed", False)))
    if spec["shape"] == "square":
        return SquareAperture(spec["half_width"], obs, dec)
    if spec["shape"] == "rectangle":
        return RectangularAperture(spec["half_width_x"], spec["half_width_y"], obs, dec)
    if spec["shape"] == "none":
        if any(float(v) for v in dec):
            raise ValueError("an open aperture ('shape': 'none') has no centre to decentre: give the decenter to "
                             "its obscuration")
        return OpenAperture(obs)
    raise ValueError(f"unknown aperture shape {spec['shape']!r} (expected 'circle', 'square', 'rectangle' or "
                     "'none')")
