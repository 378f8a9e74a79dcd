"""Issue 47 (h47o): the scaled carry's error on one case: engine PSF variants against the converged Huygens reference
(cached in $SCALED_CARRY_DIAG_CACHE), PSFs and rel L1 saved to OUT.pt / OUT.json. Variants (comma separated):
default; forced_scaled (the scaled carry from the fallback's own plane); scaled_same_plane (the scaled carry from
the plane the plain carry takes); fineF (that, on a scaled lattice F times finer); append _nochart for the carry in
the far plane's own coordinates (SCALED_CARRY_CHART False), else the chart. h47q: aaF (fineF's construction, F times
finer, low-passed to the default lattice's band and decimated to it before the carry: an alias-free input, the carry
on the default lattice); default_aaF / forced_aaF: the same from the default's / the fallback's own plane; aarF (with
the chart): low-passed but not decimated, the chart's grid at the default lattice's pitch (its bicubic reads the finer
field).

Usage (repository root, under the memory lock): python benchmarks/scaled_carry_diag.py CASE VARIANTS OUT"""
import os, sys, json, time, warnings, resource
sys.path.insert(0, "benchmarks")
import torch
torch.set_grad_enabled(False)
import stop_edge_references as S
from raywave.hybrid.coherent import exit_pupil as X
from pathlib import Path

case, variants = sys.argv[1], sys.argv[2].split(",")
out = Path(sys.argv[3])
CACHE = Path(os.environ.get("SCALED_CARRY_DIAG_CACHE", "benchmark_cache"))
orig_ff, orig_sff, orig_sl, orig_sc = X._fallback_fits, X._scaled_fallback_fits, X._scaled_lattice, X.scaled_carry
orig_cfc = X._check_fallback_carry
orig_chart = X.SphereChart
from raywave.wave.grid import Field, Grid


def decimated(field, f, keep: bool = False):
    """``field`` (a scaled-carry input on a lattice ``f``× finer) low-passed to the band of the lattice ``f``× coarser
    (an ideal filter on its FFT) and decimated to it (``keep``: not decimated)."""
    env, g = field.envelope, field.grid
    ny, nx = env.shape
    spec = torch.fft.fft2(env)
    fy = torch.fft.fftfreq(ny, dtype=torch.float64).abs()
    fx = torch.fft.fftfreq(nx, dtype=torch.float64).abs()
    spec *= ((fy[:, None] < 0.5 / f) & (fx[None, :] < 0.5 / f)).to(spec.dtype)
    low = torch.fft.ifft2(spec)
    low = low if keep else low[::f, ::f].contiguous()
    del spec
    return Field(low, Grid(g.origin, g.pitch[0] * (1 if keep else f), low.shape), field.wavelength, field.n,
                 field.carrier)


class CoarseChart(X.SphereChart):
    """h47o's chart whose grid's pitch (``pc * s_min`` in ``_charted_carry``) is ``FACTOR``× the field's."""
    FACTOR = 1

    def __init__(self, *a):
        super().__init__(*a)
        self.s_min = self.s_min * CoarseChart.FACTOR
state = {}

def patched(variant):
    X._fallback_fits, X._scaled_fallback_fits, X._scaled_lattice = orig_ff, orig_sff, orig_sl
    X.scaled_carry, X._check_fallback_carry, X.SphereChart = orig_sc, orig_cfc, orig_chart
    X.SCALED_CARRY_CHART = not variant.endswith("_nochart")
    variant = variant.replace("_nochart", "")
    if "aa" in variant:  # the construction F x finer, decimated alias-free before the carry on the default lattice
        head, f = variant.split("aa")
        keep = f.startswith("r")  # aarF: low-passed but kept F x finer; the chart's grid F x the field's pitch
        f = int(f.lstrip("r"))
        if keep:
            CoarseChart.FACTOR = f
            X.SphereChart = CoarseChart
        def sl(sim, sphere, planes, device):
            lat = orig_sl(sim, sphere, planes, device)
            return X.CoarseLattice(lat.origin, lat.pitch / f, (lat.shape[0] * f, lat.shape[1] * f), device)
        X._scaled_lattice = sl
        X.scaled_carry = lambda field, *a: orig_sc(decimated(field, f, keep), *a)
        X._check_fallback_carry = lambda *a, **k: None  # (it would size the carry on the finer construction)
        variant = {"": "scaled_same_plane", "default_": "default", "forced_": "forced_scaled"}[head]
    if variant == "default":
        pass
    elif variant == "forced_scaled":  # the research notes' forcing: _fallback_fits -> None
        X._fallback_fits = lambda *a, **k: None
    elif variant == "scaled_same_plane":  # the scaled carry from the plane the plain carry would take
        def ff(*a, **k):
            z = orig_ff(*a, **k); state["z"] = z; return None
        def sff(lens, source, zs, *a, **k):
            return orig_sff(lens, source, (state["z"],) + tuple(zs[1:]), *a, **k)
        X._fallback_fits, X._scaled_fallback_fits = ff, sff
    elif variant.startswith("fine"):  # scaled_same_plane on a lattice FACTOR x finer
        f = float(variant.split("_")[0][4:])
        def ff(*a, **k):
            z = orig_ff(*a, **k); state["z"] = z; return None
        def sff(lens, source, zs, *a, **k):
            return orig_sff(lens, source, (state["z"],) + tuple(zs[1:]), *a, **k)
        X._fallback_fits, X._scaled_fallback_fits = ff, sff
        def sl(sim, sphere, planes, device):
            lat = orig_sl(sim, sphere, planes, device)
            return X.CoarseLattice(lat.origin, lat.pitch / f, (int(lat.shape[0] * f), int(lat.shape[1] * f)), device)
        X._scaled_lattice = sl
    elif variant.startswith("scaled_at_"):  # the scaled carry from z_doe - d
        d = float(variant[len("scaled_at_"):])
        def ff(*a, **k):
            return None
        def sff(lens, source, zs, *a, **k):
            return orig_sff(lens, source, (zs[1] - d,) + tuple(zs[1:]), *a, **k)
        X._fallback_fits, X._scaled_fallback_fits = ff, sff
    elif variant.startswith("plain_at_"):
        d = float(variant[len("plain_at_"):])
        def ff(lens, source, z_from, z_doe, *a, **k):
            return orig_ff(lens, source, z_doe - d, z_doe, *a, **k)
        X._fallback_fits = ff

res = {"case": case, "rows": {}}
psfs = {}
geo = None
for v in variants:
    patched(v)
    t = time.perf_counter()
    eng, g = S.engine_psfs(case, 32, ["default"])
    r = eng["default"]
    if isinstance(r, str):
        res["rows"][v] = {"error": r}; print(v, r, flush=True); continue
    geo = g
    psfs[v] = r[0]
    res["rows"][v] = dict(step=r[3], time_s=time.perf_counter() - t,
                          warnings=[w for w in r[2] if "Deprec" not in w])
    print(v, r[3], [w[:100] for w in r[2] if "Stop" in w], flush=True)
X._fallback_fits, X._scaled_fallback_fits, X._scaled_lattice, X.scaled_carry = orig_ff, orig_sff, orig_sl, orig_sc
ref, row = S.reference(case, geo, 32, 1024, CACHE, "rim_images", 1e-6)
res["ref_error"] = row.get("ref_error")
for v, p in psfs.items():
    res["rows"][v]["l1"] = S.l1(p, ref)
    print(v, "l1", res["rows"][v]["l1"], flush=True)
res["peak_rss_kb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
torch.save(dict(ref=ref, psfs=psfs, res=res), out.with_suffix(".pt"))
json.dump(res, open(out.with_suffix(".json"), "w"), indent=1, default=str)
