"""Peak memory of the caustic fallback's exits (issue 47, h47m): the plain carry from the fallback's plane or the
farthest plane before the fold that fits (``_fallback_planes``), and the scaled carry (``scaled_carry``).

Each point is one default PSF (``edge_step="adaptive"``, ks 32, no graph unless ``--grad``) of a
benchmarks/stop_edge_references.py case in a fresh process (``--child``): the peak resident set size (VmHWM, reset
before the call) above the resident set before it (the process's baseline: torch, the lens), the exit taken (from its
StopEdgeWarning), every ``check_window_memory`` call (samples and step), and the carry's sizes: the construction's
window on the earlier plane (``n_from``), the DOE-plane window (``n_doe``), the FFT grid of the windowed angular
spectrum (``n_fft``: ``(Ny_in + Ny_out + guard)(Nx_in + Nx_out + guard)``) and its transfer band (``n_band``); and
the peak within the carry itself (VmHWM reset before the construction and before the carry). The DOE pitch
(``--pitches``, µm; default the case's own) varies the windows.

    OMP_NUM_THREADS=1 RAYWAVE_MEMORY_LIMIT=16GiB python benchmarks/fallback_memory.py CASE [CASE ...] -o OUT.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

#: issue 47's three cases whose fallback overshot a 6 GiB limit (h47f, session xxvi)
CASES = {
    "leica28_0.7": "file:/tmp/optics/Optics/Photography/Leica/Leica Elmarit/Leica Elmarit-R 28mm F2.8.zmx:0.7:3",
    "pentax50_0.7": "file:/tmp/optics/Optics/Photography/Ricoh/Ricoh Pentax/Ricoh Pentax DA/"
                    "Ricoh smc Pentax-DA 50mm F1.8.zmx:0.7:3",
    "planar80_0.7": "file:/tmp/optics/Optics/Photography/Zeiss/Zeiss Planar/Zeiss Planar 2.880.zmx:0.7:3",
}
#: a case whose fallback takes the scaled carry (under 16 GiB; h47f, session xxvi)
SCALED = {"olympus24_0.7": "file:/tmp/optics/Optics/Photography/Olympus/Olympus Auto-W/"
                           "Olympus 24mm f2 J Zuiko Auto-W.zmx:0.7:3"}


def _exit(messages: list) -> str:
    """The caustic fallback's exit named by its StopEdgeWarning (or "none")."""
    for m in messages:
        if "scaled angular spectrum" in m:
            return "scaled"
        if "carried to it by the angular spectrum" in m and "where the geometric-optics field is off by" in m:
            return "farthest_plane"
        if "carried to it by the angular spectrum" in m:
            return "fallback_plane"
    if any("built on the plane itself" in m for m in messages):
        return "plane_itself"
    return "none"


def child(case: str, pitch_um: float | None, grad: bool) -> dict:
    """One default PSF of ``case`` (DOE pitch ``pitch_um`` µm, None: the case's), its peaks and the carry's sizes."""
    import torch

    torch.set_num_threads(1)
    from _memory import peak_mb, reset_peak, rss_mb
    from stop_edge_references import _hybrid

    import raywave.hybrid.coherent.exit_pupil as ep
    import raywave.hybrid.coherent.geometry as geometry
    from raywave.wave.propagation.transfer import WindowSource, _geometry

    kw = {} if pitch_um is None else {"doe_pitch": pitch_um * 1e-3, "doe_distance": PLANES[case]}
    hl, fld, wl, depth = _hybrid(CASE_ALIASES.get(case, case), kw)
    checks, carries, stages = [], [], {}
    orig_check, orig_prop, orig_scaled = geometry.check_window_memory, ep.propagate_window, ep.scaled_carry

    def spy_check(ny, nx, p, *args, **kw2):
        step = kw2.get("step", args[1] if len(args) > 1 else "cut")
        checks.append(dict(ny=int(ny), nx=int(nx), step=step))
        if step in ("fallback", "carry", "scaled") or step.startswith("carry") or step.startswith("scaled"):
            stages["construction_peak_mb"] = peak_mb() - base
            reset_peak()
        return orig_check(ny, nx, p, *args, **kw2)

    def sizes(field, out, z):
        g = _geometry(WindowSource.between(field, out, z), out.shape, field.grid.pitch, 0.5, 2.0)
        return dict(n_from=list(field.envelope.shape[-2:]), n_doe=list(out.shape), fft=list(g.size))

    def spy_prop(field, out, z=None, *a, **k):
        carries.append(dict(kind="plain", **sizes(field, out, z)))
        t = k.get("transfer")
        r = orig_prop(field, out, z, *a, **k)
        if t is not None and hasattr(t, "band"):
            carries[-1]["band"] = list(t.band.shape)
        return r

    def spy_scaled(field, out, sphere, planes, carrier):
        fx, fy, fz = sphere
        r1, r2 = fz - planes[0], fz - planes[1]
        carries.append(dict(kind="scaled", n_from=list(field.envelope.shape[-2:]), n_doe=list(out.shape),
                            dz_scaled=(planes[1] - planes[0]) * r1 / r2))
        return orig_scaled(field, out, sphere, planes, carrier)

    for mod in list(sys.modules.values()):  # every module that imported the check by name
        if mod is not None and getattr(mod, "check_window_memory", None) is orig_check:
            mod.check_window_memory = spy_check
    ep.propagate_window, ep.scaled_carry = spy_prop, spy_scaled
    if hasattr(ep, "check_carry_memory"):  # this tree's exact check before the carry (issue 47, h47m)
        orig_carry = ep.check_carry_memory

        def spy_carry(n_from, n_doe, fft, p, *args, **kw2):
            checks.append(dict(n_from=list(map(int, n_from)), n_doe=list(map(int, n_doe)), fft=list(map(int, fft)),
                               step="carry_check", scaled=kw2.get("scaled", False),
                               estimate_bytes=geometry.carry_bytes(n_from, fft, n_doe if kw2.get("scaled") else None)
                               + kw2.get("extra", 0.0)))
            if len(args) < 1 or True:
                stages["construction_peak_mb"] = peak_mb() - base
                reset_peak()
            return orig_carry(n_from, n_doe, fft, p, *args, **kw2)

        ep.check_carry_memory = spy_carry
    base = rss_mb()
    reset_peak()
    t = time.perf_counter()
    err = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with torch.set_grad_enabled(grad):
                r = hl.psf_result(fld, wl, ks=32, depth=depth)
                if grad and r.psf.requires_grad:
                    r.psf.sum().backward()
        except ValueError as e:  # MemoryLimitError and the other refusals
            err = f"{type(e).__name__}: {e}"
            r = None
    peak = peak_mb()
    msgs = [str(w.message) for w in caught if w.category.__name__ in ("StopEdgeWarning",)]
    row = dict(case=case, doe_pitch_um=hl.doe.pitch * 1e3, grad=grad, base_mb=base, peak_mb=peak,
               extra_mb=peak - base if "construction_peak_mb" not in stages else None,
               checks=checks, carries=carries, exit=_exit(msgs), warnings=[m[:400] for m in msgs],
               s=time.perf_counter() - t, error=err, memory_limit=os.environ.get("RAYWAVE_MEMORY_LIMIT"))
    if "construction_peak_mb" in stages:  # the peak after the carry's check: the carry's own
        row["construction_extra_mb"] = stages["construction_peak_mb"]
        row["carry_extra_mb"] = peak - base
        row["extra_mb"] = max(stages["construction_peak_mb"], peak - base)
    if r is not None:
        psf = r.psf.detach().contiguous().numpy()
        row["psf_sha1"] = hashlib.sha1(psf.tobytes()).hexdigest()[:16]
    with open("/proc/self/status") as fh:
        row["vmhwm_process_mb"] = next(int(s.split()[1]) / 1024 for s in fh if s.startswith("VmHWM:"))
    return row


CASE_ALIASES = {**CASES, **SCALED}


def _carry_sizes(row: dict):
    """``(extra bytes, FFT samples, carried samples)`` of a row whose PSF ran a carry (None otherwise)."""
    plain = [c for c in row.get("carries", []) if "fft" in c]
    if not plain or row.get("error") or row.get("carry_extra_mb") is None:
        return None
    c = plain[-1]
    return row["carry_extra_mb"] * 2**20, c["fft"][0] * c["fft"][1], c["n_from"][0] * c["n_from"][1]


def fit_carry(rows: list) -> dict:
    """Least squares of the carry's extra peak (bytes) against ``a`` · FFT samples + ``b`` · carried samples over the
    rows without a graph, and each row's ratio to :data:`raywave.hybrid.coherent.geometry.CARRY_BYTES`' estimate and
    to the old estimate (120 B a sample of the larger window the old check saw)."""
    import numpy as np

    from raywave.hybrid.coherent.geometry import CARRY_BYTES

    pts = [(r, _carry_sizes(r)) for r in rows if not r.get("grad") and _carry_sizes(r) is not None]
    a = np.array([[f, n] for _, (_, f, n) in pts], float)
    y = np.array([e for _, (e, _, _) in pts], float)
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    out = dict(b_fft=float(coef[0]), b_field=float(coef[1]), points=len(pts),
               residuals=[float(v) for v in (a @ coef - y) / y], per_row=[])
    for r, (e, f, n) in pts:
        old = [c["ny"] * c["nx"] for c in r["checks"] if c.get("step") == "fallback"]
        new = CARRY_BYTES[False][0] * f + CARRY_BYTES[False][1] * n
        out["per_row"].append(dict(case=r["case"], doe_pitch_um=r["doe_pitch_um"], exit=r["exit"],
                                   extra_bytes=e, fft_samples=f, carried_samples=n,
                                   bytes_per_fft_sample=e / f, bytes_per_carried_sample=e / n,
                                   new_estimate_over_peak=new / e,
                                   old_estimate_over_peak=(120 * old[-1] / e) if old else None))
    return out
#: the cases' default DOE planes (mm after the last vertex; benchmarks/results/stop_edge_*_xxvi*.json), kept when
#: ``--pitches`` changes the DOE pitch (the default rule would move the plane with it)
PLANES = {"leica28_0.7": 32.80754512041693, "pentax50_0.7": 36.71321623199246, "planar80_0.7": 51.33601442413169,
          "olympus24_0.7": 29.278012155388467}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*", default=[], help="case names of CASES or stop_edge_references cases (none: "
                    "CASES)")
    ap.add_argument("--pitches", nargs="*", type=float, default=[], help="DOE pitches µm (none: the case's own)")
    ap.add_argument("--grad", action="store_true", help="gradients enabled (the lens's parameters' graph)")
    ap.add_argument("--child", nargs=3, metavar=("CASE", "PITCH_UM", "GRAD"), default=None)
    ap.add_argument("--time", action="store_true", help="each child under /usr/bin/time -v (its whole-process peak)")
    ap.add_argument("--rows-from", nargs="*", type=Path, default=[], help="result files whose rows join (no run "
                    "unless cases are named)")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    if a.child:
        pitch = None if a.child[1] == "case" else float(a.child[1])
        print(json.dumps(child(a.child[0], pitch, a.child[2] == "1")))
        return
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rows = [dict(r, source=str(f)) for f in a.rows_from for r in json.loads(f.read_text())["rows"]]
    for case in (a.cases or ([] if a.rows_from else list(CASES))):
        for pitch in (a.pitches or [None]):
            cmd = [sys.executable, __file__, "--child", case, "case" if pitch is None else str(pitch),
                   "1" if a.grad else "0"]
            if a.time:
                cmd = ["/usr/bin/time", "-v"] + cmd
            out = subprocess.run(cmd, capture_output=True, text=True, env=env)
            line = [s for s in out.stdout.splitlines() if s.startswith("{")]
            if out.returncode or not line:
                rows.append(dict(case=case, doe_pitch_um=pitch, rc=out.returncode, error=out.stderr[-600:]))
            else:
                rows.append(json.loads(line[-1]))
            hwm = [s for s in out.stderr.splitlines() if "Maximum resident set size" in s]
            if hwm:
                rows[-1]["time_v_max_rss_kb"] = int(hwm[-1].split()[-1])
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    res = dict(description=__doc__.split("\n\n")[0], command="OMP_NUM_THREADS=1 python benchmarks/fallback_memory.py "
               + " ".join(argv if argv is not None else sys.argv[1:]),
               memory_limit=os.environ.get("RAYWAVE_MEMORY_LIMIT"), rows=rows)
    try:
        res["fit"] = fit_carry(rows)
    except (ValueError, ImportError, IndexError) as e:  # too few points
        res["fit"] = f"no fit: {e}"
    text = json.dumps(res, indent=1)
    if a.output:
        Path(a.output).write_text(text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
