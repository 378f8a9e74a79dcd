"""Dispersive catalog glasses and model (nd, Vd) glasses."""

from __future__ import annotations

import warnings

import torch
from torch import nn

from raywave.materials import formulas
from raywave.materials.base import Material

#: Fraunhofer lines (µm) that define nd and Vd.
LINE_D, LINE_F, LINE_C = 0.5875618, 0.4861327, 0.6562725


class WavelengthRangeWarning(UserWarning):
    """A glass is evaluated outside the wavelength range its data cover."""


def _as_wavelength(wavelength) -> torch.Tensor:
    """Python numbers and integer tensors become float64; floating tensors keep their dtype."""
    if not isinstance(wavelength, torch.Tensor):
        return torch.as_tensor(wavelength, dtype=torch.float64, device="cpu")
    return wavelength if wavelength.is_floating_point() else wavelength.to(torch.float64)


class DispersiveGlass(Material):
    """A glass given by a dispersion formula (or a table) with its coefficients in a float64 buffer.

    Args:
        name: glass name, e.g. "N-BK7".
        family: "agf" (Zemax formula numbers 1–13), "rii" (refractiveindex.info formulas 1–9) or
            "tabulated" (coefficients: a (K, 2) table of λ, n).
        formula: the formula number within the family (ignored for "tabulated").
        coefficients: as the source lists them.
        wavelength_range: (lo, hi) µm where the data are valid; outside it a WavelengthRangeWarning.
        catalog: the catalog it came from (e.g. "SCHOTT"), kept when a lens file names it.
        provenance: where the numbers come from (file, reference, licence).
    """

    def __init__(self, name, family, formula, coefficients, wavelength_range, catalog=None, provenance="",
                 explicit_catalog: bool = False):
        super().__init__(name, wavelength_range)
        if family not in ("agf", "rii", "tabulated"):
            raise ValueError(f"glass {name!r}: unknown formula family {family!r}")
        if family == "agf" and formula not in formulas.AGF_FORMULAS:
            raise ValueError(f"glass {name!r}: unknown AGF formula number {formula!r} (known: 1–13)")
        if family == "rii" and formula not in formulas.RII_FORMULAS:
            raise ValueError(f"glass {name!r}: unknown refractiveindex.info formula {formula!r} (known: 1–9)")
        self.family, self.formula = family, formula
        self.register_buffer("coefficients", torch.as_tensor(coefficients, dtype=torch.float64, device="cpu").clone())
        self.catalog = catalog
        self.provenance = provenance
        self.explicit_catalog = explicit_catalog

    def _check_range(self, wl: torch.Tensor) -> None:
        lo, hi = self.wavelength_range
        w = wl.detach()
        if w.numel() and bool(((w < lo - 1e-12) | (w > hi + 1e-12)).any()):  # one host read (a GPU sync)
            bad = float(w[(w < lo) | (w > hi)].flatten()[0])
            where = f" ({self.catalog})" if self.catalog else ""
            warnings.warn(
                f"glass {self.name!r}{where}: wavelength {bad:g} µm is outside its data range "
                f"{lo:g}–{hi:g} µm; the index is extrapolated", WavelengthRangeWarning, stacklevel=3)

    def n(self, wavelength) -> torch.Tensor:
        wl = _as_wavelength(wavelength)
        self._check_range(wl)
        c = self.coefficients.to(device=wl.device, dtype=wl.dtype)
        if self.family == "agf":
            return formulas.AGF_FORMULAS[self.formula](wl, c)
        if self.family == "rii":
            return formulas.RII_FORMULAS[self.formula](wl, c)
        return formulas.tabulated(wl, c)

    def to_spec(self):
        if self.explicit_catalog and self.catalog:
            return {"name": self.name, "catalog": self.catalog}
        return self.name

    def extra_repr(self) -> str:
        return f"name={self.name!r}, catalog={self.catalog!r}, {self.family} formula {self.formula}"


class ModelGlass(Material):
    """A model glass from its d-line index ``nd`` and Abbe number ``vd`` (early design, OpticStudio's MODEL).

    n(λ) = A + B / λ² with A, B chosen so that n(λd) = nd and (nd − 1) / (nF − nC) = vd exactly.
    ``nd`` and ``vd`` are float64 parameters, so a design may optimise them.
    """

    def __init__(self, nd: float, vd: float, name: str | None = None):
        if not nd > 1.0:
            raise ValueError(f"model glass: nd must be > 1, got {nd!r}")
        if not vd > 0.0:
            raise ValueError(f"model glass: vd must be > 0, got {vd!r}")
        super().__init__(name or f"model({nd:g},{vd:g})")
        self.nd = nn.Parameter(torch.tensor(float(nd), dtype=torch.float64))
        self.vd = nn.Parameter(torch.tensor(float(vd), dtype=torch.float64))

    def n(self, wavelength) -> torch.Tensor:
        wl = _as_wavelength(wavelength)
        nd, vd = self.nd.to(wl.dtype), self.vd.to(wl.dtype)
        b = (nd - 1) / vd / (1 / LINE_F**2 - 1 / LINE_C**2)
        a = nd - b / LINE_D**2
        return a + b / (wl * wl)

    def to_spec(self):
        return {"model": {"nd": float(self.nd.detach()), "vd": float(self.vd.detach())}}
