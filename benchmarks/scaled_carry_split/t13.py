from off import *
d = torch.load(os.environ.get("RUNS", "runs") + "/planar_plainA2.pt"); A = d["A"]; (o, q, sh) = d["grid"]
ny, nx = A.shape
F = torch.fft.fft2(A)
fy = torch.fft.fftfreq(ny, dtype=torch.float64).abs(); fx = torch.fft.fftfreq(nx, dtype=torch.float64).abs()
Al = torch.fft.ifft2(F*((fy[:, None] < 0.25) & (fx[None] < 0.25)).to(F.dtype))[::2, ::2].contiguous(); del F, A
g = Grid(o, 2*q, Al.shape)
# PSF centroid of the plain proxy (pixels of 3 µm), relative to the crop centre
I = Pa; ii = torch.arange(32, dtype=torch.float64) - 15.5
cyp = float((I.sum(1)*ii).sum()/I.sum()); cxp = float((I.sum(0)*ii).sum()/I.sum())
print("plain PSF centroid offset (px of 3 µm): y", cyp, "x", cxp, " centre", geo["center"], "sphere", si["sphere"], flush=True)
fx0, fy0, fz = si["sphere"]; z1 = si["planes"][0]; k = 2*math.pi*fin.n/(fin.wavelength*1e-3)
xs = o[0] + torch.arange(Al.shape[1], dtype=torch.float64)*2*q; ys = o[1] + torch.arange(Al.shape[0], dtype=torch.float64)*2*q
def rdist(X, Y): return torch.sqrt((xs[None]-X)**2 + (ys[:, None]-Y)**2 + (fz-z1)**2)
r0 = rdist(fx0, fy0)
for dy in [0.0, cyp*3e-3, 0.02, -0.02]:
    sp = (fx0, fy0 + dy, fz)
    A2 = Al * torch.polar(torch.ones_like(r0), k*(rdist(*sp[:2]) - r0))
    u = ep.scaled_carry(Field(A2, g, fin.wavelength, fin.n, (0.0, 0.0)), out, sp, si["planes"], si["carrier"])
    print(f"sphere shifted dy={dy*1e3:.1f} µm: proxy vs plain", l1(psf(u), Pa), flush=True)
