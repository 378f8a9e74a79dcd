import os
import torch, math, sys, time
sys.path.insert(0, ".")
torch.set_grad_enabled(False)
import raywave.hybrid.coherent.exit_pupil as ep
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import propagate_window
b = torch.load(os.environ.get("RUNS", "runs") + "/planar_same.pt", weights_only=False)
ua = torch.load(os.environ.get("RUNS", "runs") + "/planar_fields.pt")["ua"]
ref = torch.load(os.environ.get("RUNS", "runs") + "/planar_ref.pt", weights_only=False)
si = b["scin"]; da = b["doe"][-1]
fin = Field(si["env"], Grid(si["origin"], si["pitch"][0], si["shape"]), si["wl"], si["n"], (0.0, 0.0))
out = Grid(*si["out"][:1], si["out"][1][0], si["out"][2])
geo = b["geo"]
def psf(u):
    cx, cy = geo["center"]; pp = 1e-3; nn = 96
    c = Grid((cx - (nn/2 - 0.5)*pp, cy - (nn/2 - 0.5)*pp), pp, (nn, nn))
    e = propagate_window(Field(u, out, si["wl"], si["n"], da["carrier"]), c, geo["z_sensor"] - geo["z_doe"]).envelope
    I = e.abs()**2
    return I.reshape(32, 3, 32, 3).sum((1, 3))
def l1(p, r): return float((p - r).abs().sum() / r.abs().sum())
Pa = psf(ua)
print("proxy: plain vs ref", l1(Pa/Pa.sum()*ref.sum(), ref))
def run(name, fn):
    t = time.time()
    u = fn(fin, out, si["sphere"], si["planes"], si["carrier"])
    P = psf(u)
    print(f"{name}: proxy L1 vs plain {l1(P, Pa):.4g}; vs ref {l1(P/P.sum()*ref.sum(), ref):.4g}  ({time.time()-t:.0f}s)", flush=True)
    return u
if __name__ == "__main__":
    run("main", ep.scaled_carry)
