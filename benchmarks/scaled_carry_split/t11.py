from off import *
d = torch.load(os.environ.get("RUNS", "runs") + "/planar_plainA2.pt"); A = d["A"]; (o, q, sh) = d["grid"]
# (a) point decimation to q
Ad = A[::2, ::2]
g = Grid(o, 2*q, Ad.shape)
u = ep.scaled_carry(Field(Ad, g, fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
print("plainA q/2 -> point-decimated to q:", l1(psf(u), Pa), flush=True)
# (b) ideal low-pass at q's Nyquist (half band) then decimate
ny, nx = A.shape
F = torch.fft.fft2(A)
fy = torch.fft.fftfreq(ny, dtype=torch.float64).abs(); fx = torch.fft.fftfreq(nx, dtype=torch.float64).abs()
for cut in (0.25, 0.2):
    m = ((fy[:, None] < cut) & (fx[None] < cut)).to(F.dtype)
    Al = torch.fft.ifft2(F*m)
    u = ep.scaled_carry(Field(Al[::2, ::2].contiguous(), g, fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
    print(f"plainA q/2 -> low-pass {cut} (cycles/sample at q/2) -> q:", l1(psf(u), Pa), flush=True)
    u = ep.scaled_carry(Field(Al, Grid(o, q, sh), fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
    print(f"   (low-passed, kept at q/2):", l1(psf(u), Pa), flush=True)
