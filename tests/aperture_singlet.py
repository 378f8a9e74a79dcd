"""A 100 mm N-BK7 singlet (stop on its front surface, 10 mm entrance pupil) as .zmx and CODE V .seq text, with a
slot for aperture lines on a flat dummy surface 10 mm in front of it; and the square grids of parallel rays that the
aperture tests trace through it. Shared by test_apertures_files, test_obscuration and test_codev_apertures."""

from __future__ import annotations

import numpy as np
import torch

from raywave.rays.bundle import RayBundle

#: the stop's clear radius (mm): ENPD 10 at the stop surface
R_STOP = 5.0

_ZMX_SURFACES = """SURF 1
  TYPE STANDARD
  CURV 0.0
  DISZ 10
{ap}
SURF 2
  STOP
  TYPE STANDARD
  CURV 9.765625E-3
  DISZ 3.6
  GLAS N-BK7 0 0 1.5168 64.17
  DIAM 12.7 1 0 0 1 ""
SURF 3
  TYPE STANDARD
  CURV -9.765625E-3
  DISZ 98.47
  DIAM 12.7 1 0 0 1 ""
SURF 4
  TYPE STANDARD
  CURV 0.0
  DISZ 0
"""

_SEQ = """RDM
TITLE '{title}'
EPD 10.0
DIM M
WL 587.5618
REF 1
XAN 0.0
YAN 0.0
SO 0.0 1e13
S 0.0 10.0
{ap}
STO 102.4 3.6 {glass}
  CIR 12.7
S -102.4 {last}
  CIR 12.7
SI 0.0 {defocus}
GO
"""


def zmx_head(name: str, enpd: float, wavelength: float, gcat: str = "") -> str:
    """The system lines and the object surface (at infinity) of a .zmx with one on-axis field and one wavelength
    (µm); ``enpd`` the entrance pupil diameter (mm), ``gcat`` an optional ``GCAT`` line."""
    return (f"VERS 190513 80 123457\nMODE SEQ\nNAME {name}\nUNIT MM X W X CM MR CPMM\nENPD {enpd:g}\n{gcat}"
            f"FTYP 0 0 1 1 0 0 0\nXFLN 0\nYFLN 0\nWAVM 1 {wavelength} 1\nPWAV 1\n"
            "SURF 0\n  TYPE STANDARD\n  CURV 0.0\n  DISZ INFINITY\n")


def singlet_zmx(ap: str = "", name: str = "APERTURE SINGLET") -> str:
    """The singlet as .zmx text; ``ap``: the dummy surface's aperture lines (e.g. ``"  OBSC 0 2.0"``)."""
    return zmx_head(name, 10, 0.5875618, gcat="GCAT SCHOTT\n") + _ZMX_SURFACES.format(ap=ap)


def singlet_seq(ap: str = "", glass: str = "NBK7_SCHOTT", last: str = "98.47", defocus: str = "0.0",
                title: str = "APERTURE SINGLET") -> str:
    """The singlet as CODE V .seq text; ``ap``: the dummy surface's aperture lines, ``glass`` the lens's glass,
    ``last`` the back focal distance (mm), ``defocus`` the image surface's thickness (mm)."""
    return _SEQ.format(title=title, ap=ap, glass=glass, last=last, defocus=defocus)


def grid(step: float = 0.1, half: float = 6.0):
    """(x, y) of the cell centres of a square grid of side 2·half (mm), pitch ``step``: never on a shape's edge."""
    c = np.arange(-half + step / 2, half, step)
    yy, xx = np.meshgrid(c, c, indexing="ij")
    return xx.ravel(), yy.ravel()


def parallel_rays(x, y) -> RayBundle:
    """Rays along +z from (x, y, -1) mm at 0.5875618 µm; x, y: arrays of shape (N,)."""
    xt, yt = torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(y, dtype=torch.float64)
    o = torch.stack([xt, yt, torch.full_like(xt, -1.0)], -1)
    return RayBundle.create(o, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 0.5875618)
