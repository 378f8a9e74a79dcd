"""Seeded random *physical* hybrid lenses for property tests (tests/test_random_lenses.py).

A lens is 1–4 singlets of catalog glasses (spherical, some even aspheres with a small conic and a4 term),
air-spaced, with its aperture stop given one of three ways: a circular aperture on one of the lens surfaces,
a flat stop (an air plane with a circular aperture) in front of the first element, or an entrance pupil
diameter (``system_aperture.epd``, stop on the first surface). Every surface clears the beam (edge thickness
and air gaps checked at 1.5× the pupil radius), the sensor sits at the paraxial back focus, and a 256² PixelDOE
(blank or a smooth random phase) sized to hold the beam lies between the last vertex and the sensor.
Lenses whose paraxial back focus is shorter than 3 mm or longer than 150 mm are redrawn.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

GLASSES = ("N-BK7", "N-SF11", "N-LAK9", "F2", "N-SK16", "N-SF5", "N-BAF10", "N-LASF9", "N-K5", "N-SF2",
           "N-LAK22", "N-FK51A")
STOP_MODES = ("surface", "flat", "epd")
DOE_PIXELS = 256


@dataclass
class RandomHybrid:
    """One random hybrid lens and the sources to image with it."""

    seed: int
    hybrid: object  # raywave.hybrid.HybridLens
    spec: dict
    fields: list  # [(θx, θy)] degrees
    wavelength: float  # µm
    stop_mode: str


def _sag(c: float, k: float, a4: float, r: float) -> float:
    arg = 1 - (1 + k) * c * c * r * r
    return c * r * r / (1 + math.sqrt(max(arg, 0.0))) + a4 * r**4


def _surface(rng, semi: float, asphere_prob: float = 0.3, r_min: float = 2.2) -> dict:
    """A random surface dict (radius, maybe even asphere) with |radius| >= ``r_min``×``semi``."""
    c_max = 1.0 / (r_min * semi)
    c = float(rng.uniform(-c_max, c_max))
    if abs(c) < 1e-4:
        c = 0.0
    s = {"type": "standard", "radius": "inf" if c == 0 else 1.0 / c}
    if rng.random() < asphere_prob:
        k = float(rng.uniform(-1.5, 0.5))
        a4 = float(rng.uniform(-1, 1) * 0.02 / semi**4)
        s.update(type="even_asphere", conic=k, aspheric={"a4": a4})
    return s


def _geom(s: dict):
    c = 0.0 if s["radius"] == "inf" else 1.0 / s["radius"]
    return c, s.get("conic", 0.0), s.get("aspheric", {}).get("a4", 0.0)


def random_lens_spec(rng: np.random.Generator, epd_range=(2.0, 8.0), r_min: float = 2.2) -> tuple[dict, str]:
    """A random lens spec (last thickness a placeholder) and its stop mode."""
    n_el = int(rng.integers(1, 5))
    stop_mode = str(rng.choice(STOP_MODES))
    epd = float(rng.uniform(*epd_range))
    semi = 0.75 * epd + 0.5  # clear radius every surface must reach (beam + field growth)
    surfaces: list[dict] = []
    if stop_mode == "flat":
        surfaces.append({"type": "standard", "radius": "inf", "thickness": float(rng.uniform(0.5, 3.0)),
                         "material": "air", "stop": True, "aperture": {"shape": "circle", "radius": 0.5 * epd}})
    for _ in range(n_el):
        front, back = _surface(rng, semi, r_min=r_min), _surface(rng, semi, r_min=r_min)
        # centre thickness: edge thickness ≥ 0.8 mm at the clear radius
        edge = _sag(*_geom(front), semi) - _sag(*_geom(back), semi)
        front.update(thickness=max(float(rng.uniform(1.5, 6.0)), edge + 0.8),
                     material=str(rng.choice(GLASSES)))
        back.update(thickness=float(rng.uniform(0.5, 5.0)), material="air")
        if surfaces and surfaces[-1]["material"] == "air":  # air gap: ≥ 0.3 mm at the clear radius
            prev = surfaces[-1]
            gap = _sag(*_geom(prev), semi) - _sag(*_geom(front), semi)
            prev["thickness"] = max(prev["thickness"], gap + 0.3)
        surfaces += [front, back]
    spec = {"format": "raywave-lens", "version": 1, "object": {"distance": "inf"},
            "fields": {"type": "angle", "values": [0.0]}, "wavelengths": {"values": [0.55], "primary": 0},
            "surfaces": surfaces}
    if stop_mode == "epd":
        spec["system_aperture"] = {"epd": epd}
    elif stop_mode == "surface":
        i = int(rng.integers(0, len(surfaces)))
        surfaces[i]["stop"] = True
        surfaces[i]["aperture"] = {"shape": "circle", "radius": 0.5 * epd}
    return spec, stop_mode


def random_hybrid(seed: int, max_tries: int = 50, sampled: bool = False) -> RandomHybrid:
    """A random physical hybrid lens (see the module docstring), reproducible from ``seed``.

    ``sampled``: a slow, weakly curved lens (EPD 1–2 mm, |R| >= 10× the clear radius) with the DOE at 0.3–0.6 of
    the back focus, so that the 256² DOE grid resolves the wavefront (the model is then smooth in the lens
    parameters, for finite differences); otherwise EPD 2–8 mm, |R| >= 2.2× the clear radius and the DOE
    anywhere in 0.2–0.8 of the back focus (often aliased: the PSFs are wrong, but must stay finite)."""
    from raywave.doe import PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.hybrid.build import beam_half_extent
    from raywave.lens.build import lens_from_spec

    rng = np.random.default_rng(seed)
    for _ in range(max_tries):
        spec, mode = random_lens_spec(rng, (1.0, 2.0) if sampled else (2.0, 8.0), 10.0 if sampled else 2.2)
        wl = float(rng.uniform(0.45, 0.65))
        spec["wavelengths"] = {"values": [wl], "primary": 0}
        try:
            lens = lens_from_spec(spec)
            bfl = float(lens.paraxial(wl).bfl)
        except ValueError:
            continue
        if not (math.isfinite(bfl) and 3.0 <= bfl <= 150.0):
            continue
        spec["surfaces"][-1]["thickness"] = bfl
        lens = lens_from_spec(spec)
        fields = [(0.0, 0.0), (0.0, float(rng.uniform(1.0, 10.0)))]
        distance = float(rng.uniform(*((0.3, 0.6) if sampled else (0.2, 0.8)))) * bfl
        z = float(lens.vertex_z()[-1].detach()) + distance
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ext = beam_half_extent(lens, z, fields=fields, wavelengths=[wl])
        if ext is None or not max(ext) > 0:  # nothing (or a single ray) reaches the DOE plane: no beam to size
            continue
        size = 2.4 * max(ext)
        if rng.random() < 0.5:
            phase = torch.zeros(DOE_PIXELS, DOE_PIXELS, dtype=torch.float64)
        else:  # a smooth random phase: a few low-order terms, up to a few waves across the DOE
            g = torch.linspace(-1, 1, DOE_PIXELS, dtype=torch.float64)
            y, x = torch.meshgrid(g, g, indexing="ij")
            a = rng.normal(size=4) * 6.0
            phase = a[0] * (x * x + y * y) + a[1] * x * y + a[2] * x + a[3] * (x * x - y * y)
        doe = PixelDOE(phase, size / DOE_PIXELS)
        return RandomHybrid(seed, HybridLens(lens, doe, distance), spec, fields, wl, mode)
    raise RuntimeError(f"seed {seed}: no physical lens in {max_tries} draws")


def loss_weights(ks: int, seed: int) -> torch.Tensor:
    """Fixed random weights (ks, ks) for a scalar PSF loss that every PSF pixel feeds."""
    return torch.rand(ks, ks, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
