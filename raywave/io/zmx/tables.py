"""The .zmx vocabulary raywave knows: surface types (modelled, known but unsupported, diffractive), lens units,
asphere term limits, and the surface / system keys that are skipped, unsupported or name the system aperture."""

from __future__ import annotations

#: Zemax surface types raywave models, and their spec type.
SURFACE_TYPES = {"STANDARD": "standard", "EVENASPH": "even_asphere", "ODDASPHE": "odd_asphere",
                 "TOROIDAL": "toroidal", "PARAXIAL": "paraxial", "COORDBRK": "coordinate_break"}
#: Extended aspheres, read into the spec type of their base (their XDAT terms on (r / R_norm)^i become mm terms):
#: XASPHERE sag = conic + sum_i A_i rho^(2i) (XDAT 1 = N, 2 = R_norm, 3.. = A_1..A_N); XOSPHERE sag = conic +
#: sum_i B_i rho^i (XDAT 1 = N, 2 = R_norm, 3.. = B_1..B_N); rho = r / R_norm.
EXTENDED_TYPES = {"XASPHERE": "even_asphere", "XOSPHERE": "odd_asphere"}
#: The most extended-asphere terms OpticStudio stores (XDAT 1).
MAX_EXTENDED_TERMS = 240
#: Types raywave cannot trace yet, with what they are (a clearer error than "not supported").
KNOWN_UNSUPPORTED_TYPES = {
    "BICONIC": "biconic", "SZERNSAG": "Zernike standard sag", "FZERNSAG": "Zernike fringe sag",
    "XPOLYNOM": "extended polynomial", "POLYNOMI": "polynomial", "GRID_SAG": "grid sag", "CYLINDER": "cylinder",
    "IRREGULA": "irregular", "USERSURF": "user-defined (DLL)", "GRADIENT": "gradient index",
}
#: Zemax diffractive surface types: as the last surface before the image, such a surface is the DOE plane of
#: a hybrid lens (spec "doe"); anywhere else it is an error. Also any type whose name says diffractive.
DIFFRACTIVE_TYPES = {"BINARY_1", "BINARY_2", "BINARY_3", "BINARY_4", "DGRATING", "RADGRATI", "ELGRATIN", "ELGRAT2",
                     "TOROGRAT", "HOLOGRM1", "HOLOGRM2", "VLSGRATI"}
#: ... and any type whose name contains one of these.
DIFFRACTIVE_NAME_PARTS = ("BINARY", "GRAT", "HOLOG", "DIFFRACT", "PHAS")
#: BINARY_2: PARM 0 = diffraction order, PARM 1..8 = even-asphere substrate terms (must be 0: the DOE is a plane);
#: XDAT 1 = number of terms N, XDAT 2 = normalisation radius, XDAT 3.. = A_i on (r / R_norm)^(2i), radians.
MAX_BINARY2_TERMS = 230


def is_diffractive_type(typ: str) -> bool:
    """A Zemax surface type that adds a diffractive phase (binary optics, gratings, holograms, phase maps)."""
    t = typ.upper()
    return t in DIFFRACTIVE_TYPES or any(part in t for part in DIFFRACTIVE_NAME_PARTS)


#: Lens units -> mm.
UNIT_SCALE = {"MM": 1.0, "CM": 10.0, "IN": 25.4, "INCH": 25.4, "M": 1000.0, "METER": 1000.0, "METERS": 1000.0}
#: EVENASPH: PARM i multiplies r^(2i) (PARM 1 = a2, ..., PARM 8 = a16).
MAX_EVENASPH_PARM = 8
#: ODDASPHE: PARM i multiplies r^i (PARM 1 = b1, ..., PARM 8 = b8).
MAX_ODDASPHE_PARM = 8

#: Surface keys skipped on purpose: they do not change the rays raywave traces.
IGNORED_SURFACE_KEYS = {
    "HIDE": "drawing visibility",
    "MIRR": "mirror substrate drawing (a reflecting surface is GLAS MIRROR)",
    "SLAB": "surface label",
    "POPS": "physical optics settings",
    "MAZH": "mechanical aperture settings",
    "COAT": "coating (raywave traces uncoated surfaces)",
    "PPAR": "extra parameter data",
    "VPAR": "variable flags",
    "VCON": "variable flags",
    "EDGE": "edge drawing",
    "BLNK": "blank line",
    "PZUP": "pickup data",
    "PKUP": "pickup solve (the solved values are in the file)",
    "FLWR": "glass weight data",
    "TCE": "thermal expansion",
    "MEMA": "mechanical semi-diameter",
    "NOTE": "note text",
    "FIMP": "importance flag (tolerancing)",
    "OEMA": "optical edge margin (drawing)",
}
#: Surface apertures raywave has no model for.
UNSUPPORTED_APERTURES = {
    "ELAP": "elliptical aperture",
    "ELOB": "elliptical obscuration",
    "UDAP": "user-defined aperture",
    "USAP": "user-defined aperture",
    "SPID": "spider obscuration",
}
#: System keys skipped on purpose (settings that do not change the prescription raywave reads).
IGNORED_SYSTEM_KEYS = {
    "VERS", "PFIL", "LANG", "ENVD", "GFAC", "RAIM", "PUSH", "SDMA", "ROPD", "PICB", "POLS", "GLRS", "GSTD",
    "NSCD", "COFN", "BLNK", "TOL", "TOLE", "MOFF", "CONF", "DMFS", "ISNA", "VDSZ", "ZVDX", "ZVDY", "ZVCX",
    "ZVCY", "ZVAN", "MNCA", "MNEA", "MNCG", "MNEG", "MXCA", "MXCG", "RGLA", "TRAC", "TCMM", "PMAG", "TOTR",
    "OPDX", "EFFL", "PUPD", "TCED", "FWGN", "FWGT", "VDXN", "VDYN", "VCXN", "VCYN", "VANN", "WWGN", "WWGT",
    "WAVN", "MNUM", "NOTE", "FIMP", "SCOL", "SCTH",
    # display and bookkeeping: database date, layout options, hyperhemispheric drawing, glass substitution
    "DBDT", "OMMA", "HYPR", "OPDX", "SDMA", "FTYP_DISPLAY", "MNUM", "MOFF", "CWGT",
}
#: Merit function operands (OpticStudio writes the merit function editor's rows into the .zmx): optimisation
#: targets, not the prescription; skipped silently.
MERIT_OPERANDS = {
    "ABSO", "ASTI", "AXCL", "BLNK", "COMA", "CTVA", "CVVA", "CTGT", "CTLT", "CVGT", "CVLT", "DIFF", "DIST", "DIVI",
    "EFFL", "EFLX", "EFLY", "ETVA", "ETGT", "ETLT", "FCUR", "FCGS", "FCGT", "INDX", "LACL", "LONA", "MNAB", "MXAB",
    "MNCT", "MXCT", "MNET", "MXET", "OPGT", "OPLT", "OPVA", "PETZ", "POWR", "PROD", "RAID", "RAED", "REAX", "REAY",
    "REAR", "RECI", "RELI", "SPHA", "SUMM", "TTHI", "TOTR", "WFNO", "ISFN", "PMAG", "AMAG", "ENPP", "EXPP", "RSCE",
    "RSCH", "RSRE", "RSRH", "TRAC", "TRAY", "TRAX", "DMFS", "OPTH", "EQUA", "CONS", "ZERN", "SQRT", "DIVB", "OSUM",
    "SUMM", "PARB", "PARR", "RANG", "RAGA", "RAGB", "RAGC", "ANAR", "GCOS", "GTCE", "MNIN", "MXIN", "MNAB", "MNCG",
    "MXCG", "MNEG", "MXEG", "MNCA", "MXCA", "MNEA", "MXEA", "LINV", "WAVE", "PMVA", "FICL", "FICP", "YNIP",
}
#: Multi-configuration operands raywave applies to the chosen configuration: ``OPER surface config value``
#: (YFIE: field number; APER: 0). The others that change the optics are named in a warning.
MULTI_CONFIG_APPLIED = {"THIC": "thickness", "SDIA": "semi-diameter", "YFIE": "y field", "APER": "system aperture"}
#: Multi-configuration operands that do not change the optics (config weight, an unused row, notes).
MULTI_CONFIG_IGNORED = {"MOFF", "CWGT", "TOL", "TOLE", "NOTE"}
#: System aperture keys -> spec "system_aperture" key, by the flag after the value (FNUM v 0 = image-space F/#,
#: FNUM v 1 = paraxial working F/#; OBNA v 0 = object-space NA, OBNA v 1 = object cone angle in degrees).
SYSTEM_APERTURE_KEYS = {
    "ENPD": {0: "epd"},
    "FNUM": {0: "f_number", 1: "working_f_number"},
    "OBNA": {0: "object_na", 1: "object_cone_angle"},
}

