"""raywave: end-to-end design of hybrid refractive-diffractive lenses with a differentiable ray-wave model.

The public API (one import path per thing; docs/architecture.md)::

    import raywave

    lens = raywave.load_lens("cooke_triplet")            # a file path or a bundled lens's name
    hl = raywave.load_hybrid("hybrid_asphere")           # refractive lens + DOE + sensor
    psf = hl.psf([(0.0, 0.0), (0.0, 10.0)], [0.53], ks=32)  # (F, W, ks, ks)
    ml = raywave.load_midsystem("lens_with_a_doe_inside.zmx")  # a DOE between surfaces: a MidSystemLens

The names are loaded lazily (PEP 562): ``import raywave`` imports neither torch nor matplotlib and changes no
global state; the first use of a name imports its module.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

#: public name -> the module that defines it
_EXPORTS = {
    # lenses
    "Lens": "raywave.lens.lens",
    "load_lens": "raywave.lens.build",
    "save_lens": "raywave.lens.build",
    "ideal_lens": "raywave.lens.build",
    "bundled_lens_path": "raywave.lens.build",
    "get_material": "raywave.materials",
    # DOEs
    "DOE": "raywave.doe",
    "BlankDOE": "raywave.doe",
    "PixelDOE": "raywave.doe",
    "Binary2DOE": "raywave.doe",
    "CubicDOE": "raywave.doe",
    "FresnelDOE": "raywave.doe",
    "GratingDOE": "raywave.doe",
    "RadialDOE": "raywave.doe",
    "SumDOE": "raywave.doe",
    "ZernikeDOE": "raywave.doe",
    "load_doe": "raywave.doe",
    "save_doe": "raywave.doe",
    # the ray-wave engine and hybrids from files
    "HybridLens": "raywave.hybrid.hybrid_lens",
    "PSFResult": "raywave.hybrid.hybrid_lens",
    "psf_metrics": "raywave.hybrid.metrics",
    "load_hybrid": "raywave.assembly.build",
    "hybrid_from_spec": "raywave.assembly.build",
    "tolerance_monte_carlo": "raywave.assembly.tolerance",
    # a DOE inside the lens (issue 46)
    "MidSystemLens": "raywave.hybrid.midsystem",
    "load_midsystem": "raywave.assembly.midsystem",
    "midsystem_from_spec": "raywave.assembly.midsystem",
    # comparison models
    "make_model": "raywave.models.interface",
    "MODEL_NAMES": "raywave.models.interface",
    # imaging
    "psf_map": "raywave.imaging.psfmap",
    "PSFMap": "raywave.imaging.psfmap",
    "field_grid": "raywave.imaging.psfmap",
    "render": "raywave.imaging.render",
    "render_map": "raywave.imaging.render",
    "ColorSpec": "raywave.imaging.color",
    "Sensor": "raywave.imaging.sensor",
    # training
    "Trainer": "raywave.training.trainer",
    "TrainConfig": "raywave.training.config",
    "load_config": "raywave.training.config",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("raywave")
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


__version__ = _version()


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'raywave' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # static analysers and IDEs see the real names
    from raywave.assembly.build import hybrid_from_spec, load_hybrid
    from raywave.assembly.midsystem import load_midsystem, midsystem_from_spec
    from raywave.assembly.tolerance import tolerance_monte_carlo
    from raywave.doe import (DOE, Binary2DOE, BlankDOE, CubicDOE, FresnelDOE, GratingDOE, PixelDOE, RadialDOE, SumDOE,
                             ZernikeDOE, load_doe, save_doe)
    from raywave.hybrid.hybrid_lens import HybridLens, PSFResult
    from raywave.hybrid.metrics import psf_metrics
    from raywave.hybrid.midsystem import MidSystemLens
    from raywave.imaging.color import ColorSpec
    from raywave.imaging.psfmap import PSFMap, field_grid, psf_map
    from raywave.imaging.render import render, render_map
    from raywave.imaging.sensor import Sensor
    from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens, save_lens
    from raywave.lens.lens import Lens
    from raywave.materials import get_material
    from raywave.models.interface import MODEL_NAMES, make_model
    from raywave.training.config import TrainConfig, load_config
    from raywave.training.trainer import Trainer
