import math, sys, torch
sys.path.insert(0, ".")
import raywave.hybrid.coherent.exit_pupil as ep
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import propagate_window

def axes(g):
    (ny, nx), (ox, oy), (p, _) = g.shape, g.origin, g.pitch
    return (ox + torch.arange(nx, dtype=torch.float64) * p)[None, :], (oy + torch.arange(ny, dtype=torch.float64) * p)[:, None]

def disc(x, y, a, edge, cx=0.0, cy=0.0):
    r = torch.sqrt((x-cx) ** 2 + (y-cy) ** 2)
    if edge == 0:
        return (r <= a).double()
    t = ((a + edge / 2 - r) / edge).clamp(0, 1)
    return 0.5 - 0.5 * torch.cos(math.pi * t)

def case(wl=0.55, a=0.4, edge=0.08, fz=8.0, z2=6.0, tilt=0.0, pitch=2e-3, fine=None, amp=None, carry=None, verbose=True):
    k = 2 * math.pi / (wl * 1e-3)
    fx, fy = fz * math.tan(math.radians(tilt)), 0.01
    f = (fx, fy, fz)
    r0 = math.sqrt(fx*fx+fy*fy+fz*fz)
    car = (fx / r0, fy / r0)
    fine = fine or pitch
    h = a + 0.05 * a / 0.4 + edge
    n1 = int(2 * h / fine) + 1
    g1 = Grid((-h, -h), fine, (n1, n1))
    x, y = axes(g1)
    env = disc(x, y, a, edge) if amp is None else disc(x, y, a, edge) * amp(x, y)
    u1 = env * torch.polar(torch.ones((), dtype=torch.float64),
                           -k * (torch.sqrt((x - fx) ** 2 + (y - fy) ** 2 + fz ** 2) + car[0] * x + car[1] * y))
    mag = (fz - z2) / fz
    w = (a+edge) * mag + 0.25 * (a * mag)
    no = int(2 * w / pitch) + 1
    out = Grid((-w + fx * (1 - mag), -w + fy * (1 - mag)), pitch, (no, no))
    plain = propagate_window(Field(u1.to(torch.complex128), g1, wl, 1.0, car), out, z2).envelope
    lat = ep._scaled_lattice(out, f, (0.0, z2), None)
    nc = int(2 * h / lat.pitch) + 1
    coarse = Grid((-h, -h), lat.pitch, (nc, nc))
    xc, yc = axes(coarse)
    a1 = (disc(xc, yc, a, edge) if amp is None else disc(xc, yc, a, edge) * amp(xc, yc)).to(torch.complex128)
    fn = carry or ep.scaled_carry
    s = fn(Field(a1, coarse, wl, 1.0, (0.0, 0.0)), out, f, (0.0, z2), car)
    ph = (s.conj() * plain).sum()
    s = s * (ph / ph.abs())
    err = float(torch.linalg.vector_norm(s - plain) / torch.linalg.vector_norm(plain))
    pw = float((s.abs()**2).sum() / (plain.abs()**2).sum())
    # PSF: propagate both to the focal plane (crop)
    res = dict(err=err, pw=pw)
    return res, (plain, s, out, f, car, wl, z2)

def psf_l1(plain, s, out, f, car, wl, z2, crop_px=64, cpitch=None):
    fx, fy, fz = f
    rem = fz - z2
    cpitch = cpitch or out.pitch[0]
    c = Grid((fx - crop_px/2*cpitch, fy - crop_px/2*cpitch), cpitch, (crop_px, crop_px))
    # propagate envelope fields to the focal plane
    pa = propagate_window(Field(plain, out, wl, 1.0, car), c, rem).envelope
    pb = propagate_window(Field(s, out, wl, 1.0, car), c, rem).envelope
    ia, ib = pa.abs()**2, pb.abs()**2
    return float((ia - ib).abs().sum() / ia.sum())
