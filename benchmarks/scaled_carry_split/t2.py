from off import *
A = torch.load(os.environ.get("RUNS", "runs") + "/planar_plainA.pt")["A"]
As = fin.envelope
ph = (As.conj()*A).sum(); A = A*(ph.abs()/ph).conj()*0 + A*(ph.conj()/ph.abs())  # align global phase of A to As
print("plane-1 envelopes rel L2 (plain resampled vs scaled construction)", float((A-As).norm()/As.norm()))
w = As.abs(); m = w > 0.5*w.max()
r = A[m]/As[m]
print("interior ratio |.| mean/std", float(r.abs().mean()), float(r.abs().std()), "phase std", float(r.angle().std()))
fin2 = Field(A, fin.grid, fin.wavelength, fin.n, (0.0, 0.0))
u = ep.scaled_carry(fin2, out, si["sphere"], si["planes"], si["carrier"])
P = psf(u); print("scaled carry of the plain construction: proxy L1 vs plain", l1(P, Pa))
# spectra at low f
N = 4096
Fa, Fb = torch.fft.fft2(A, s=(N, N)), torch.fft.fft2(As, s=(N, N))
f = torch.fft.fftfreq(N, d=fin.grid.pitch[0], dtype=torch.float64); FR = torch.sqrt(f[None]**2 + f[:, None]**2)
for lim in (2, 4.3, 10, 30, 113):
    mm = FR < lim
    print(lim, "rel err", float((Fa[mm]-Fb[mm]).norm()/Fa[mm].norm()))
