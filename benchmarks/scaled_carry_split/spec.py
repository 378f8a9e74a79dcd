import os
import torch, math
a = torch.load(os.environ.get("RUNS", "runs") + "/planar_plain.pt", weights_only=False)
d = torch.load(os.environ.get("RUNS", "runs") + "/planar_fields.pt"); ua, ub = d["ua"], d["ub"]
da = a["doe"][-1]; (ox, oy), (p, _), (ny, nx) = da["origin"], da["pitch"], da["shape"]
wl, n, car = da["wl"], da["n"], da["carrier"]
fx, fy, fz = (0.0, 14.938340186269224, 97.34); zd = 92.9860144241317; r2 = fz - zd
k = 2*math.pi*n/(wl*1e-3)
xs = ox + torch.arange(nx, dtype=torch.float64)*p; ys = oy + torch.arange(ny, dtype=torch.float64)*p
rr = torch.sqrt((xs[None]-fx)**2 + (ys[:, None]-fy)**2 + r2*r2)
S = torch.polar(torch.ones_like(rr), -k*((rr - r2) + car[0]*xs[None] + car[1]*ys[:, None]))
ea, eb = ua/S, ub/S
del rr, S
N = 8192
Fa = torch.fft.fft2(ea, s=(N, N)); Fb = torch.fft.fft2(eb, s=(N, N))
f = torch.fft.fftfreq(N, d=p, dtype=torch.float64)
FR = torch.sqrt(f[None]**2 + f[:, None]**2)
for lim in (5, 10, 20, 40, 80, 160, 1000):
    m = FR < lim
    print(f"|f|<{lim}/mm: power frac a {float((Fa[m].abs()**2).sum()/(Fa.abs()**2).sum()):.6f}  rel err {float((Fa[m]-Fb[m]).norm()/Fa[m].norm()):.4g}")
m = (FR < 20) & (Fa.abs() > 0.05*Fa.abs().max())
r = Fb[m]/Fa[m]
fxm = f[None].expand(N, N)[m]; fym = f[:, None].expand(N, N)[m]
ph = r.angle(); w = Fa[m].abs()**2
cols = torch.stack([torch.ones_like(fxm), fxm, fym, fxm**2, fxm*fym, fym**2], 1)
W = w.sqrt()[:, None]
c = torch.linalg.lstsq(cols*W, (ph*w.sqrt())[:, None]).solution[:, 0]
res = ph - cols@c
print("phase fit coeffs", c.tolist(), "resid wstd", float(((res**2*w).sum()/w.sum()).sqrt()), "raw wstd", float(((ph-(ph*w).sum()/w.sum())**2*w).sum().div(w.sum()).sqrt()))
print("amp ratio wmean", float((r.abs()*w).sum()/w.sum()), "wstd", float((((r.abs()-1)**2*w).sum()/w.sum()).sqrt()))
Fb2 = Fb.clone(); FX, FY = f[None].expand(N,N), f[:, None].expand(N,N)
corr = torch.polar(torch.ones((), dtype=torch.float64), -(c[0]+c[1]*FX+c[2]*FY+c[3]*FX**2+c[4]*FX*FY+c[5]*FY**2))
for lim in (10, 20, 40):
    mm = FR < lim
    print(lim, "after quad phase removal rel err", float((Fa[mm]-(Fb*corr)[mm]).norm()/Fa[mm].norm()))
