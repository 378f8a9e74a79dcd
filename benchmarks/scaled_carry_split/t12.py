from off import *
b2 = torch.load(os.environ.get("RUNS", "runs") + "/planar_same2.pt", weights_only=False); s2 = b2["scin"]
A = s2["env"]; g2 = Grid(s2["origin"], s2["pitch"][0], s2["shape"])
P2 = b2["psf"]
print("engine fine2 psf vs ref", l1(P2, ref))
u = ep.scaled_carry(Field(A, g2, fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
print("engine construction q/2, carried at q/2: proxy vs plain", l1(psf(u), Pa), flush=True)
ny, nx = A.shape
F = torch.fft.fft2(A)
fy = torch.fft.fftfreq(ny, dtype=torch.float64).abs(); fx = torch.fft.fftfreq(nx, dtype=torch.float64).abs()
m = ((fy[:, None] < 0.25) & (fx[None] < 0.25)).to(F.dtype)
Al = torch.fft.ifft2(F*m)[::2, ::2].contiguous(); del F
g = Grid(s2["origin"], 2*s2["pitch"][0], Al.shape)
u = ep.scaled_carry(Field(Al, g, fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
print("engine construction q/2, low-passed, decimated to q, carried at q:", l1(psf(u), Pa), flush=True)
u = ep.scaled_carry(Field(A[::2, ::2].contiguous(), g, fin.wavelength, fin.n, (0.0, 0.0)), out, si["sphere"], si["planes"], si["carrier"])
print("engine construction q/2, point-decimated to q:", l1(psf(u), Pa), flush=True)
