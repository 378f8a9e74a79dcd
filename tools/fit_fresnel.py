"""Generate the fitted coefficients of :mod:`raywave.utils.fresnel` with mpmath (50 significant digits).

Two fits, both against mpmath's Fresnel integrals (``mp.fresnelc``, ``mp.fresnels``, the same convention
``C(x) = ∫₀ˣ cos(πt²/2) dt``):

* ``|x| < X_SPLIT``: ``C(x)/x`` and ``S(x)/x³`` are entire functions of ``w = x⁴`` (the power series
  ``C = Σ (−1)ⁿ (π/2)²ⁿ x⁴ⁿ⁺¹ / ((2n)! (4n+1))``, ``S = Σ (−1)ⁿ (π/2)²ⁿ⁺¹ x⁴ⁿ⁺³ / ((2n+1)! (4n+3))``); each is
  interpolated at Chebyshev points of ``s = w / X_SPLIT⁴ ∈ [0, 1]`` by a polynomial of the smallest degree whose
  Chebyshev tail is below the target, and written in monomials of ``s`` (economised power series: fewer terms
  than the Taylor series, and no large alternating terms).
* ``|x| ≥ X_SPLIT``: the auxiliary functions ``f``, ``g`` (``C = ½ + f sin(πx²/2) − g cos(πx²/2)``,
  ``S = ½ − f cos(πx²/2) − g sin(πx²/2)``) scaled by their asymptotic leading terms, ``F = πx·f`` and
  ``G = π²x³·g``, are smooth functions of ``u = 1/(πx²)²`` on ``[0, u_s]`` (``u_s = 1/(π X_SPLIT²)²``; ``F, G → 1``
  as ``u → 0``; their asymptotic series ``F ~ Σ (−1)ᵐ (4m−1)!! uᵐ``, ``G ~ Σ (−1)ᵐ (4m+1)!! uᵐ`` diverge, so no
  polynomial in ``u`` converges fast at ``u = 0`` and the Padé approximants of those series do not either (checked:
  [12/12] still 1e-5 at x = 1.5)). Each is fitted by a rational function ``P(s)/Q(s)`` of ``s = u/u_s``: linearised
  least squares ``min Σ wᵢ (P(sᵢ) − Fᵢ Q(sᵢ))²`` at Chebyshev points with the weights ``1/Q_prev(sᵢ)²``
  (Sanathanan–Koerner iteration), then Lawson reweighting towards the minimax relative error.

Prints the fits' maximum relative errors (in mpmath, at 800 / 1000 evenly spaced points of ``s``) as comments and
the coefficients as Python literals, those of raywave/utils/fresnel.py (tests/test_fresnel.py, slow, checks that
they are; the float64 evaluation's accuracy is tested there against scipy and mpmath).

    python tools/fit_fresnel.py [M [N]]   (rational degrees, default 9/9: the module's)
"""

import sys

import mpmath as mp

mp.mp.dps = 50
#: the split between the economised power series and the rational fits of f, g (|x|)
X_SPLIT = mp.mpf("1.6")
TARGET = mp.mpf("2e-17")


def fresnel_fg(x):
    """``(f, g)`` of mpmath's Fresnel integrals at ``x``."""
    c, s = mp.fresnelc(x), mp.fresnels(x)
    ph = mp.pi * x * x / 2
    sn, cs, h = mp.sin(ph), mp.cos(ph), mp.mpf(1) / 2
    return (c - h) * sn - (s - h) * cs, -(c - h) * cs - (s - h) * sn


def cheb_points(n, lo=0, hi=1):
    return [lo + (hi - lo) * (1 - mp.cos(mp.pi * (k + mp.mpf(1) / 2) / n)) / 2 for k in range(n)]


def poly_fit(fun, deg):
    """Monomial coefficients (low first) in ``s ∈ [0, 1]`` of the Chebyshev interpolant of degree ``deg``."""
    pts = cheb_points(deg + 1)
    vals = [fun(s) for s in pts]
    a = mp.matrix([[s ** j for j in range(deg + 1)] for s in pts])
    return list(mp.lu_solve(a, mp.matrix(vals)))


def rational_fit(fun, m, n, npts=300, iters=12):
    """``(p, q)`` monomial coefficients (low first, ``q[0] = 1``) of ``P/Q`` ≈ ``fun`` on ``s ∈ [0, 1]``."""
    pts = cheb_points(npts)
    vals = [fun(s) for s in pts]
    w = [mp.mpf(1)] * npts
    lw = [mp.mpf(1)] * npts
    p = q = None
    for it in range(iters):
        rows, rhs = [], []
        for s, v, wi, li in zip(pts, vals, w, lw):
            sc = mp.sqrt(li) * wi / v
            rows.append([sc * s ** j for j in range(m + 1)] + [-sc * v * s ** j for j in range(1, n + 1)])
            rhs.append(sc * v)
        sol, _ = mp.qr_solve(mp.matrix(rows), mp.matrix(rhs))
        p, q = list(sol[:m + 1]), [mp.mpf(1)] + list(sol[m + 1:])
        qv = [mp.polyval(q[::-1], s) for s in pts]
        w = [1 / abs(x) for x in qv]
        err = [abs(mp.polyval(p[::-1], s) / x / v - 1) for s, x, v in zip(pts, qv, vals)]
        if it >= iters // 2:  # Lawson: weight up where the error is largest
            lw = [li * e for li, e in zip(lw, err)]
            tot = mp.fsum(lw)
            lw = [li / tot * npts for li in lw]
    return p, q


def max_rel_err(fun, approx, lo, hi, n=4000):
    return max(abs(approx(s) / fun(s) - 1) for s in (lo + (hi - lo) * mp.mpf(k) / n for k in range(n + 1)))


def main():
    ws = X_SPLIT ** 4
    us = 1 / (mp.pi * X_SPLIT ** 2) ** 2

    def c_over_x(s):
        x = mp.root(s * ws, 4)
        return mp.fresnelc(x) / x if x else mp.mpf(1)

    def s_over_x3(s):
        x = mp.root(s * ws, 4)
        return mp.fresnels(x) / x ** 3 if x else mp.pi / 6

    def big_f(s):
        if s == 0:
            return mp.mpf(1)
        x = 1 / mp.sqrt(mp.pi * mp.sqrt(s * us))
        return mp.pi * x * fresnel_fg(x)[0]

    def big_g(s):
        if s == 0:
            return mp.mpf(1)
        x = 1 / mp.sqrt(mp.pi * mp.sqrt(s * us))
        return mp.pi ** 2 * x ** 3 * fresnel_fg(x)[1]

    out = {}
    for name, fun in (("C_SERIES", c_over_x), ("S_SERIES", s_over_x3)):
        for deg in range(6, 30):
            c = poly_fit(fun, deg)
            e = max_rel_err(fun, lambda s: mp.polyval(c[::-1], s), 0, 1, 800)
            if e < TARGET:
                break
        out[name] = (c,)
        print(f"# {name}: degree {deg}, max rel err {float(e):.1e}")
    m = int(sys.argv[1]) if len(sys.argv) > 1 else 9
    n = int(sys.argv[2]) if len(sys.argv) > 2 else m
    for name, fun in (("F_RATIONAL", big_f), ("G_RATIONAL", big_g)):
        p, q = rational_fit(fun, m, n)
        e = max_rel_err(fun, lambda s: mp.polyval(p[::-1], s) / mp.polyval(q[::-1], s), 0, 1, 1000)
        out[name] = (p, q)
        print(f"# {name}: degrees {m}/{n}, max rel err {float(e):.1e}")
    print(f"X_SPLIT = {float(X_SPLIT)!r}")
    for name, cs in out.items():
        for tag, c in zip(("", "_DEN") if len(cs) == 2 else ("",), cs):
            print(f"{name}{tag} = (" + ", ".join(repr(float(v)) for v in c) + ")")


if __name__ == "__main__":
    main()
