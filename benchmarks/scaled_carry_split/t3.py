from off import *
from pou import pou_carry
import functools
A = torch.load(os.environ.get("RUNS", "runs") + "/planar_plainA.pt")["A"]
ph = (fin.envelope.conj()*A).sum(); A = A*(ph.conj()/ph.abs())
fin2 = Field(A, fin.grid, fin.wavelength, fin.n, (0.0, 0.0))
for P in (1, 3):
    u = pou_carry(fin2, out, si["sphere"], si["planes"], si["carrier"], P=P)
    print("pou", P, "plainA proxy L1 vs plain", l1(psf(u), Pa), flush=True)
ep.SCALED_CARRY_CHART = True
u = ep.scaled_carry(fin2, out, si["sphere"], si["planes"], si["carrier"])
print("chart plainA", l1(psf(u), Pa))
