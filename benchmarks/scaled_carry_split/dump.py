"""Run the Planar case (plain carry default, scaled_same_plane as `same`, on a 2x finer lattice as `same2`) dumping the DOE-plane fields and the scaled carry inputs."""
import os, sys, torch, warnings
sys.path.insert(0, "benchmarks"); sys.path.insert(0, ".")
torch.set_grad_enabled(False)
import stop_edge_references as S
from raywave.hybrid.coherent import exit_pupil as X
case = sys.argv[1]; tag = sys.argv[2]; variants = sys.argv[3].split(",")
D = {}
orig_DF = X.DOEField
def DF(field, *a, **k):
    D.setdefault("doe", []).append(dict(u=field.envelope.clone(), origin=field.grid.origin, pitch=field.grid.pitch, shape=field.grid.shape,
                                        wl=field.wavelength, n=field.n, carrier=field.carrier))
    return orig_DF(field, *a, **k)
X.DOEField = DF
orig_sc = X.scaled_carry
def sc(field, out, sphere, planes, carrier):
    D["scin"] = dict(env=field.envelope.clone(), origin=field.grid.origin, pitch=field.grid.pitch, shape=field.grid.shape,
                     wl=field.wavelength, n=field.n, out=(out.origin, out.pitch, out.shape), sphere=sphere, planes=planes, carrier=carrier)
    print("scaled carry: sphere", sphere, "planes", planes, "in", field.grid.shape, field.grid.pitch, "out", out.shape, out.pitch, flush=True)
    return orig_sc(field, out, sphere, planes, carrier)
X.scaled_carry = sc
orig_ff, orig_sff, orig_sl = X._fallback_fits, X._scaled_fallback_fits, X._scaled_lattice
st = {}
for v in variants:
    D.clear()
    X._fallback_fits, X._scaled_fallback_fits = orig_ff, orig_sff
    X.SCALED_CARRY_CHART = False
    X._scaled_lattice = orig_sl
    if v in ("same", "same2"):  # the scaled carry from the plain carry's plane (same2: on a lattice 2x finer)
        def ff(*a, **k):
            z = orig_ff(*a, **k); st["z"] = z; return None
        def sff(lens, source, zs, *a, **k):
            return orig_sff(lens, source, (st["z"],) + tuple(zs[1:]), *a, **k)
        X._fallback_fits, X._scaled_fallback_fits = ff, sff
    if v == "same2":
        def sl(sim, sphere, planes, device):
            lat = orig_sl(sim, sphere, planes, device)
            return X.CoarseLattice(lat.origin, lat.pitch / 2, (int(lat.shape[0] * 2), int(lat.shape[1] * 2)), device)
        X._scaled_lattice = sl
    eng, geo = S.engine_psfs(case, 32, ["default"])
    r = eng["default"]
    print(v, r[3], flush=True)
    hl = geo[0]
    D["psf"] = r[0]; D["geo"] = dict(center=geo[4], z_doe=float(hl.doe_z()), z_sensor=float(hl.sensor_z()), pitch=hl.sensor_pitch)
    torch.save(dict(D), f"{os.environ.get('RUNS', 'runs')}/{tag}_{v}.pt")
ref, row = S.reference(case, geo, 32, 1024, __import__("pathlib").Path(os.environ.get("SCALED_CARRY_DIAG_CACHE", "benchmark_cache")), "rim_images", 1e-6)
torch.save(ref, f"{os.environ.get('RUNS', 'runs')}/{tag}_ref.pt")
