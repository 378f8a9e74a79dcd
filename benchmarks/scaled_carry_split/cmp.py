import os
import torch, math, sys
a = torch.load(os.environ.get("RUNS", "runs") + "/planar_plain.pt", weights_only=False); b = torch.load(os.environ.get("RUNS", "runs") + "/planar_same.pt", weights_only=False)
ref = torch.load(os.environ.get("RUNS", "runs") + "/planar_ref.pt", weights_only=False)
def l1(p, r): return float((p - r).abs().sum() / r.abs().sum())
print("psf l1 plain", l1(a["psf"], ref), "scaled", l1(b["psf"], ref), "plain-vs-scaled", l1(b["psf"], a["psf"]))
da, db = a["doe"][-1], b["doe"][-1]
print(da["origin"], da["shape"], db["origin"], db["shape"], da["carrier"], db["carrier"])
ua, ub = da["u"], db["u"]
assert da["origin"] == db["origin"] and da["shape"] == db["shape"]
ph = (ub.conj() * ua).sum(); ub = ub * (ph / ph.abs())
print("field rel L2", float((ua - ub).norm() / ua.norm()))
# by distance from the beam's edge: use amplitude of ua as proxy
A = ua.abs(); top = A.max()
for lo, hi in [(0.9, 2), (0.5, 0.9), (0.1, 0.5), (0.01, 0.1), (0, 0.01)]:
    m = (A >= lo * top) & (A < hi * top)
    e = (ua - ub)[m].norm()**2 / ua.norm()**2
    print(f"amp in [{lo},{hi}): frac err^2 {float(e):.3g}  n={int(m.sum())}")
m = A > 0.5 * top
r = (ub[m] / ua[m])
print("interior: |ratio| mean", float(r.abs().mean()), "std", float(r.abs().std()), "phase std", float(r.angle().std()))
torch.save(dict(ua=ua, ub=ub), os.environ.get("RUNS", "runs") + "/planar_fields.pt")
