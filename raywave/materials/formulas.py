"""Dispersion formulas in float64, differentiable in wavelength (µm) and in the coefficients.

Two families, as the data come:

* ``AGF_FORMULAS[k]``: the formula numbers of Zemax AGF glass catalogs (1 Schott … 13 Extended 3);
* ``RII_FORMULAS[k]``: the ``formula k`` types of the refractiveindex.info database (1 Sellmeier … 9 exotic).

Each function takes ``(wl, c)``: ``wl`` a tensor of wavelengths in µm (any shape), ``c`` a 1-D tensor of
coefficients in the order the source lists them, and returns n with ``wl``'s shape and dtype.
"""

from __future__ import annotations

import torch


def _c(c, i):
    return c[i] if i < c.shape[0] else c.new_zeros(())


def _sqrt_n2(n2):
    # Indices are far from 0 in every valid range; the clamp only keeps wild extrapolation finite.
    return torch.sqrt(torch.clamp(n2, min=1e-6))


# ---------------------------------------------------------------------------- AGF (Zemax) formulas
def schott(wl, c):
    """1 Schott: n² = a0 + a1 λ² + a2 λ⁻² + a3 λ⁻⁴ + a4 λ⁻⁶ + a5 λ⁻⁸."""
    l2 = wl * wl
    return _sqrt_n2(_c(c, 0) + _c(c, 1) * l2 + _c(c, 2) / l2 + _c(c, 3) / l2**2 + _c(c, 4) / l2**3 + _c(c, 5) / l2**4)


def _sellmeier_terms(l2, c, n_terms):
    # the coefficients as 0-d views from one unbind, and the sum started from its first term (0 + x is x exactly):
    # the same values in fewer ops (issue 43: a glass index is evaluated in every trace)
    k = c.unbind() if c.shape[0] >= 2 * n_terms else [_c(c, i) for i in range(2 * n_terms)]
    s = None
    for i in range(n_terms):
        term = k[2 * i] * l2 / (l2 - k[2 * i + 1])
        s = term if s is None else s + term
    return torch.zeros_like(l2) if s is None else s


def sellmeier1(wl, c):
    """2 Sellmeier 1: n² − 1 = Σ₁³ Kᵢ λ² / (λ² − Lᵢ); c = (K1, L1, K2, L2, K3, L3)."""
    return _sqrt_n2(1 + _sellmeier_terms(wl * wl, c, 3))


def herzberger(wl, c):
    """3 Herzberger: n = A + B L + C L² + D λ² + E λ⁴ + F λ⁶, L = 1 / (λ² − 0.028)."""
    l2 = wl * wl
    L = 1.0 / (l2 - 0.028)
    return _c(c, 0) + _c(c, 1) * L + _c(c, 2) * L * L + _c(c, 3) * l2 + _c(c, 4) * l2**2 + _c(c, 5) * l2**3


def sellmeier2(wl, c):
    """4 Sellmeier 2: n² − 1 = A + B1 λ² / (λ² − λ1²) + B2 / (λ² − λ2²); c = (A, B1, λ1, B2, λ2)."""
    l2 = wl * wl
    return _sqrt_n2(1 + _c(c, 0) + _c(c, 1) * l2 / (l2 - _c(c, 2) ** 2) + _c(c, 3) / (l2 - _c(c, 4) ** 2))


def conrady(wl, c):
    """5 Conrady: n = n0 + A / λ + B / λ^3.5."""
    return _c(c, 0) + _c(c, 1) / wl + _c(c, 2) / wl**3.5


def sellmeier3(wl, c):
    """6 Sellmeier 3: four terms Kᵢ λ² / (λ² − Lᵢ)."""
    return _sqrt_n2(1 + _sellmeier_terms(wl * wl, c, 4))


def handbook1(wl, c):
    """7 Handbook of Optics 1: n² = A + B / (λ² − C) − D λ²."""
    l2 = wl * wl
    return _sqrt_n2(_c(c, 0) + _c(c, 1) / (l2 - _c(c, 2)) - _c(c, 3) * l2)


def handbook2(wl, c):
    """8 Handbook of Optics 2: n² = A + B λ² / (λ² − C) − D λ²."""
    l2 = wl * wl
    return _sqrt_n2(_c(c, 0) + _c(c, 1) * l2 / (l2 - _c(c, 2)) - _c(c, 3) * l2)


def sellmeier4(wl, c):
    """9 Sellmeier 4: n² = A + B λ² / (λ² − C) + D λ² / (λ² − E)."""
    l2 = wl * wl
    return _sqrt_n2(_c(c, 0) + _c(c, 1) * l2 / (l2 - _c(c, 2)) + _c(c, 3) * l2 / (l2 - _c(c, 4)))


def extended1(wl, c):
    """10 Extended 1: n² = a0 + a1 λ² + a2 λ⁻² + … + a7 λ⁻¹²."""
    l2 = wl * wl
    n2 = _c(c, 0) + _c(c, 1) * l2
    for i in range(2, 8):
        n2 = n2 + _c(c, i) / l2 ** (i - 1)
    return _sqrt_n2(n2)


def sellmeier5(wl, c):
    """11 Sellmeier 5: five terms Kᵢ λ² / (λ² − Lᵢ)."""
    return _sqrt_n2(1 + _sellmeier_terms(wl * wl, c, 5))


def extended2(wl, c):
    """12 Extended 2: n² = a0 + a1 λ² + a2 λ⁻² + a3 λ⁻⁴ + a4 λ⁻⁶ + a5 λ⁻⁸ + a6 λ⁴ + a7 λ⁶."""
    l2 = wl * wl
    n2 = _c(c, 0) + _c(c, 1) * l2 + _c(c, 2) / l2 + _c(c, 3) / l2**2 + _c(c, 4) / l2**3 + _c(c, 5) / l2**4
    return _sqrt_n2(n2 + _c(c, 6) * l2**2 + _c(c, 7) * l2**3)


def extended3(wl, c):
    """13 Extended 3: n² = a0 + a1 λ² + a2 λ⁴ + a3 λ⁻² + a4 λ⁻⁴ + a5 λ⁻⁶ + a6 λ⁻⁸ + a7 λ⁻¹⁰ + a8 λ⁻¹²."""
    l2 = wl * wl
    n2 = _c(c, 0) + _c(c, 1) * l2 + _c(c, 2) * l2**2
    for i in range(3, 9):
        n2 = n2 + _c(c, i) / l2 ** (i - 2)
    return _sqrt_n2(n2)


AGF_FORMULAS = {
    1: schott, 2: sellmeier1, 3: herzberger, 4: sellmeier2, 5: conrady, 6: sellmeier3, 7: handbook1,
    8: handbook2, 9: sellmeier4, 10: extended1, 11: sellmeier5, 12: extended2, 13: extended3,
}
AGF_NAMES = {
    1: "Schott", 2: "Sellmeier 1", 3: "Herzberger", 4: "Sellmeier 2", 5: "Conrady", 6: "Sellmeier 3",
    7: "Handbook of Optics 1", 8: "Handbook of Optics 2", 9: "Sellmeier 4", 10: "Extended 1",
    11: "Sellmeier 5", 12: "Extended 2", 13: "Extended 3",
}


# ---------------------------------------------------------------------------- refractiveindex.info types
def rii_sellmeier(wl, c):
    """formula 1: n² − 1 = C0 + Σ Cᵢ λ² / (λ² − Cᵢ₊₁²)."""
    l2 = wl * wl
    s = _c(c, 0) + torch.zeros_like(l2)
    for i in range(1, c.shape[0] - 1, 2):
        s = s + c[i] * l2 / (l2 - c[i + 1] ** 2)
    return _sqrt_n2(1 + s)


def rii_sellmeier2(wl, c):
    """formula 2: n² − 1 = C0 + Σ Cᵢ λ² / (λ² − Cᵢ₊₁)."""
    l2 = wl * wl
    if c.shape[0] < 3:
        return _sqrt_n2(1 + (_c(c, 0) + torch.zeros_like(l2)))
    k = c.unbind()  # 0-d views from one op; C0 + (first term) is C0 + 0 + (first term) exactly (issue 43)
    s = k[0] + k[1] * l2 / (l2 - k[2])
    for i in range(3, c.shape[0] - 1, 2):
        s = s + k[i] * l2 / (l2 - k[i + 1])
    return _sqrt_n2(1 + s)


def _power_series(wl, c, start):
    s = torch.zeros_like(wl)
    for i in range(start, c.shape[0] - 1, 2):
        s = s + c[i] * wl ** c[i + 1]
    return s


def rii_polynomial(wl, c):
    """formula 3: n² = C0 + Σ Cᵢ λ^Cᵢ₊₁."""
    return _sqrt_n2(_c(c, 0) + _power_series(wl, c, 1))


def rii_rii(wl, c):
    """formula 4: n² = C0 + C1 λ^C2 / (λ² − C3^C4) + C5 λ^C6 / (λ² − C7^C8) + Σ_{i≥9} Cᵢ λ^Cᵢ₊₁."""
    l2 = wl * wl
    n2 = _c(c, 0) + torch.zeros_like(wl)
    for j in (1, 5):
        if c.shape[0] > j + 3:
            n2 = n2 + c[j] * wl ** c[j + 1] / (l2 - c[j + 2] ** c[j + 3])
    return _sqrt_n2(n2 + _power_series(wl, c, 9))


def rii_cauchy(wl, c):
    """formula 5: n = C0 + Σ Cᵢ λ^Cᵢ₊₁."""
    return _c(c, 0) + _power_series(wl, c, 1)


def rii_gases(wl, c):
    """formula 6: n − 1 = C0 + Σ Cᵢ / (Cᵢ₊₁ − λ⁻²)."""
    s = _c(c, 0) + torch.zeros_like(wl)
    for i in range(1, c.shape[0] - 1, 2):
        s = s + c[i] / (c[i + 1] - 1.0 / (wl * wl))
    return 1 + s


def rii_herzberger(wl, c):
    """formula 7: n = C0 + C1 / (λ² − 0.028) + C2 / (λ² − 0.028)² + C3 λ² + C4 λ⁴ + C5 λ⁶."""
    l2 = wl * wl
    L = 1.0 / (l2 - 0.028)
    return _c(c, 0) + _c(c, 1) * L + _c(c, 2) * L * L + _c(c, 3) * l2 + _c(c, 4) * l2**2 + _c(c, 5) * l2**3


def rii_retro(wl, c):
    """formula 8: (n² − 1) / (n² + 2) = C0 + C1 λ² / (λ² − C2) + C3 λ²."""
    l2 = wl * wl
    a = _c(c, 0) + _c(c, 1) * l2 / (l2 - _c(c, 2)) + _c(c, 3) * l2
    return _sqrt_n2((1 + 2 * a) / (1 - a))


def rii_exotic(wl, c):
    """formula 9: n² = C0 + C1 / (λ² − C2) + C3 (λ − C4) / ((λ − C4)² + C5)."""
    l2 = wl * wl
    d = wl - _c(c, 4)
    return _sqrt_n2(_c(c, 0) + _c(c, 1) / (l2 - _c(c, 2)) + _c(c, 3) * d / (d * d + _c(c, 5)))


RII_FORMULAS = {
    1: rii_sellmeier, 2: rii_sellmeier2, 3: rii_polynomial, 4: rii_rii, 5: rii_cauchy, 6: rii_gases,
    7: rii_herzberger, 8: rii_retro, 9: rii_exotic,
}


def tabulated(wl, table):
    """Refractiveindex.info ``tabulated n`` / ``tabulated nk`` (n column only): linear interpolation of a
    (K, 2) table of rows [λ, n] with λ ascending. Differentiable in λ (piecewise-constant slope) and in the
    table values; outside the table the end values are held (constant extrapolation)."""
    x, y = table[:, 0].contiguous(), table[:, 1].contiguous()
    if x.shape[0] == 1:
        return y[0] + torch.zeros_like(wl)
    idx = torch.clamp(torch.searchsorted(x, wl.detach().contiguous()), 1, x.shape[0] - 1)
    x0, x1, y0, y1 = x[idx - 1], x[idx], y[idx - 1], y[idx]
    t = torch.clamp((wl - x0) / (x1 - x0), 0.0, 1.0)
    return y0 + t * (y1 - y0)
