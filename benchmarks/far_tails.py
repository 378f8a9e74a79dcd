"""Issue 46: where the mid-system grating's error against the wave reference comes from: the far tails of a focused
beam, ring by ring, and the grating's orders against references fed the same DOE.

* ``reference``: :func:`wave_truth_doe.airy_reference` (the Rayleigh–Sommerfeld integral of lens A alone, F/12.5,
  0.55 µm, 2 µm pixels, a 128-pixel crop) in its earlier form (600 radii over twice the crop, linear interpolation,
  8×8 midpoint pixel points) against the converged one (cubic spline on 24 radii a µm, Gauss–Legendre pixel points),
  ring by ring (µm from the focus; relative L1 of each ring, both scaled to the same power in their central 32 µm).
* ``lens_a``: lens A alone (``HybridLens``, a blank 1 mm DOE of 1 µm pixels 3 mm or 1 mm before the focus) against the
  converged integral, per edge: the sharp cut on the DOE plane (``doe``; the default ``adaptive`` takes it on this
  sphere), the Fresnel step, the exact construction (``asm``) as it is (its lattice coarsened by
  :func:`~raywave.hybrid.coherent.exit_pupil.asm_coarsening`, 3× here) and with the coarsening held to 2× / 1×;
  and ``cut_sphere_vs_stop``: the integral of the sphere cut sharply on the DOE plane against the stop's (what
  the DOE-plane cut computes, the Fresnel scaling theorem being paraxial), ``doe_cut_vs_cut_sphere``: the engine's
  cut against it.
* ``two_lens_blank``: the two-lens system (lens B perfect for the beam) with a blank DOE: the exact edge against the
  reference (1 µm grid, 800 samples of padding; its own convergence against 0.5 µm), and the sphere cut sharply on
  its exit pupil (the exact edge's model) against the reference, with lens B (f 10 mm) and without it.
* ``gratings``: the binary grating DOE of ``benchmarks/midsystem_cull.py`` (20 / 50 / 100 µm periods, 0°, 32-pixel
  crop on order −1), the default edge (the sharp cut on the final plane) and the exact edge, against the reference
  fed the fabricated pixel map and against the reference fed the traced orders ``Σ c_m e^{i m φ0}`` (the same
  DOE as the engine's); ``series_vs_fabricated``: the reference of the orders |m| ≤ M against the fabricated map's.

Usage: ``python benchmarks/far_tails.py [--out FILE] [--quick]`` (prints JSON; ``--quick``: no gratings).
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.coherent.exit_pupil as XP  # noqa: E402
import raywave.hybrid.midsystem as ms  # noqa: E402
from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.doe.params import GratingDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.lens.lens import Lens  # noqa: E402
from raywave.materials import get_material  # noqa: E402
from raywave.surfaces.aperture import CircularAperture  # noqa: E402
from raywave.surfaces.geometry import Plane  # noqa: E402
from raywave.surfaces.interaction import IdealLens  # noqa: E402
from raywave.surfaces.surface import Surface  # noqa: E402

N, PITCH, PS, KS, WL, KS_TAIL = 1000, 1e-3, 2e-3, 32, 0.55, 128
EXACT = dict(stop_edge="exit_pupil", edge_step="asm")
RINGS = ((0, 10), (10, 30), (30, 60), (60, 90), (90, 126))


def rings(e, ref, ks: int = KS_TAIL, edges=RINGS) -> dict:
    """Relative L1 of ``e`` against ``ref`` ((ks, ks), both scaled to the same power in their central 32 µm) over
    the rings ``edges`` (inner and outer radius, µm) around the centre pixel."""
    h = ks // 2
    core = (slice(h - 8, h + 8), slice(h - 8, h + 8))
    e, ref = e / e[core].sum(), ref / ref[core].sum()
    idx = np.arange(ks) - h
    rr = np.hypot(*np.meshgrid(idx, idx)) * PS * 1e3
    return {f"{lo}-{hi}um": float(np.abs(e[(rr >= lo) & (rr < hi)] - ref[(rr >= lo) & (rr < hi)]).sum()
                                  / ref[(rr >= lo) & (rr < hi)].sum()) for lo, hi in edges}


def old_airy(sys_, ks: int) -> np.ndarray:
    """The earlier form of :func:`wave_truth_doe.airy_reference` (``sub=8, n_rho=300, n_phi=512``)."""
    k, a, f = sys_.k, sys_.radius_a, sys_.f_a
    from scipy.special import roots_legendre
    t, wt = roots_legendre(300)
    rho = 0.5 * a * (t + 1)
    w_rho = 0.5 * a * wt * rho
    phi = (np.arange(512) + 0.5) * 2 * math.pi / 512
    radii = np.linspace(0, PS * ks, 600)
    prof = np.empty(radii.size)
    for i, r in enumerate(radii):
        dx = r - rho[:, None] * np.cos(phi)[None, :]
        dy = -rho[:, None] * np.sin(phi)[None, :]
        big_r = np.sqrt(dx * dx + dy * dy + f * f)
        h = (f / big_r**2) * (1 / big_r - 1j * k) * np.exp(1j * k * (big_r - np.sqrt(rho * rho + f * f)[:, None]))
        prof[i] = abs(np.sum(h * w_rho[:, None]) * (2 * math.pi / 512)) ** 2
    o = ((np.arange(8) + 0.5) / 8 - 0.5) * PS
    c = (np.arange(ks) - ks // 2) * PS
    xx = (c[:, None] + o[None, :]).reshape(-1)
    img = np.interp(np.hypot(xx[None, :], xx[:, None]), radii, prof).reshape(ks, 8, ks, 8).sum((1, 3))
    return img / img.sum()


def _psf(model, field, ks):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = model.psf_result([field], WL, ks=ks)
    return r.psf[0, 0].detach().numpy(), r.center[0, 0].detach().numpy()


def _coarsening(m: int):
    """Context: :data:`exit_pupil.MAX_ASM_COARSENING` held to ``m`` (restored after)."""
    class _C:
        def __enter__(self):
            self.old = XP.MAX_ASM_COARSENING
            XP.MAX_ASM_COARSENING = m

        def __exit__(self, *a):
            XP.MAX_ASM_COARSENING = self.old
    return _C()


def lens_a() -> dict:
    sys_ = W.TwoLensSystem()
    ref = W.airy_reference(sys_, PS, KS_TAIL)
    out = {"reference": {"old_form_vs_converged": rings(old_airy(sys_, KS_TAIL), ref)}}
    a = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                is_stop=True)
    lens = Lens([a], wavelengths=(WL,), primary=0)
    for d in (7.0, 9.0):
        row = {}
        for name, kw, m in (("doe", {"stop_edge": "doe"}, None), ("default", {}, None),
                            ("fresnel", {"stop_edge": "exit_pupil", "edge_step": "fresnel"}, None),
                            ("asm", EXACT, None), ("asm_coarsening_2", EXACT, 2), ("asm_coarsening_1", EXACT, 1)):
            if m is None:
                e, _ = _psf(HybridLens(lens, BlankDOE(N, PITCH), d, sensor_pitch=PS, **kw), (0.0, 0.0), KS_TAIL)
            else:
                with _coarsening(m):
                    e, _ = _psf(HybridLens(lens, BlankDOE(N, PITCH), d, sensor_pitch=PS, **kw), (0.0, 0.0), KS_TAIL)
            row[name] = rings(e, ref)
            if name == "doe":
                cut = W.airy_reference(W.TwoLensSystem(f_a=10.0 - d, radius_a=0.4 * (10.0 - d) / 10.0), PS, KS_TAIL)
                row["cut_sphere_vs_stop"] = rings(cut, ref)
                row["doe_cut_vs_cut_sphere"] = rings(e, cut)
        out[f"doe_plane_{10 - d:g}mm_before_focus"] = row
    return out


def two_lens_blank() -> dict:
    out = {}
    for fb in (10.0, math.inf):
        sys_ = W.TwoLensSystem(f_b=fb)
        c = np.array(sys_.image()[:2])
        ref = W.sensor_psf(sys_, N, PITCH, None, c, PS, KS_TAIL, pad=800)
        row = {}
        if fb == 10.0:
            fine = W.sensor_psf(sys_, 2 * N, PITCH / 2, None, c, PS, KS_TAIL, pad=1600)
            row["reference_1um_vs_0.5um"] = rings(ref, fine)
            ref = fine
            # the exit pupil: A imaged by B (15 mm before B, radius 1 mm), the sphere cut sharply there
            zb = -(sys_.gap1 + sys_.gap2)
            zx = 1.0 / (1.0 / sys_.f_b + 1.0 / zb)
            xp = W.TwoLensSystem(f_a=sys_.image()[2] - zx, radius_a=sys_.radius_a * zx / zb)
            row["exit_pupil_sphere_vs_reference"] = rings(W.airy_reference(xp, PS, KS_TAIL), ref)
        for name, kw, m in (("default", {}, None), ("exact", EXACT, None), ("exact_coarsening_1", EXACT, 1)):
            with _coarsening(XP.MAX_ASM_COARSENING if m is None else m):
                ml = ms.MidSystemLens(M.two_lens(sys_), BlankDOE(N, PITCH), 0, sys_.gap1, final_distance=0.01,
                                      final_size=N * PITCH, final_pitch=PITCH, sensor_pitch=PS, **kw)
                e, _ = _psf(ml, (0.0, 0.0), KS_TAIL)
            row[f"{name}_vs_reference"] = rings(e, ref)
        out["f_b_10mm" if fb == 10.0 else "no_lens_b"] = row
    return out


def gratings() -> dict:
    out = {}
    cs = ms.order_coefficients(2, True, 1.0, range(-61, 62))
    for per in (20.0, 50.0, 100.0):
        doe = GratingDOE(per * 1e-3, N, PITCH)
        doe.fabricate(2)
        sys_ = W.TwoLensSystem()
        phi0 = doe.design_phase_pixels(slice(None), slice(None)).detach().numpy()
        fab = doe.phase(WL).detach().numpy()
        row = {}
        for name, kw in (("default", {}), ("exact", EXACT)):
            ml = ms.MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=N * PITCH,
                                  final_pitch=PITCH, sensor_pitch=PS, **kw)
            e, c = _psf(ml, (0.0, 0.0), KS)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                orders = ml.source_orders((0.0, 0.0), WL)
            traced = sum(cm * np.exp(1j * float(s) * phi0) for s, cm in orders)
            row[f"{name}_vs_fabricated"] = W.rel_l1(e, W.sensor_psf(sys_, N, PITCH, fab, c, PS, KS))
            row[f"{name}_vs_traced_orders"] = W.rel_l1(e, W.sensor_psf(sys_, N, PITCH, traced, c, PS, KS))
            row["orders"] = [float(s) for s, _ in orders]
        ref_fab = W.sensor_psf(sys_, N, PITCH, fab, c, PS, KS)
        row["series_vs_fabricated"] = {
            mm: W.rel_l1(W.sensor_psf(sys_, N, PITCH, sum(cs[m] * np.exp(1j * m * phi0) for m in range(-mm, mm + 1)
                                                          if abs(cs[m]) > 1e-12), c, PS, KS), ref_fab)
            for mm in (1, 3, 5, 9, 31, 61)}
        # where the fabricated map's transitions fall: pixel centres exactly on a level boundary (rounding ties)
        frac = (phi0[N // 2] / math.pi - 0.5) % 1.0
        row["pixel_centres_on_a_level_boundary"] = int(np.sum(np.minimum(frac, 1 - frac) < 1e-9))
        out[f"{per:g}um"] = row
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    out = {"issue": 46, "what": __doc__.split("\n\n")[1:4], "command": "python benchmarks/far_tails.py "
           + " ".join(argv if argv is not None else sys.argv[1:]), "lens_a": lens_a(),
           "two_lens_blank": two_lens_blank()}
    if not a.quick:
        out["gratings"] = gratings()
    emit_json(out, a.out, indent=1)


if __name__ == "__main__":
    main()
