"""DOEs <-> plain dicts and files: ``DOE.to_spec()`` / :func:`doe_from_spec`, :func:`save_doe` / :func:`load_doe`
(spec + ``state_dict`` in one ``torch.save`` file), and :func:`doe_from_phase_model` for a lens file's
``doe.phase_model`` (docs/lens-format.md)."""

from __future__ import annotations

from pathlib import Path

import torch

from raywave.doe.base import DOE, BlankDOE, PixelDOE, check_levels
from raywave.doe.params import Binary2DOE, CubicDOE, FresnelDOE, GratingDOE, RadialDOE, SumDOE, ZernikeDOE
from raywave.utils.errors import NonFiniteError

__all__ = ["MAX_PHASE", "MODEL_TYPES", "check_phase_finite", "doe_from_phase_model", "doe_from_spec", "load_doe", "save_doe"]

#: phase-model ``type`` -> DOE class
MODEL_TYPES = {"blank": BlankDOE, "pixel": PixelDOE, "radial": RadialDOE, "binary_2": Binary2DOE,
               "zernike": ZernikeDOE, "fresnel": FresnelDOE, "grating": GratingDOE, "cubic": CubicDOE,
               "sum": SumDOE}
_FORMAT = "raywave-doe"
#: largest |phase| (rad) a DOE may reach: beyond it float64 resolves the phase to worse than ~1e-4 rad
MAX_PHASE = 1e12
_CHECK_SAMPLES = 192  # pixels a side of the sub-grid on which check_phase_finite evaluates the phase


def check_phase_finite(doe: DOE, what: str = "the DOE phase",
                       hint: str = "check its coefficients, order and normalisation radius") -> None:
    """Raise :class:`~raywave.utils.errors.NonFiniteError` when ``doe``'s design phase is NaN, infinite or beyond
    :data:`MAX_PHASE` rad on its grid (e.g. a BINARY_2 order of 1e308, a normalisation radius of 1e-300 mm).

    The phase is evaluated on a strided sub-grid of at most ~192² pixels plus the outer rows and columns (where
    polynomial phases peak), so the check is cheap for any grid size."""
    ny, nx = doe.shape
    sy, sx = max(1, ny // _CHECK_SAMPLES), max(1, nx // _CHECK_SAMPLES)
    picks = [(slice(0, ny, sy), slice(0, nx, sx)), (slice(ny - 1, ny), slice(0, nx, sx)),
             (slice(0, ny, sy), slice(nx - 1, nx)), (slice(ny - 1, ny), slice(nx - 1, nx))]
    with torch.no_grad():
        for rows, cols in picks:
            ph = doe.design_phase_pixels(rows, cols) * doe.phase_scale
            bad = ~torch.isfinite(ph) | (ph.abs() > MAX_PHASE)
            if bool(bad.any()):
                iy, ix = (int(v) for v in bad.nonzero()[0])
                iy = range(*rows.indices(ny))[iy]
                ix = range(*cols.indices(nx))[ix]
                v = float(ph[bad][0])
                raise NonFiniteError(f"{what} is {v:g} rad at pixel [{iy}, {ix}] of the {ny}×{nx} DOE (allowed: "
                                     f"finite, |phase| <= {MAX_PHASE:g} rad): {hint}; {doe.extra_repr()}")


def _build(model: dict, shape, pitch, aperture, optics: dict) -> DOE:
    if not isinstance(model, dict) or model.get("type") not in MODEL_TYPES:
        kind = model.get("type") if isinstance(model, dict) else model
        raise ValueError(f"unknown DOE phase model {kind!r}: one of {', '.join(MODEL_TYPES)}")
    kind = model["type"]
    if kind == "blank":
        return BlankDOE(shape, pitch, aperture, **optics)
    if kind == "pixel":
        return PixelDOE(torch.zeros(tuple(shape), dtype=torch.float64), pitch, aperture=aperture,
                        trainable=bool(model.get("trainable", True)), **_pixel_optics(optics))
    if kind == "sum":
        terms = [doe_from_spec(t) for t in model["terms"]]
        return SumDOE(*terms, aperture=aperture, design_wavelength=model.get("term_wavelength"),
                      **{k: v for k, v in optics.items() if k != "design_wavelength"})
    return MODEL_TYPES[kind].from_model_spec(model, shape, pitch, aperture, **optics)


def _pixel_optics(optics: dict) -> dict:
    out = dict(optics)
    if out.get("dispersion") == "none":
        out.pop("design_wavelength", None)  # PixelDOE: design_wavelength=None means "none"
        out["dispersion"] = "none"
    return out


def doe_from_spec(spec: dict) -> DOE:
    """A DOE from :meth:`DOE.to_spec` (pixel maps come back as zeros: load the ``state_dict`` after)."""
    optics = {"design_wavelength": spec.get("design_wavelength"), "material": spec.get("material"),
              "dispersion": spec.get("dispersion"), "n_medium": spec.get("n_medium", 1.0)}
    doe = _build(spec["model"], tuple(spec["shape"]), float(spec["pitch"]), spec.get("aperture", "square"), optics)
    return doe._load_optics(spec)


def save_doe(doe: DOE, path) -> None:
    """Write ``doe`` (its spec and its ``state_dict``) to ``path`` (a ``torch.save`` file, e.g. ``.pt``)."""
    state = {k: v.detach().cpu() for k, v in doe.state_dict().items()}
    torch.save({"format": _FORMAT, "spec": doe.to_spec(), "state_dict": state}, Path(path))


def load_doe(path, map_location="cpu") -> DOE:
    """The DOE written by :func:`save_doe`."""
    data = torch.load(Path(path), map_location=map_location, weights_only=True)
    if not isinstance(data, dict) or data.get("format") != _FORMAT:
        raise ValueError(f"{str(path)!r} is not a raywave DOE file (written by raywave.doe.save_doe)")
    doe = doe_from_spec(data["spec"])
    doe.load_state_dict(data["state_dict"])
    return doe


def doe_from_phase_model(model: dict, shape, pitch: float, aperture: str = "square",
                         design_wavelength: float | None = None, material=None, levels: int | None = None,
                         wrap: bool = False) -> DOE:
    """The DOE of a lens file's ``doe.phase_model`` (checked by :mod:`raywave.io.doe`) on the grid
    ``shape`` × ``pitch``. Without a material and a design wavelength the phase is the same at every wavelength
    (as OpticStudio's BINARY_2); a design wavelength alone makes it a fixed optical path in air; a material a
    dispersive height map designed at ``design_wavelength`` (default 0.55 µm). ``levels``: fabricate it (wrap
    and quantise at the design wavelength); ``wrap`` alone: wrap it to [0, 2π) there without quantising (a
    continuous kinoform)."""
    optics = {"design_wavelength": design_wavelength, "material": material,
              "dispersion": "material" if material is not None else ("air" if design_wavelength is not None
                                                                      else "none")}
    if model.get("type") == "sum":
        terms = [_build(t, shape, pitch, aperture, optics) for t in model["terms"]]
        doe = SumDOE(*terms, aperture=aperture)
    else:
        doe = _build(model, shape, pitch, aperture, optics)
    check_phase_finite(doe, f"the {model.get('type')} phase model's phase")
    if levels is not None:
        doe.fabricate(levels=check_levels(levels))
    elif wrap:
        doe.fabricate(levels=None)
    return doe
