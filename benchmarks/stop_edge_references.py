"""Issue 47: the default stop edge (exit pupil, ``edge_step="adaptive"``) and the other edges against *converged*
references, with each reference's own convergence beside every figure. One JSON line per case (and the list with
``-o``).

References:

- ``real:NAME:FRAC`` (the lenses of tests/test_stop_edge_real_lenses.py through ``raywave psf``'s defaults, their
  blank DOE, at FRAC of the lens's largest field; sensor pitch as the slow test's SETTINGS) and ``asphere:DEG`` (the
  bundled hybrid_asphere's lens, a 6 mm blank DOE of 1 µm pixels at 0.7 mm, 3 µm sensor pixels, λ 0.53 µm): the
  Huygens exit-pupil PSF, :func:`raywave.models.exit_pupil.huygens_psf` with ``n_pupil="auto"`` (since 2026-11-29
  the polar pupil quadrature: levels ×1.25 up to ``--max-n`` until two agree to ``tol``; ``ref_error`` the last
  change, an upper bound for the finer level's error, ~1e-10 once the wavefront is resolved; ``ref_levels`` each
  level's change).
- ``file:PATH:FRAC[:PITCH_UM]`` (issue 47, h47c: any lens file, e.g. of the OpticExplorer database in
  ../shared/data/opticsdatabase, through ``raywave psf``'s defaults and its blank DOE, as ``real:``; ``FRAC`` a
  fraction of the file's largest field, in its own field type (an angle, or since h47v an object height for a
  finite object) or ``NNdeg`` an angle, for files with only an on-axis field such as a catalogue achromat;
  ``PITCH_UM`` the sensor pitch, default the DOE pitch): the same Huygens reference. Each row
  also names the step the default took (``step``: "doe cut", "fresnel" or "caustic fallback", :func:`default_step`)
  and the lens's F-number. ``--tol`` sets the reference's level agreement (1e-6: ~1e-10 once resolved).
- ``two_lens:DEG`` (tests/test_ideal_lens_truth.py's two ideal lenses, a blank DOE 5 mm behind lens B) and
  ``single:CASE`` (one ideal lens, a DOE 1 mm behind it: binary, 16level, fresnel200 (a Fresnel DOE, object at
  200 mm), blank): the independent wave-optics truths of tests/wave_truth.py (no rays, no exit pupil: the stop's
  edge diffracts from the stop itself); ``ref_error``: the two-lens truth's change from 2 to 1 µm sampling.

``--sphere rim_images`` (issue 47, h47: the double Gauss at full field): the Huygens reference with the stop's edge
where it is sharp, at each rim point's own image (:func:`raywave.hybrid.coherent.stop_rim_images`), instead of on
the sphere through the paraxial exit pupil: the sum runs over a surface that meets each rim ray at its rim image's
distance ``rho(theta)`` from the sphere's centre and blends smoothly into the paraxial sphere inside (``rho``'s
azimuthal harmonics ``m`` weighted by ``r^|m|``, the mean by ``r²``), with each node's amplitude from its ray
tube's cross-section normal to the ray (:func:`_edge_at_rim_images`). Inside the stop the surface does not matter
(geometric optics: a surface through 139.2 mm at the rim only agrees with the 139.2 mm sphere to 3e-7); only where
the edge sits does. Cached as ``ref_CASE_ksK_rim_images.pt``.

Variants: ``default`` (the engine's default), ``fresnel`` / ``asm`` (``edge_step``), ``doe`` (``stop_edge="doe"``,
the paper's edge), and ``*_iu8`` (the same with ``intensity_upsample=8``: the sensor pixels' quadrature, which at
4 leaves ~1e-3 on a PSF as sharp as the DOE grid allows, e.g. the F/1.3 asphere at its 0.56 µm Nyquist pitch).
``--cache DIR`` keeps the references (torch files) so that a sweep can be resumed.

``--pick ROOT [--seed S]`` (h47v) runs nothing: it prints a seeded pick of lens files from a database folder (e.g.
the OpticExplorer database extracted from ../shared/data/opticsdatabase/optics.tar.gz), one per kind of
:data:`KINDS` (:func:`pick_lens_files`): each kind's candidates in a ``random.Random(S)`` order, the first that
loads, has a finite focal length, its kind's F-number and focal ranges (camera lenses F > 2: faster ones off axis
are refused for memory) and is not among the lenses already tested (:data:`TESTED`); the files passed over are
listed with their reasons. ``--doe-distance MM`` (h47v): a file case's blank DOE on that plane instead of the
default rule's (a plane scan at a fixed ``PITCH_UM``; the cached reference is reused).

    PYTHONPATH=. python benchmarks/stop_edge_references.py real:double_gauss:0 asphere:0 two_lens:0 single:blank \
        [--variants default doe] [--max-n 432] [--cache DIR] [-o F]
    PYTHONPATH=. python benchmarks/stop_edge_references.py "file:/tmp/db/Optics/.../Lens.zmx:0.7:3" \
        --variants default doe --sphere rim_images --max-n 1024 --tol 1e-6 --cache DIR
    PYTHONPATH=. python benchmarks/stop_edge_references.py --pick /tmp/db/Optics --seed 47
"""

import argparse
import json
import math
import os
import random
import re
import sys
import time
import warnings
from pathlib import Path

import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

from raywave.lens.sources import entrance_plane_z, point_source_rays, source_weight
from raywave.utils.errors import MEMORY_LIMIT_ENV

ROOT = Path(__file__).resolve().parents[1]
LENSES = {
    "cooke_triplet": "cooke_triplet",
    "double_gauss": str(ROOT / "tests/data/zmx/double_gauss_ohara_cdgm_hoya.zmx"),
    "singlet_nbk7_50": str(ROOT / "tests/data/real_lenses/singlet_nbk7_50.zmx"),
    "asphere_f13": str(ROOT / "tests/data/real_lenses/asphere_f13_nsf11.zmx"),
}
#: sensor pitch (mm) of the slow test where its default (the DOE pitch) leaves most of the PSF outside the crop
PITCH = {("asphere_f13", 0.7): 3e-3, ("asphere_f13", 1.0): 3e-3, ("double_gauss", 0.7): 3e-3,
         ("double_gauss", 1.0): 3e-3, ("singlet_nbk7_50", 1.0): 3e-3}
VARIANTS = {"default": {}, "fresnel": {"edge_step": "fresnel"}, "asm": {"edge_step": "asm"},
            "doe": {"stop_edge": "doe"}, "default_iu8": {"intensity_upsample": 8},
            "doe_iu8": {"stop_edge": "doe", "intensity_upsample": 8}}
#: lens kinds of ``--pick``: (path regex relative to the database root, F-number range (lo, hi], focal range mm or
#: None); a zoom is named by a focal range ("24-70mm"), a prime by its absence
_ZOOM = r"\d+(?:\.\d+)?\s*-\s*\d+(?:\.\d+)?\s*mm"
KINDS = {
    "slow camera prime (F/4 - F/8)": (rf"^Photography/(?!.*{_ZOOM})", (4.0, 8.0), (35.0, 150.0)),
    "wide-angle prime (f <= 28 mm)": (rf"^Photography/(?!.*{_ZOOM})(?!.*(?i:fisheye))", (2.0, 11.0), (0.0, 28.0)),
    "long telephoto (f >= 200 mm)": (rf"^Photography/(?!.*{_ZOOM})", (2.0, 11.0), (200.0, 2000.0)),
    "zoom": (rf"^Photography/.*{_ZOOM}", (2.0, 11.0), None),
    "triplet / Heliar / Tessar variant": (r"(?i)(heliar|triplet|tessar|cooke|taylor)(?!.*\d-\d)", (2.0, 16.0), None),
    "eyepiece": (r"^Astronomy/Eyepieces/", (0.0, 100.0), None),
    "telescope objective": (r"^Astronomy/Objectives/", (2.0, 30.0), None),
    "catalogue doublet": (r"^(Achromats/|Components/.*Doublet)", (2.0, 30.0), None),
    "microscope objective": (r"^Microscopy/", (0.0, 100.0), None),
    "telecentric": (r"^Illumination/Telecentric", (0.0, 100.0), None),
}
#: lens files already compared with the converged reference (tests/test_stop_edge_{other,real}_lenses.py)
TESTED = ("Zeiss Tessar f2.8 50mm", "Zeiss Planar 2.880", "Tele-Dynar 100mm f6.3", "Telescope Fraunhofer",
          "cooke_triplet", "double_gauss", "singlet_nbk7_50", "asphere_f13")
SINGLE = {"binary": "binary", "16level": "16-level at 0.45 µm", "fresnel200": "Fresnel, object at 200 mm",
          "blank": "blank"}


def pick_lens_files(root: Path, seed: int) -> dict:
    """One lens file per kind of :data:`KINDS` under ``root`` (``.zmx`` / ``.seq``), in a ``random.Random(seed)``
    order of each kind's candidates (sorted paths): the first that loads, has a positive finite focal length, an
    F-number and a focal length in the kind's ranges, and is not in :data:`TESTED` or picked for an earlier kind.
    Returns ``{"seed", "root", "kinds": {kind: {"file", "f_number", "efl", "fields", "field_type", "candidates",
    "passed_over": [[file, reason], ...]}}}``."""
    from raywave.lens.build import load_lens

    files = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.suffix.lower() in (".zmx", ".seq"))
    rng, out, taken = random.Random(seed), {}, set()
    for kind, (pattern, (f_lo, f_hi), efl_range) in KINDS.items():
        cands = [f for f in files if re.search(pattern, f) and f not in taken and not any(t in f for t in TESTED)]
        rng.shuffle(cands)
        row = {"file": None, "candidates": len(cands), "passed_over": []}
        for rel in cands:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    lens = load_lens(root / rel)
                    par = lens.paraxial()
                    efl, fno = float(par.efl), float(par.efl) / float(par.epd)
            except Exception as err:  # a refusal is a reason to pass over
                row["passed_over"].append([rel, f"refused: {type(err).__name__}: {str(err)[:80]}"])
                continue
            reason = ("afocal or virtual image" if not (math.isfinite(efl) and efl > 0) else
                      f"F/{fno:.2f} outside ({f_lo:g}, {f_hi:g}]" if not f_lo < fno <= f_hi else
                      f"f {efl:.1f} mm outside {efl_range}" if efl_range and not efl_range[0] <= efl <= efl_range[1]
                      else None)
            if reason is not None:
                row["passed_over"].append([rel, reason])
                continue
            taken.add(rel)
            row.update(file=rel, f_number=round(fno, 3), efl=round(efl, 3),
                       fields=[round(float(f), 4) for f in lens.fields], field_type=lens.field_type)
            break
        out[kind] = row
    return {"seed": seed, "root": str(root), "kinds": out}


def l1(a, b) -> float:
    return float((torch.as_tensor(a) - torch.as_tensor(b)).abs().sum())


def _file_case(rest: list) -> tuple:
    """``(path, frac, sensor pitch mm or None)`` of a ``file:PATH:FRAC[:PITCH_UM]`` case's parts after "file"."""
    if len(rest) < 2:
        raise ValueError(f"a file case is file:PATH:FRAC[:PITCH_UM], got file:{':'.join(rest)}")
    if len(rest) >= 3 and _is_number(rest[-1]) and (rest[-2].endswith("deg") or _is_number(rest[-2])):
        return ":".join(rest[:-2]), rest[-2], float(rest[-1]) * 1e-3
    return ":".join(rest[:-1]), rest[-1], None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _field_value(frac: str, lens) -> tuple:
    """``(field value, field type)`` of a case's ``FRAC``: a fraction of the lens's largest field in the file's own
    field type (degrees, or mm of object height for a finite object), or ``"2deg"``: an angle (for a lens file with
    only an on-axis field, e.g. a catalogue achromat)."""
    if frac.endswith("deg"):
        return float(frac[:-3]), "angle"
    return float(frac) * max(abs(float(f)) for f in lens.fields), lens.field_type


def _case_tag(case: str) -> str:
    """A file-name-safe tag of a case (a ``file:`` case by its lens file's stem)."""
    kind, *rest = case.split(":")
    if kind == "file":
        path, frac, pitch = _file_case(rest)
        tail = "" if pitch is None else f"_{pitch * 1e3:g}um"
        return "file_" + "".join(c if c.isalnum() or c in ".-" else "_" for c in Path(path).stem) + f"_{frac}{tail}"
    return case.replace(":", "_")


def default_step(hl, fld, wl, depth, caught) -> str:
    """The step the default (``edge_step="adaptive"``) took for the source: "doe cut" (a blank DOE on a spherical
    wave: the edge cut on the DOE plane, exact there), "fresnel" (the knife-edge step from the rim images) or
    "caustic fallback" (the DOE plane too near the rays' focus: the Fresnel step to an earlier plane, the angular
    spectrum beyond; named by its StopEdgeWarning in ``caught``; "caustic fallback (scaled carry)": the same with the
    envelope relative to the converging sphere, issue 47 class B)."""
    from raywave.hybrid.coherent.exit_pupil import adaptive_edge_step

    if hl.stop_edge != "exit_pupil":
        return f"{hl.stop_edge} edge"
    if hl.edge_step != "adaptive":
        return hl.edge_step
    step = adaptive_edge_step(hl.lens, hl.doe, fld, wl, depth, float(hl.doe_z()), float(hl.sensor_z()), "angle")
    if step == "fresnel" and any("carried to it by the scaled angular spectrum" in w for w in caught):
        return "caustic fallback (scaled carry)"
    if step == "fresnel" and any("carried to it by the angular spectrum" in w for w in caught):
        return "caustic fallback"
    return step if step == "fresnel" else "doe cut"


def _hybrid(case: str, kw: dict):
    """``(HybridLens, field (2,), wavelength µm, depth)`` of a case with the variant's keywords ``kw``."""
    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens

    kw = dict(kw)
    iu = kw.pop("intensity_upsample", 4)
    kind, *rest = case.split(":")
    if kind == "asphere":
        from raywave.lens.build import bundled_lens_path, load_lens

        lens = load_lens(bundled_lens_path("asphere_hk51"))
        hl = HybridLens(lens, BlankDOE(6000, 1e-3), 0.7, sensor_pitch=3e-3, intensity_upsample=iu, **kw)
        return hl, (0.0, float(rest[0])), 0.53, None
    if kind in ("real", "file"):
        from raywave.assembly.build import load_hybrid
        from raywave.lens.build import load_lens, resolve_lens_path

        if kind == "real":
            path, frac, pitch = LENSES[rest[0]], rest[1], PITCH.get((rest[0], float(rest[1])))
        else:
            path, frac, pitch = _file_case(rest)
        lens = load_lens(resolve_lens_path(path))
        value, field_type = _field_value(frac, lens)
        fld = (0.0, value)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hl = load_hybrid(path, sensor_pitch=pitch, fields=[list(fld), [0.0, 0.0]], field_type=field_type, **kw)
        hl.intensity_upsample = iu
        return hl, fld, hl.lens.primary_wavelength, None
    sys.path.insert(0, str(ROOT / "tests"))
    import test_ideal_lens_truth as t

    if kind == "two_lens":
        th = float(rest[0])
        hl = HybridLens(t.two_lens_engine_lens(th), BlankDOE(2000, 1e-3), 5.0, sensor_pitch=t.PIXEL,
                        intensity_upsample=iu, **kw)
        return hl, (0.0, th), t.WL, None
    doe, wl, depth, sensor = t._doe(SINGLE[rest[0]])
    hl = HybridLens(t._single_lens(depth, sensor, wl), doe, t.DOE_DIST, sensor_pitch=t.PIXEL, intensity_upsample=iu,
                    **kw)
    return hl, (0.0, 0.0), wl, depth


def engine_psfs(case: str, ks: int, variants, doe_distance: float | None = None):
    """``({variant: (psf (ks, ks), seconds, warnings, step, DOE plane) or an error string}, (hybrid, field, λ,
    depth, centre))``; the DOE plane: ``{"doe_distance": mm after the last vertex, "distance_rule": the rule that
    placed a default blank DOE (raywave.assembly.build)}``; ``doe_distance``: a file case's DOE plane (mm after the
    last vertex) instead of the default rule's."""
    out, geo = {}, None
    for v in variants:
        try:
            extra = {} if doe_distance is None else {"doe_distance": doe_distance}
            hl, fld, wl, depth = _hybrid(case, {**VARIANTS[v], **extra})
        except ValueError as e:  # a refusal on load (e.g. a MemoryLimitError of the default DOE's grid)
            out[v] = f"{type(e).__name__}: {str(e)[:200]}"
            continue
        t = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                with torch.no_grad():
                    r = hl.psf_result(fld, wl, ks=ks, depth=depth)
            except ValueError as e:
                out[v] = str(e)[:200]
                continue
        dt = time.perf_counter() - t
        out[v] = (r.psf[0, 0].detach(), dt,
                  sorted({f"{w.category.__name__}: {str(w.message)[:100]}" for w in caught
                          if w.category.__name__ != "SensorCropWarning"}),
                  default_step(hl, fld, wl, depth, [str(w.message) for w in caught]),
                  dict(doe_distance=hl.doe_distance,
                       distance_rule=(getattr(hl, "doe_info", None) or {}).get("distance_rule")))
        geo = (hl, fld, wl, depth, tuple(float(c) for c in r.center[0, 0]))
    return out, geo


def _rim_surface(rim, sph):
    """:func:`raywave.models.exit_pupil._rim_surface` (moved there in h47b)."""
    from raywave.models import exit_pupil as mx

    return mx._rim_surface(rim, sph)


def _rim_polar_samples(lens, field, wl, depth, n_pupil, z_s, n_img, sph, crop, check=True):
    """:func:`raywave.models.exit_pupil._rim_image_samples` (``huygens_psf(sphere="rim_images")``; moved there in
    h47b)."""
    from raywave.models import exit_pupil as mx

    return mx._rim_image_samples(lens, field, wl, depth, n_pupil, z_s, n_img, sph, crop, check)


def _edge_at_rim_images(fn):
    """Run ``fn()`` with the Huygens reference's polar nodes on the rim images' surface (:func:`_rim_polar_samples`)."""
    from raywave.models import exit_pupil as mx

    orig = mx._polar_samples
    mx._polar_samples = _rim_polar_samples
    try:
        return fn()
    finally:
        mx._polar_samples = orig


def _edge_on_sphere(fn, radius: float):
    """Run ``fn()`` (a ``huygens_psf(sphere="rim")`` call) with the reference sphere's radius set to ``radius`` mm
    (about the same centre): where the Huygens reference's edge sits, moved along the rim rays."""
    from raywave.models import exit_pupil as mx

    orig = mx._rim_radius
    mx._rim_radius = lambda *a, **k: float(radius)
    try:
        return fn()
    finally:
        mx._rim_radius = orig


def _sphere_kind(sphere: str):
    """``sphere`` of :func:`reference`: "paraxial", "rim_images" or a radius in mm (a number)."""
    if sphere in ("paraxial", "rim_images"):
        return sphere
    try:
        return float(sphere)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sphere: 'paraxial', 'rim_images' or a radius in mm, got {sphere!r}")


def reference(case: str, geo, ks: int, max_n: int, cache: Path | None, sphere: str = "paraxial",
              tol: float | None = None):
    """``(reference psf, row)``: the converged reference of the case and its convergence (cached in ``cache``);
    ``sphere``: where the Huygens reference's edge sits ("paraxial": the sphere through the paraxial exit pupil;
    "rim_images": at each rim point's image, :func:`_edge_at_rim_images`; a number: on the sphere of that radius in
    mm about the chief ray's sensor intercept, :func:`_edge_on_sphere`); ``tol``: the Huygens levels' agreement that
    ends the refinement (None: huygens_psf's own AUTO_TOL)."""
    tail = "" if sphere == "paraxial" else f"_{sphere}" if isinstance(sphere, str) else f"_R{sphere:g}"
    tail += "" if tol is None else f"_tol{tol:g}"
    fn = None if cache is None else cache / f"ref_{_case_tag(case)}_ks{ks}{tail}.pt"
    if fn is not None and fn.exists():
        d = torch.load(fn, weights_only=False)
        return d["psf"], d["row"]
    hl, fld, wl, depth, center = geo
    kind, *rest = case.split(":")
    t = time.perf_counter()
    if kind in ("real", "file", "asphere"):
        from raywave.models.exit_pupil import huygens_psf

        def run():
            extra = {} if tol is None else {"tol": tol}
            return huygens_psf(hl.lens, fld, wl, ks=ks, pitch=hl.sensor_pitch, center=center, n_pupil="auto",
                               sensor_z=float(hl.sensor_z()), max_n_pupil=max_n,
                               sphere="paraxial" if sphere in ("paraxial", "rim_images") else "rim", **extra)

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if sphere == "paraxial":
                r = run()
            elif sphere == "rim_images":
                r = _edge_at_rim_images(run)
            else:
                r = _edge_on_sphere(run, sphere)
        psf = r.psf
        row = dict(reference="huygens_psf(n_pupil='auto')" + ("" if sphere == "paraxial" else f", edge at {sphere}"),
                   ref_error=r.error_estimate, ref_n_pupil=r.n_pupil,
                   ref_levels=[list(lv) for lv in r.levels],
                   ref_warnings=sorted({str(w.message)[:120] for w in caught}))
    else:
        sys.path.insert(0, str(ROOT / "tests"))
        import test_ideal_lens_truth as tl
        from wave_truth import ideal_lens_doe_psf, two_ideal_lenses_psf

        if kind == "two_lens":
            psf = two_ideal_lenses_psf(tl.SYSTEM, fld, wl, center, ks, tl.PIXEL, pitch=1e-3)
            coarse = two_ideal_lenses_psf(tl.SYSTEM, fld, wl, center, ks, tl.PIXEL, pitch=2e-3)
            row = dict(reference="wave_truth.two_ideal_lenses_psf (1 µm)", ref_error=l1(psf, coarse),
                       ref_note="ref_error: the truth's change from 2 to 1 µm sampling")
        else:
            doe, wl, depth, sensor = tl._doe(SINGLE[rest[0]])
            psf = ideal_lens_doe_psf(tl.F1, tl.R1, wl, center, ks, tl.PIXEL, sensor, doe=doe, doe_dist=tl.DOE_DIST,
                                     depth=depth)
            row = dict(reference="wave_truth.ideal_lens_doe_psf", ref_error=None,
                       ref_note="the truth samples the DOE's own 1 µm grid (tests/test_ideal_lens_truth.py)")
    row["ref_s"] = time.perf_counter() - t
    if fn is not None:
        torch.save(dict(psf=psf, row=row), fn)
    return psf, row


def run(case: str, ks: int, variants, max_n: int, cache, sphere: str = "paraxial", tol: float | None = None,
        doe_distance: float | None = None):
    eng, geo = engine_psfs(case, ks, variants, doe_distance)
    limit = {"memory_limit": os.environ.get(MEMORY_LIMIT_ENV)}  # (the engine's refusals depend on it)
    if geo is None:
        return dict(case=case, error={v: r for v, r in eng.items()}, **limit)
    try:
        ref, row = reference(case, geo, ks, max_n, cache, sphere, tol)
    except ValueError as e:  # e.g. no stop-rim images for sphere="rim_images" (a rim ray that fails off axis)
        ref, row = None, dict(reference_error=str(e)[:200])
    row["sphere"] = sphere
    hl, fld, wl, depth, center = geo
    res = dict(case=case, ks=ks, field=list(fld), wavelength=wl, depth=depth, pitch=hl.sensor_pitch,
               doe_distance=hl.doe_distance, doe_pitch=float(hl.doe.pitch), **limit, **row)
    if case.startswith("file:"):
        par = hl.lens.paraxial()
        res["f_number"] = float(par.efl) / float(par.epd)
    for v, r in eng.items():
        res[v] = r if isinstance(r, str) else dict(l1=None if ref is None else l1(r[0], ref), time_s=r[1], step=r[3],
                                                   warnings=r[2], **r[4])
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*")
    ap.add_argument("--pick", type=Path, default=None, help="print a seeded pick of lens files from this folder, "
                    "one per kind (pick_lens_files), and run nothing")
    ap.add_argument("--seed", type=int, default=47, help="--pick's seed")
    ap.add_argument("--ks", type=int, default=32)
    ap.add_argument("--max-n", type=int, default=432, help="the Huygens reference's finest pupil grid")
    ap.add_argument("--variants", nargs="+", default=["default", "fresnel", "asm", "doe", "default_iu8"])
    ap.add_argument("--cache", type=Path, default=None, help="a folder for the references (resumable sweeps)")
    ap.add_argument("--sphere", type=_sphere_kind, default="paraxial",
                    help="the Huygens reference's edge: 'paraxial' (on the sphere through the paraxial exit pupil), "
                         "'rim_images' (at the stop rim's images) or a sphere radius in mm")
    ap.add_argument("--doe-distance", type=float, default=None,
                    help="file cases with PITCH_UM only: the blank DOE's plane (mm after the last vertex) instead "
                         "of the default rule's (a plane scan; the reference, which does not depend on it, is reused)")
    ap.add_argument("--tol", type=float, default=None,
                    help="the Huygens reference's levels must agree to this (default: huygens_psf's AUTO_TOL, 2e-4)")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    if a.pick is not None:
        picked = pick_lens_files(a.pick, a.seed)
        print(json.dumps(picked, indent=1))
        return picked
    if not a.cases:
        ap.error("give cases (or --pick ROOT)")
    if a.doe_distance is not None and not all(c.startswith("file:") and _file_case(c.split(":")[1:])[2] is not None
                                               for c in a.cases):
        ap.error("--doe-distance: file:PATH:FRAC:PITCH_UM cases only (the sensor pitch must not follow the DOE's)")
    if a.cache is not None:
        a.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for c in a.cases:
        r = run(c, a.ks, a.variants, a.max_n, a.cache, a.sphere, a.tol, a.doe_distance)
        emit_row(rows, r, a.output)
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
