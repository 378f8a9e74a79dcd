"""Wavefront (OPD) maps over the pupil and their Zernike fit.

The OPD is :func:`raywave.lens.analysis.wavefront_opd`'s: waves at the exit pupil against the reference sphere
centred on the chief ray's image point (OpticStudio's and optiland's "chief ray" reference), positive where the
wavefront leads. Pupil coordinates are normalised to the stop (fully aimed rays; the rim rule of
:mod:`raywave.rays.pupil`).

Zernike polynomials on the unit disk, ``Z = N·R_n^|m|(ρ)·(cos mθ if m >= 0 else sin |m|θ)``, in two orderings:
``"fringe"`` (University of Arizona / OpticStudio "Fringe", N = 1, terms 1..37) and ``"noll"`` (Noll 1976, N =
sqrt(n+1) for m = 0 else sqrt(2(n+1)): each term has unit RMS over the disk, so a coefficient is that term's RMS in
waves). Coefficients are least-squares fits to the valid samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from raywave.lens.analysis import wavefront_opd
from raywave.rays.pupil import inset_rim


@dataclass
class OPDMap:
    """A wavefront map of one field and wavelength.

    Attributes:
        opd: (N,) waves at the samples (NaN where the ray is vignetted).
        px, py: (N,) normalised pupil coordinates of the samples.
        valid: (N,) bool.
        field: (x, y) in the lens's field type; ``wavelength`` µm.
    """

    opd: torch.Tensor
    px: torch.Tensor
    py: torch.Tensor
    valid: torch.Tensor
    field: tuple
    wavelength: float

    def rms(self) -> float:
        """RMS (waves) about the mean over the valid samples (NaN when none is valid)."""
        v = self.opd[self.valid]
        return float(torch.sqrt(((v - v.mean()) ** 2).mean())) if v.numel() else math.nan

    def peak_to_valley(self) -> float:
        v = self.opd[self.valid]
        return float(v.max() - v.min()) if v.numel() else math.nan


def square_pupil_grid(n: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """An ``n`` × ``n`` grid over [-1, 1]² with the rim on the grid (``linspace(-1, 1, n)``, optiland's and
    OpticStudio's FFT pupil sampling), row-major (row = y), every point (the ones outside the unit disk too):
    ``(px, py)`` each (n²,) float64."""
    if n < 2:
        raise ValueError(f"a pupil grid needs n >= 2 samples across, got {n}")
    c = torch.linspace(-1.0, 1.0, n, dtype=torch.float64, device=device)
    gy, gx = torch.meshgrid(c, c, indexing="ij")
    return gx.reshape(-1), gy.reshape(-1)


def opd_map(lens, field=(0.0, 0.0), wavelength: float | None = None, pupil=("grid", 33)) -> OPDMap:
    """The OPD (waves) of one field (x, y) at ``wavelength`` µm (default primary) over ``pupil``: ``(pattern, n)``
    of :func:`raywave.rays.pupil.sample`, or explicit ``(px, py)`` tensors. Samples outside the unit disk are
    invalid (NaN); so are vignetted rays. No autograd."""
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    if isinstance(pupil[0], str):
        from raywave.rays import pupil as patterns

        px, py = patterns.sample(pupil[0], pupil[1], device=lens.device)
    else:
        px, py = (torch.as_tensor(p, dtype=torch.float64, device=lens.device).reshape(-1) for p in pupil)
    inside = px * px + py * py <= 1.0 + 1e-12
    with torch.no_grad():  # rim samples: the rim rule (raywave.rays.pupil)
        opd, _, _, v = wavefront_opd(lens, [tuple(float(f) for f in field)], [wl],
                                     pupil=inset_rim(px[inside], py[inside]))
    full = torch.full(px.shape, math.nan, dtype=torch.float64, device=px.device)
    ok = torch.zeros(px.shape, dtype=torch.bool, device=px.device)
    vv = v.reshape(-1) & torch.isfinite(opd.reshape(-1))
    full[inside] = torch.where(vv, opd.reshape(-1), torch.full_like(vv, math.nan, dtype=torch.float64))
    ok[inside] = vv
    return OPDMap(full, px, py, ok, tuple(float(f) for f in field), wl)


# ---------------------------------------------------------------------------- Zernike polynomials
def fringe_index(j: int) -> tuple[int, int]:
    """(n, m) of Fringe Zernike term ``j`` (1-based: 1 piston, 2/3 tilt x/y, 4 defocus, 9 spherical, ...)."""
    if j < 1:
        raise ValueError(f"Fringe Zernike terms start at 1, got {j}")
    for d in range(0, 64):  # d = (n + |m|)/2: the terms with the same d occupy j in [d² + 1, (d + 1)²]
        if j <= (d + 1) ** 2:
            k = j - d * d - 1  # 0 .. 2d
            am = d - k // 2
            n = 2 * d - am
            m = am if k % 2 == 0 else -am
            return n, m
    raise ValueError(f"Fringe Zernike term {j} is too high")


def noll_index(j: int) -> tuple[int, int]:
    """(n, m) of Noll Zernike term ``j`` (1-based; for m != 0 the even j of a pair is the cos term, m > 0)."""
    if j < 1:
        raise ValueError(f"Noll Zernike terms start at 1, got {j}")
    k, n = 1, 0
    while True:
        for am in range(n % 2, n + 1, 2):
            pair = [0] if am == 0 else ([am, -am] if k % 2 == 0 else [-am, am])
            for m in pair:
                if k == j:
                    return n, m
                k += 1
        n += 1


def _radial(n: int, am: int, r: torch.Tensor) -> torch.Tensor:
    out = torch.zeros_like(r)
    for k in range((n - am) // 2 + 1):
        c = (-1) ** k * math.factorial(n - k) / (math.factorial(k) * math.factorial((n + am) // 2 - k)
                                                 * math.factorial((n - am) // 2 - k))
        out = out + c * r ** (n - 2 * k)
    return out


def zernike_term(j: int, px: torch.Tensor, py: torch.Tensor, ordering: str = "fringe") -> torch.Tensor:
    """Zernike term ``j`` of ``ordering`` ("fringe" or "noll") at normalised pupil points (…)."""
    if ordering == "fringe":
        n, m = fringe_index(j)
        norm = 1.0
    elif ordering == "noll":
        n, m = noll_index(j)
        norm = math.sqrt(n + 1) if m == 0 else math.sqrt(2 * (n + 1))
    else:
        raise ValueError(f"Zernike ordering must be 'fringe' or 'noll', got {ordering!r}")
    r = torch.sqrt(px * px + py * py)
    t = torch.atan2(py, px)
    ang = torch.cos(m * t) if m >= 0 else torch.sin(-m * t)
    return norm * _radial(n, abs(m), r) * ang


@dataclass
class ZernikeFit:
    """Least-squares Zernike coefficients (waves) ``coefficients`` (J,) for terms 1..J of ``ordering``, and the RMS
    of the fit's residual (waves) over the valid samples."""

    coefficients: torch.Tensor
    ordering: str
    residual_rms: float

    def names(self) -> list[str]:
        idx = fringe_index if self.ordering == "fringe" else noll_index
        return [f"Z{j} (n={idx(j)[0]}, m={idx(j)[1]})" for j in range(1, self.coefficients.numel() + 1)]


def zernike_fit(m: OPDMap, terms: int = 37, ordering: str = "fringe") -> ZernikeFit:
    """Fit Zernike terms 1..``terms`` of ``ordering`` to the valid samples of the OPD map ``m`` (waves)."""
    if terms < 1:
        raise ValueError(f"a Zernike fit needs terms >= 1, got {terms}")
    x, y, z = m.px[m.valid], m.py[m.valid], m.opd[m.valid]
    if x.numel() < terms:
        raise ValueError(f"{x.numel()} valid pupil samples cannot fit {terms} Zernike terms: sample the pupil more "
                         "finely")
    a = torch.stack([zernike_term(j, x, y, ordering) for j in range(1, terms + 1)], -1)
    coef = torch.linalg.lstsq(a, z[:, None], driver="gelsd").solution[:, 0]
    res = z - a @ coef
    return ZernikeFit(coef, ordering, float(torch.sqrt((res * res).mean())))
