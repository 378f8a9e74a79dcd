"""Zemax OpticStudio .zmx files (sequential subset) <-> lens specs.

What is read (see docs/lens-format.md, "Zemax .zmx"): system data (NAME, UNIT, the system aperture: ENPD, FNUM
(image-space or paraxial working F/#), OBNA (object NA or cone angle), FLOA; GCAT, FTYP, XFLN/YFLN, WAVM/WAVL,
PWAV) and the surfaces ``SURF n`` of types STANDARD, EVENASPH, ODDASPHE, TOROIDAL and PARAXIAL with
STOP, CURV, DISZ, GLAS (``GLAS MIRROR``: a mirror), DIAM, CONI, PARM, COMM and CLAP / SQAP / FLAP apertures, and
coordinate breaks (``TYPE COORDBRK``: PARM 1..6 = decentre x, decentre y, tilt x, tilt y, tilt z, order flag). Surface 0 is the object
(its DISZ is the object distance), the last surface is the image plane (dropped: the thickness before it
is the distance to the image). A diffractive surface (BINARY_2, DGRATING, ...) as the last surface before the
image becomes the spec's "doe" (the DOE plane of a hybrid lens; BINARY_2 coefficients become its
``phase_model``, and :func:`write_zmx` writes such a DOE back as a BINARY_2 surface); anywhere else it is a DOE
inside the lens (a surface's ``"doe"``), which :func:`write_zmx` writes back as a BINARY_2 / DGRATING surface.
Anything raywave
cannot model (other surface types, decentred
apertures, curved object or image, non-sequential mode) raises
:class:`LensFileError` naming the surface and line; known bookkeeping keys are skipped and unknown keys
give one :class:`LensFileWarning` listing them.

Files are decoded from bytes: UTF-16 (BOM, or NUL bytes: what OpticStudio writes), else UTF-8, else
Latin-1. :func:`write_zmx` writes UTF-16 LE with BOM and CRLF line ends by default, as OpticStudio does.
"""

# Split by concern (issue 17): tables (the .zmx vocabulary), tokens (decoding, lines), surface (one SURF block),
# diffractive (the DOE plane), reader (read_zmx), writer (zmx_text, write_zmx), surface_doe_writer (the diffractive
# surfaces the writer makes of DOEs). Every name stays importable here.
from raywave.io.zmx.reader import read_zmx
from raywave.io.zmx.tables import (DIFFRACTIVE_NAME_PARTS, DIFFRACTIVE_TYPES, IGNORED_SURFACE_KEYS,
                                   IGNORED_SYSTEM_KEYS, KNOWN_UNSUPPORTED_TYPES, MAX_BINARY2_TERMS,
                                   MAX_EVENASPH_PARM, MAX_ODDASPHE_PARM, SURFACE_TYPES, SYSTEM_APERTURE_KEYS,
                                   UNIT_SCALE, UNSUPPORTED_APERTURES, is_diffractive_type)
from raywave.io.zmx.tokens import decode_zmx_bytes
from raywave.io.zmx.writer import write_zmx, zmx_text

__all__ = ["DIFFRACTIVE_NAME_PARTS", "DIFFRACTIVE_TYPES", "IGNORED_SURFACE_KEYS", "IGNORED_SYSTEM_KEYS",
           "KNOWN_UNSUPPORTED_TYPES", "MAX_BINARY2_TERMS", "MAX_EVENASPH_PARM", "MAX_ODDASPHE_PARM", "SURFACE_TYPES",
           "SYSTEM_APERTURE_KEYS", "UNIT_SCALE", "UNSUPPORTED_APERTURES", "decode_zmx_bytes", "is_diffractive_type",
           "read_zmx", "write_zmx", "zmx_text"]
