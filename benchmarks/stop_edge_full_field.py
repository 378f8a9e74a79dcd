"""Issue 47 (h47): why the default stop edge misses 1e-3 on the double Gauss at full field. Each engine variant's PSF
against two converged Huygens references of benchmarks/stop_edge_references.py: the edge on the sphere through the
paraxial exit pupil (``paraxial``, the table's reference) and at the stop rim's images (``rim_images``). One JSON line
per variant (and the list with ``-o``); docs/ray-wave.md "The double Gauss at full field" has the table.

Variants (``NAME``; the engine's constants set for the variant's PSF only, a diagnostic, not an API):

- ``default``;  ``nodes128`` / ``nodes32`` (the node grid);  ``rim256`` (256 rim points instead of 64);
- ``no_rim`` (the edge sharp on the paraxial exit-pupil plane instead of at the rim's images);
- ``rzN`` (the ripple band fixed at ``N`` Fresnel zones, no reach rule, the inner tail scaling with it as in the
  library);  ``norule`` (the band fixed at ``RIPPLE_ZONES``, 5: the default before the reach rule of h47b);
- ``gotolX`` (the caustic fallback's ``GO_PHASE_TOL = X`` rad);  ``rmX`` (the reach rule's ``REACH_MARGIN = X``);
  ``rzN_no_rim``;  ``rzN_in5`` (the inner tail held where 5 zones put it);
- ``tailX`` (``INNER_TAIL = X``);  ``doeD`` (the blank DOE ``D`` mm after the last vertex instead of the default).

    PYTHONPATH=. python benchmarks/stop_edge_full_field.py real:double_gauss:1.0 --cache DIR \
        --variants default rz12 rz16 no_rim rz12_no_rim [-o F]

The references are computed (and cached in ``--cache``) by stop_edge_references.py's ``reference`` when missing.
"""

import argparse
import contextlib
import re
import sys
import time
from pathlib import Path

import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stop_edge_references as ser  # noqa: E402

X = "raywave.hybrid.coherent"


def _settings(name: str):
    """``(load_hybrid keywords, {module: {constant: value}}, nodes or None, rim points or None, no_rim)`` of a
    variant name."""
    kw, consts, nodes, rim_k = {}, {}, None, None
    parts = name.replace("no_rim", "norim").split("_")
    for part in parts:
        if m := re.fullmatch(r"rz(\d+(?:\.\d+)?)", part):
            rz = float(m[1])
            consts.setdefault(f"{X}.stop_edge", {}).update(RIPPLE_ZONES=rz, MAX_RIPPLE_ZONES=rz)  # fixed: no rule
            if "in5" in parts:  # the inner tail where 5 zones put it
                consts.setdefault(f"{X}.stop_edge", {})["INNER_TAIL"] = 0.8 * 5.0 / rz
        elif part == "norule":  # the band fixed at RIPPLE_ZONES (before the reach rule, h47b)
            consts.setdefault(f"{X}.stop_edge", {})["MAX_RIPPLE_ZONES"] = 5.0
        elif m := re.fullmatch(r"gotol(\d+(?:\.\d+)?(?:e-?\d+)?)", part):  # the caustic fallback's tolerance
            consts.setdefault(f"{X}.exit_pupil", {})["GO_PHASE_TOL"] = float(m[1])
        elif m := re.fullmatch(r"rm(\d+(?:\.\d+)?)", part):  # the reach rule's margin (zones)
            consts.setdefault(f"{X}.stop_edge", {})["REACH_MARGIN"] = float(m[1])
        elif m := re.fullmatch(r"tail(\d+(?:\.\d+)?)", part):
            consts.setdefault(f"{X}.stop_edge", {})["INNER_TAIL"] = float(m[1])
        elif m := re.fullmatch(r"nodes(\d+)", part):
            nodes = int(m[1])
        elif m := re.fullmatch(r"rim(\d+)", part):
            rim_k = int(m[1])
        elif m := re.fullmatch(r"doe(\d+(?:\.\d+)?)", part):
            kw["doe_distance"] = float(m[1])
        elif part not in ("default", "norim", "in5"):
            raise ValueError(f"unknown variant part {part!r} in {name!r}")
    return kw, consts, nodes, rim_k, "norim" in parts


@contextlib.contextmanager
def _patched(consts: dict, rim_k, no_rim: bool):
    """The engine's module constants and rim-image functions set for one variant, restored after."""
    import importlib

    from raywave.hybrid import hybrid_lens
    from raywave.hybrid.coherent import exit_pupil, stop_edge

    saved = []
    for mod, vals in consts.items():
        m = importlib.import_module(mod)
        for k, v in vals.items():
            saved.append((m, k, getattr(m, k)))
            setattr(m, k, v)
    if rim_k is not None:
        for fn in (stop_edge.stop_rim_images, stop_edge.stop_rim_images_many, stop_edge.stop_rim_images_all):
            saved.append((fn, "__defaults__", fn.__defaults__))
            fn.__defaults__ = fn.__defaults__[:-1] + (rim_k,)
    if no_rim:
        saved.append((hybrid_lens, "stop_rim_images_all", hybrid_lens.stop_rim_images_all))
        saved.append((exit_pupil, "stop_rim_images", exit_pupil.stop_rim_images))
        hybrid_lens.stop_rim_images_all = lambda optics, ft, wls, depth, *a, **k: [[None] * ft.shape[0] for _ in wls]
        exit_pupil.stop_rim_images = lambda *a, **k: None
    try:
        yield
    finally:
        for obj, k, v in reversed(saved):
            setattr(obj, k, v)


def variant_psf(case: str, name: str, ks: int):
    """``(psf (ks, ks), geo as stop_edge_references.engine_psfs, seconds)`` of one variant, or an error string."""
    kw, consts, nodes, rim_k, no_rim = _settings(name)
    hl, fld, wl, depth = ser._hybrid(case, kw)
    t = time.perf_counter()
    with _patched(consts, rim_k, no_rim), torch.no_grad():
        try:
            r = hl.psf_result(fld, wl, ks=ks, depth=depth, rays=nodes)
        except (ValueError, MemoryError) as e:
            return f"{type(e).__name__}: {str(e)[:160]}"
    return r.psf[0, 0].detach(), (hl, fld, wl, depth, tuple(float(c) for c in r.center[0, 0])), \
        time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case")
    ap.add_argument("--variants", nargs="+", default=["default", "rz12", "rz16", "no_rim", "rz12_no_rim"])
    ap.add_argument("--ks", type=int, default=32)
    ap.add_argument("--max-n", type=int, default=1024)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    a.cache.mkdir(parents=True, exist_ok=True)
    refs, rows = {}, []
    for v in a.variants:
        out = variant_psf(a.case, v, a.ks)
        if isinstance(out, str):
            row = dict(case=a.case, variant=v, error=out)
        else:
            psf, geo, secs = out
            if not refs:  # the references at the default variant's crop centre (the same for every variant)
                for s in ("paraxial", "rim_images"):
                    refs[s] = ser.reference(a.case, geo, a.ks, a.max_n, a.cache, s)
            row = dict(case=a.case, variant=v, time_s=secs, doe_distance=geo[0].doe_distance,
                       **{f"l1_{s}": ser.l1(psf, r[0]) for s, r in refs.items()},
                       **{f"ref_error_{s}": r[1].get("ref_error") for s, r in refs.items()})
        emit_row(rows, row, a.output)
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
