"""The Fresnel integrals ``C(x) = ∫₀ˣ cos(πt²/2) dt`` and ``S(x) = ∫₀ˣ sin(πt²/2) dt`` in torch (float64, on the
argument's device, elementwise, no host round trip): :func:`fresnel`.

Derivation (the coefficients below come from ``tools/fit_fresnel.py``, which fits them with mpmath at 50 digits and
prints them; nothing is taken from other libraries' tables). Both functions are odd, so everything is evaluated at
``a = |x|`` and the sign of ``x`` put back.

* ``a < X_SPLIT`` (1.6): the power series ``C = Σ (−1)ⁿ (π/2)²ⁿ x⁴ⁿ⁺¹/((2n)!(4n+1))``,
  ``S = Σ (−1)ⁿ (π/2)²ⁿ⁺¹ x⁴ⁿ⁺³/((2n+1)!(4n+3))`` make ``C/x`` and ``S/x³`` entire functions of ``x⁴``. Each is
  replaced by its Chebyshev interpolant in ``s = (x/X_SPLIT)⁴ ∈ [0, 1]`` of degree 11 (an economised power series:
  12 terms instead of the Taylor series' ~17, and smaller alternating terms), written in monomials of ``s``
  (:data:`C_SERIES`, :data:`S_SERIES`; fit error ≤ 5e-18 relative). Multiplying back by ``x`` and ``x³`` keeps the
  *relative* accuracy near 0 (``C ≈ x``, ``S ≈ πx³/6``).
* ``a ≥ X_SPLIT``: the auxiliary functions ``f``, ``g`` with ``C = ½ + f sin(πx²/2) − g cos(πx²/2)``,
  ``S = ½ − f cos(πx²/2) − g sin(πx²/2)`` are smooth and decay like their asymptotic leading terms ``1/(πx)``,
  ``1/(π²x³)``. Scaled by those, ``F = πx·f`` and ``G = π²x³·g`` are functions of ``u = 1/(πx²)²`` → 1 as ``u → 0``,
  with the asymptotic series ``F ~ Σ (−1)ᵐ (4m−1)!! uᵐ``, ``G ~ Σ (−1)ᵐ (4m+1)!! uᵐ``. Those diverge (their terms
  reach 1e-16 only for x ≳ 5), and neither polynomials in ``u`` (a slowly decaying Chebyshev tail at ``u = 0``) nor
  the Padé approximants of the series (still 1e-5 at x = 1.5 for [12/12]) converge fast there; a rational function
  fitted on the whole interval does: ``F ≈ P_F(s)/Q_F(s)``, ``G ≈ P_G(s)/Q_G(s)`` of degrees 9/9 in
  ``s = u/u_s = (X_SPLIT/x)⁴ ∈ (0, 1]`` (linearised least squares at Chebyshev points with Sanathanan–Koerner
  weights, then Lawson reweighting towards minimax; relative error ≤ 4e-17 for F, ≤ 6e-16 for G, i.e. ≤ 2e-17
  absolute in ``f``, ``g``). All their coefficients are positive: no cancellation in the Horner sums for ``s ≥ 0``.
  This one fit covers every ``x ≥ X_SPLIT`` up to infinity (``s → 0``); no separate asymptotic branch is needed.
* The phase ``πx²/2`` of large ``x``: ``x²`` is not exact in float64, and an error ``δ`` of it moves ``C``, ``S`` by
  ``~f·πδ/2`` (1e-14 at x = 100 with ``x²`` rounded). So ``x`` is split exactly into ``x_h + x_l`` (Veltkamp:
  ``x_h`` of 26 bits, ``x_l`` of at most 26), making ``x_h²``, ``2x_h x_l`` and ``x_l²`` exact products; each is
  reduced modulo 4 exactly (``t − 4·round(t/4)``, exact for a float64 ``t``), and only the sum of the three
  reductions (|·| ≤ 6) is rounded: ``x² mod 4`` to ~1e-15 absolute for every ``x``, so ``sin``, ``cos`` of
  ``(π/2)·(x² mod 4)`` stay accurate for huge ``x``. Beyond ``2⁵⁴`` every float64 is a multiple of 4 (``x² ≡ 0``
  mod 4) and ``f``, ``g`` < 2e-17 round away against ½: ``|x|`` is clamped there (also maps ±inf to ±½).

Accuracy (tests/test_fresnel.py): within 2e-15 absolute of mpmath on [−1e4, 1e4] (measured ≤ 6.7e-16), and
relative near 0; against scipy (cephes) likewise on |x| ≤ 23 (the knife-edge factor's range), beyond which cephes'
own rounded phase ``πx²/2`` leaves it up to ~``|x|·2e-16`` off (4e-13 at x ~ 1e4) while this stays at the mpmath
values. NaN gives NaN.

No autograd inside: the outputs carry no graph (callers use ``dC/dx = cos(πx²/2)``, ``dS/dx = sin(πx²/2)``).
"""

from __future__ import annotations

import math

import torch

#: the split (|x|) between the economised power series and the rational fits of the auxiliary functions
X_SPLIT = 1.6

#: ``C(x)/x`` ≈ Σ C_SERIES[k]·sᵏ, ``s = (x/X_SPLIT)⁴``, |x| < X_SPLIT (tools/fit_fresnel.py)
C_SERIES = (1.0, -1.6170359850744802, 1.2105580449193347, -0.4517344432280272, 0.09974917074488943,
            -0.01450828557117232, 0.0014929357545540572, -0.0001143486229858377, 6.770338871211028e-06,
            -3.1888321169065744e-07, 1.2104899020972098e-08, -3.3236645600630444e-10)
#: ``S(x)/x³`` ≈ Σ S_SERIES[k]·sᵏ, ``s = (x/X_SPLIT)⁴``, |x| < X_SPLIT
S_SERIES = (0.5235987755982989, -0.6047700442024193, 0.31116111223603427, -0.08785310908023927,
            0.015576934076967662, -0.0018916236981015514, 0.00016702977487334964, -1.1202012464717747e-05,
            5.898360757734393e-07, -2.5015135885367957e-08, 8.649006092352163e-10, -2.200733620826112e-11)
#: ``πx·f(x)`` ≈ P/Q (numerator, denominator; low order first) in ``s = (X_SPLIT/x)⁴``, |x| ≥ X_SPLIT
F_RATIONAL = (1.0, 43.808597271959854, 672.4152120715237, 4662.92896678826, 15739.77751112895,
              26003.69200237606, 20086.16059112873, 6485.591290657297, 684.3883869385998, 11.666367997091669)
F_RATIONAL_DEN = (1.0, 43.85497842902257, 674.4241592439074, 4693.147304256486, 15942.093595829858,
                  26646.725105122492, 21045.188703269112, 7107.140608022875, 830.8060556907523, 19.649591243186936)
#: ``π²x³·g(x)`` ≈ P/Q in ``s = (X_SPLIT/x)⁴``, |x| ≥ X_SPLIT
G_RATIONAL = (0.9999999999999994, 49.3977119327241, 858.8063713471353, 6771.718837232603, 26055.849998473997,
              49062.869745015756, 42965.78618464309, 15466.110723189115, 1727.4221787037893, 22.847519221381717)
G_RATIONAL_DEN = (1.0, 49.629617718036265, 870.08988958842, 6962.786892735212, 27496.84226586421,
                  54215.747879428214, 51586.87492784535, 21711.415141167803, 3369.7068637532675,
                  123.98628856049586)

#: Veltkamp's splitter for float64: ``2²⁷ + 1``
_SPLITTER = 134217729.0
#: |x| is clamped here: every float64 beyond is a multiple of 4, and ``C``, ``S`` round to ½
_X_HUGE = 2.0 ** 54

#: the series' coefficients as ``(12, 2, 1)`` (term, [C, S], 1) and the rationals' as ``(10, 4, 1)`` (term,
#: [P_F, Q_F, P_G, Q_G], 1): one fused multiply-add per term evaluates a whole group (one float64 CPU tensor, moved
#: to an accelerator once per call without a synchronisation)
_PACKED = torch.tensor([c for k in range(len(C_SERIES)) for c in (C_SERIES[k], S_SERIES[k])]
                       + [c for k in range(len(F_RATIONAL)) for c in (F_RATIONAL[k], F_RATIONAL_DEN[k],
                                                                      G_RATIONAL[k], G_RATIONAL_DEN[k])],
                       dtype=torch.float64)


def _coefficients(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(series (12, 2, 1), rationals (10, 4, 1))`` coefficient tensors on ``device`` (views of :data:`_PACKED` on
    the CPU; elsewhere one non-blocking host-to-device copy: no synchronisation, no host read)."""
    packed = _PACKED if device.type == "cpu" else _PACKED.to(device, non_blocking=True)
    ns = 2 * len(C_SERIES)
    return packed[:ns].view(-1, 2, 1), packed[ns:].view(-1, 4, 1)


def _horner(coef: torch.Tensor, s: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``Σ coef[k]·sᵏ`` for a group of polynomials at once (``coef`` (K, R, 1), ``s`` (n,), ``out`` (R, n):
    returned), one fused multiply-add pass per term."""
    c = coef.unbind(0)  # the terms' views in one op (an index each would dispatch one op a term)
    torch.addcmul(c[-2], s, c[-1], out=out)
    for k in range(len(c) - 3, -1, -1):
        torch.addcmul(c[k], out, s, out=out)
    return out


def _mod4_(t: torch.Tensor, tmp: torch.Tensor) -> torch.Tensor:
    """``t − 4·round(t/4)`` (in ``[−2, 2]``) in place, exact for float64 ``t`` (``tmp``: a scratch buffer)."""
    torch.mul(t, 0.25, out=tmp).round_().mul_(4.0)
    return t.sub_(tmp)


@torch.no_grad()
def fresnel(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Fresnel integrals ``(C(x), S(x))`` (``C = ∫₀ˣ cos(πt²/2) dt``, ``S = ∫₀ˣ sin(πt²/2) dt``; scipy's
    ``fresnel`` returns ``(S, C)``) of a real tensor ``x`` (any shape; integer or floating, evaluated in float64):
    two float64 tensors of ``x``'s shape on its device. Within 2e-15 absolute of the exact values (relative near 0);
    NaN → NaN, ±inf → ±½. No graph (``dC/dx = cos(πx²/2)``, ``dS/dx = sin(πx²/2)``). Method: the module docstring.
    Every step is a whole-array torch operation (both branches evaluated everywhere, finite by clamping, then
    selected; ~70 of them), written in place into a few work arrays: no data-dependent control flow, no host
    read."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"fresnel: x must be a torch.Tensor, got {type(x).__name__}")
    if x.is_complex():
        raise TypeError("fresnel: x must be real, got a complex tensor")
    shape = x.shape
    x = x.detach().to(torch.float64).reshape(-1)
    c_series, c_rational = _coefficients(x.device)
    b0, b1, b2 = (torch.empty_like(x) for _ in range(3))
    series = x.new_empty((2,) + x.shape)
    rational = x.new_empty((4,) + x.shape)
    a = torch.abs(x, out=b0)
    small = a < X_SPLIT
    # |x| < X_SPLIT: C = x·P_C(s), S = x³·P_S(s), s = (x/X_SPLIT)⁴ (clamped: finite everywhere, used only there)
    s = torch.clamp(a, max=X_SPLIT, out=b1).mul_(1.0 / X_SPLIT)
    s.mul_(s)
    s.mul_(s)
    _horner(c_series, s, series).mul_(x)
    series[1].mul_(x).mul_(x)
    # |x| ≥ X_SPLIT: f = F/(πa), g = G/(π²a³), F = P_F/Q_F, G = P_G/Q_G in s = (X_SPLIT/a)⁴
    a.clamp_(X_SPLIT, _X_HUGE)
    s = torch.reciprocal(a, out=b1).mul_(X_SPLIT)
    s.mul_(s)
    s.mul_(s)
    _horner(c_rational, s, rational)
    fg = rational[0::2].div_(rational[1::2])  # (F, G)
    rc = torch.reciprocal(a, out=b2).mul_(1.0 / math.pi)  # 1/(πa)
    fg.mul_(rc)
    f, g = fg.unbind(0)
    g.mul_(rc).mul_(rc).mul_(math.pi)  # G/(π²a³) = G·π·(1/(πa))³
    # the phase πa²/2 from a² mod 4: Veltkamp's split a = hi + lo, hi = γ − (γ − a), γ = a·(2²⁷ + 1)
    gam = torch.mul(a, _SPLITTER, out=b1)
    tmp = rational[1]  # Q_F, free now
    hi = torch.sub(gam, torch.sub(gam, a, out=tmp), out=b1)
    lo = torch.sub(a, hi, out=tmp)
    r = _mod4_(torch.mul(hi, hi, out=b0), b2)  # a is not needed any more
    r.add_(_mod4_(torch.mul(hi, lo, out=b2).mul_(2.0), b1))
    r.add_(_mod4_(torch.mul(lo, lo, out=b2), b1))
    r.mul_(0.5 * math.pi)
    cos_, sin_ = torch.cos(r, out=b1), r.sin_()
    # C = ½ + f sin − g cos, S = ½ − f cos − g sin, with the sign of x
    c_big = torch.mul(f, sin_, out=b2)
    torch.addcmul(c_big, g, cos_, value=-1.0, out=c_big).add_(0.5).copysign_(x)
    s_big = f.mul_(cos_)
    torch.addcmul(s_big, g, sin_, out=s_big).sub_(0.5).neg_().copysign_(x)
    c_out = torch.where(small, series[0], c_big, out=c_big)
    s_out = torch.where(small, series[1], s_big, out=b0)  # sin_ is used up: each output owns its own storage
    return c_out.reshape(shape), s_out.reshape(shape)
